"""Rigid transforms and the pinhole camera: the geometry every stage shares.

Conventions (see docs/conventions.md):
- millimetres; transforms are 4x4 float64 named ``T_<dst>_from_<src>`` and compose as
  ``T_a_from_c = T_a_from_b @ T_b_from_c``; camera poses are ``T_world_from_cam``;
- OpenCV camera axes: +x right, +y down, +z forward (optical axis);
- pixel centres at integer coordinates: pixel (row v, column u) is centred at (u, v);
- depth is z-depth along the optical axis, float32 mm, NaN = invalid in memory.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from typing import SupportsFloat, SupportsInt

import numpy as np
from numpy.typing import ArrayLike

from chisel.core.errors import CameraError, PoseError

RIGID_TOL = 1e-5
"""Tolerance on ``R^T R - I`` and ``det(R) - 1`` for a pose to count as rigid."""


def vec3(a: Iterable[SupportsFloat]) -> tuple[float, float, float]:
    """A 3-vector (array, sequence) as a tuple of three Python floats."""
    x, y, z = (float(v) for v in a)
    return x, y, z


def ivec3(a: Iterable[SupportsInt]) -> tuple[int, int, int]:
    """A 3-vector of indices or counts as a tuple of three Python ints."""
    i, j, k = (int(v) for v in a)
    return i, j, k


def check_rigid(T: np.ndarray, source: str = "pose") -> np.ndarray:
    """Return ``T`` as a (4, 4) float64 array, or raise :class:`PoseError`.

    T : (4, 4) or (N, 4, 4) array-like, rigid transform(s), translation in mm.
    """
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape[-2:] != (4, 4):
        raise PoseError(source, f"expected a 4x4 transform, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr.reshape(-1, 16)).all(axis=1)).ravel()
        raise PoseError(source, f"non-finite values (NaN/inf) in pose(s) {bad[:10].tolist()}")
    batch = arr.reshape(-1, 4, 4)
    bottom_err = np.abs(batch[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    R = batch[:, :3, :3]
    ortho_err = np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max(axis=(1, 2))
    det_err = np.abs(np.linalg.det(R) - 1.0)
    bad = np.flatnonzero((bottom_err > RIGID_TOL) | (ortho_err > RIGID_TOL) | (det_err > RIGID_TOL))
    if bad.size:
        i = int(bad[0])
        raise PoseError(
            source,
            f"pose {i} is not rigid (|R^T R - I| = {ortho_err[i]:.2e}, det R = "
            f"{np.linalg.det(R[i]):.6f}, bottom row {batch[i, 3].tolist()}); "
            f"{bad.size} non-rigid pose(s) in total",
        )
    return arr


def invert_rigid(T_b_from_a: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s): returns ``T_a_from_b``. Shape (..., 4, 4) float64."""
    T = np.asarray(T_b_from_a, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_dst_from_src: np.ndarray, points_src: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points.

    points_src : (..., 3) float, mm, in frame ``src``. Returns (..., 3) float64 in ``dst``.
    """
    T = np.asarray(T_dst_from_src, dtype=np.float64)
    p = np.asarray(points_src, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def make_transform(R: ArrayLike, t_mm: ArrayLike) -> np.ndarray:
    """4x4 transform from a (3, 3) rotation and a (3,) translation in mm."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t_mm
    return T


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a (3, 3) rotation, in degrees (0..180)."""
    c = (np.trace(np.asarray(R)[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def look_at(eye_mm: np.ndarray, target_mm: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_world_from_cam`` of a camera at ``eye_mm`` looking at ``target_mm``.

    The camera's +z points at the target and its -y (image up) is as close to ``up`` as
    possible (OpenCV axes). Raises ``ValueError`` when eye == target or up is parallel.
    """
    eye = np.asarray(eye_mm, dtype=np.float64)
    z = np.asarray(target_mm, dtype=np.float64) - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z /= n
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise ValueError("look_at: up vector is parallel to the viewing direction")
    x /= nx
    y = np.cross(z, x)
    return make_transform(np.stack([x, y, z], axis=1), eye)


def distort_normalized(x, y, k1, k2, p1, p2, k3):  # noqa: ANN001, ANN201 - arrays or numba scalars
    """OpenCV's lens model on normalised coordinates: undistorted (x, y) -> distorted.

    The one home of the polynomial: :meth:`Camera.project` calls it on arrays, and the
    numba kernels (fusion, carving, change) compile it inline (``chisel.fusion.distort``).
    """
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with OpenCV distortion, in pixels.

    The pinhole model with ``K`` describes *undistorted* images; ``dist`` describes how
    the physical lens distorts them (OpenCV ``k1, k2, p1, p2, k3``). Images stored in a
    sequence are raw (distorted) unless the sequence says ``undistorted``; depth stored
    in a sequence is always per-pixel on the same grid as its RGB.
    """

    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    K: np.ndarray
    """(3, 3) float64 intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels."""
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    """(5,) float64 OpenCV distortion k1, k2, p1, p2, k3; zeros = no distortion."""

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).ravel()
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CameraError(
                "camera", f"image size must be positive, got {self.width}x{self.height}"
            )
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraError("camera", f"K must be a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise CameraError("camera", f"K is not a pinhole intrinsic matrix: {K.tolist()}")
        if dist.shape != (5,) or not np.all(np.isfinite(dist)):
            raise CameraError(
                "camera", f"dist must be 5 finite OpenCV coefficients, got {dist.tolist()}"
            )

    @classmethod
    def from_fov(
        cls,
        width: int,
        height: int,
        fov_deg: float,
        principal_offset_px: tuple[float, float] = (0.0, 0.0),
        dist: np.ndarray | None = None,
    ) -> Camera:
        """Square-pixel camera whose *diagonal* field of view is ``fov_deg``.

        Endoscope FOV is quoted across the circular image, i.e. the diagonal-ish extent;
        we use the image diagonal. ``principal_offset_px`` shifts (cx, cy) from the centre.
        """
        if not 1.0 < fov_deg < 179.0:
            raise CameraError("fov_deg", f"must be in (1, 179) degrees, got {fov_deg}")
        diag_px = float(np.hypot(width, height))
        f = (diag_px / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
        cx = (width - 1) / 2.0 + principal_offset_px[0]
        cy = (height - 1) / 2.0 + principal_offset_px[1]
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        return cls(width, height, K, np.zeros(5) if dist is None else np.asarray(dist))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width), the shape of a depth map."""
        return (int(self.height), int(self.width))

    @property
    def principal_point_in_image(self) -> bool:
        """Whether (cx, cy) lies on the image, [-0.5, W - 0.5] x [-0.5, H - 0.5] (pixel
        centres sit at integer coordinates); outside, K was made for another image size."""
        return bool(-0.5 <= self.cx <= self.width - 0.5 and -0.5 <= self.cy <= self.height - 0.5)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def check_image(self, image: np.ndarray, source: str) -> None:
        """Raise :class:`CameraError` if ``image`` (H, W[, C]) is not this camera's size."""
        if tuple(image.shape[:2]) != self.shape:
            raise CameraError(
                source,
                f"image is {image.shape[1]}x{image.shape[0]} (WxH) but the camera is "
                f"{self.width}x{self.height}",
            )

    def pixel_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) pixel-centre coordinates, each (H, W) float64."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return u, v

    @cached_property
    def _rays_cam(self) -> np.ndarray:
        u, v = self.pixel_grid()
        x: np.ndarray
        y: np.ndarray
        if not self.has_distortion:
            x = (u - self.cx) / self.fx
            y = (v - self.cy) / self.fy
        else:
            # The image is distorted: undo the lens model per pixel (iteratively, to ~1e-9).
            # Imported here: cv2 takes ~1 s to import, and the phantom generator, which
            # imports this module for its rigid geometry only, runs once per dataset seed.
            import cv2  # noqa: PLC0415

            pts = np.stack([u.ravel(), v.ravel()], axis=-1)[:, None, :]
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            und = cv2.undistortPoints(pts, self.K, self.dist, None, None, None, criteria)
            x = und[:, 0, 0].reshape(u.shape)
            y = und[:, 0, 1].reshape(u.shape)
        rays = np.stack([x, y, np.ones_like(x)], axis=-1)
        rays.setflags(write=False)
        return rays

    def rays_cam(self) -> np.ndarray:
        """(H, W, 3) float64 rays with z = 1 through every pixel centre of the raw image.

        With distortion, each ray is the undistorted direction whose distorted projection
        is the pixel centre; so ``backproject`` and ``project`` are exact inverses.
        """
        return self._rays_cam

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points into the raw (distorted) image.

        points_cam : (..., 3) mm in the camera frame.
        Returns (uv, z_mm): uv (..., 2) float64 pixels, z_mm (...,) float64. Points
        behind the camera give meaningless uv; callers mask on ``z_mm > 0``.
        """
        p = np.asarray(points_cam, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = p[..., 0] / z
            y = p[..., 1] / z
        if self.has_distortion:
            k1, k2, p1, p2, k3 = self.dist
            x, y = distort_normalized(x, y, k1, k2, p1, p2, k3)
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1), z

    def backproject(self, depth_mm: np.ndarray) -> np.ndarray:
        """Back-project a z-depth map of the raw image to camera-frame points.

        depth_mm : (H, W) float32, z-depth in mm, NaN = invalid.
        Returns (H, W, 3) float64 mm, NaN where the depth is invalid.
        """
        self.check_image(depth_mm, "depth_mm")
        return self.rays_cam() * np.asarray(depth_mm, dtype=np.float64)[..., None]

    def to_dict(self) -> dict:
        return {
            "width": int(self.width),
            "height": int(self.height),
            "K": np.asarray(self.K).tolist(),
            "dist": np.asarray(self.dist).tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> Camera:
        try:
            return cls(
                int(d["width"]),
                int(d["height"]),
                np.asarray(d["K"], float),
                np.asarray(d.get("dist", [0.0] * 5), float),
            )
        except KeyError as exc:
            raise CameraError(source, f"missing camera field {exc}") from None
        except CameraError as exc:
            raise CameraError(source, exc.problem) from None
