"""The one place where Mitsuba's camera conventions meet ours (docs/conventions.md).

Ours: OpenCV camera axes (+x right, +y down, +z forward), pinhole ``K`` plus OpenCV
distortion, pixel centres at integer coordinates, z-depth in mm with NaN = invalid.

Mitsuba's ``perspective`` sensor: camera frame +x left, +y up, +z forward; square
pixels only; film coordinate ``s in [0, 1]^2`` across the image, pixel ``(u, v)``
centred at ``s = ((u + 0.5) / W, (v + 0.5) / H)``; its rays start on the near clip
plane, so the ``depth`` AOV is the ray length from the near plane (0 on a miss).

Rendering with distortion: Mitsuba renders an undistorted square-pixel pinhole image
(the :class:`RenderGrid`, wide enough to cover every ray of the distorted image), which
is remapped onto the raw (distorted) pixel grid with ``cv2.remap``: bilinear for colour,
nearest neighbour for depth. Ground-truth depth on the JIT variants does not go through
this remap: it is the exact ray length of :meth:`chisel.core.geometry.Camera.rays_cam`'s ray
through each raw pixel centre, computed in the kernel (:func:`chisel.core.raycast.jit_z_depth`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from chisel.core.errors import CameraError
from chisel.core.geometry import Camera, check_rigid

T_CV_FROM_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])
"""(4, 4) maps Mitsuba camera-frame points (+x left, +y up) to OpenCV camera-frame points."""


def mitsuba_to_world(T_world_from_cam: np.ndarray) -> np.ndarray:
    """Mitsuba sensor ``to_world`` for an OpenCV pose.

    T_world_from_cam : (4, 4) float64, OpenCV camera axes, mm.
    Returns (4, 4) float64 ``T_world_from_mitsubacam``.
    """
    T = check_rigid(T_world_from_cam, "T_world_from_cam")
    return T @ T_CV_FROM_MITSUBA


def opencv_from_mitsuba_to_world(T_world_from_mitsubacam: np.ndarray) -> np.ndarray:
    """Inverse of :func:`mitsuba_to_world`: (4, 4) Mitsuba ``to_world`` -> ``T_world_from_cam``."""
    return np.asarray(T_world_from_mitsubacam, dtype=np.float64) @ T_CV_FROM_MITSUBA


@dataclass(frozen=True)
class RenderGrid:
    """The undistorted square-pixel pinhole image Mitsuba renders for a :class:`Camera`.

    ``map_x``/``map_y`` give, for every raw camera pixel, where its ray lands on this grid
    (pixels); both None when the grid *is* the camera (no distortion, fx == fy).
    """

    width: int
    """Grid width, pixels."""
    height: int
    """Grid height, pixels."""
    f_px: float
    """Focal length of the grid, pixels (square pixels)."""
    cx: float
    """Principal point x of the grid, pixels."""
    cy: float
    """Principal point y of the grid, pixels."""
    map_x: np.ndarray | None = None
    """(H, W) float32 grid x coordinate of each raw pixel's ray; None = identity."""
    map_y: np.ndarray | None = None
    """(H, W) float32 grid y coordinate of each raw pixel's ray; None = identity."""

    @property
    def identity(self) -> bool:
        return self.map_x is None

    def x_fov_deg(self) -> float:
        """Mitsuba's ``fov`` with ``fov_axis = x``, degrees."""
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.f_px)))

    def principal_point_offset(self) -> tuple[float, float]:
        """Mitsuba's ``principal_point_offset_x/y`` (fractions of the film size).

        Mitsuba places pixel ``u`` at ``x_cv / z = tan(fov/2) (2 ((u + 0.5) / W + off_x) - 1)``,
        so ``cx = (W - 1) / 2 - off_x W`` (and likewise for y, with ``fy = f``).
        """
        return ((self.width - 1) / 2.0 - self.cx) / self.width, (
            (self.height - 1) / 2.0 - self.cy
        ) / self.height

    def rays_cam(self) -> np.ndarray:
        """(h, w, 3) float64 rays (z = 1, OpenCV axes) through this grid's pixel centres."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        x = (u - self.cx) / self.f_px
        y = (v - self.cy) / self.f_px
        return np.stack([x, y, np.ones_like(x)], axis=-1)


def render_grid(
    camera: Camera,
    max_upscale: float = 3.0,
    margin_px: float = 2.0,
    used: np.ndarray | None = None,
) -> RenderGrid:
    """The Mitsuba render grid for ``camera`` (see :class:`RenderGrid`).

    used : optional (H, W) bool, the raw pixels whose colour matters (the field stop); the
    grid then only covers their rays (fewer samples to render), and the other pixels map
    outside it (black after the remap).

    Raises :class:`CameraError` if the distortion needs a grid larger than ``max_upscale``
    times the camera's pixel count (a distortion model that folds over or is extreme).
    """
    if not camera.has_distortion and math.isclose(camera.fx, camera.fy, rel_tol=1e-12):
        return RenderGrid(camera.width, camera.height, camera.fx, camera.cx, camera.cy)
    rays = camera.rays_cam()
    x, y = rays[..., 0], rays[..., 1]
    # The distortion must be invertible over the image: a model that folds over (e.g. a
    # strong k1 < 0 reaching past its turning radius) has pixels without a unique ray.
    uv, _ = camera.project(rays)
    u, v = camera.pixel_grid()
    err = float(np.max(np.hypot(uv[..., 0] - u, uv[..., 1] - v)))
    r_max = float(np.max(np.hypot(x, y)))
    r = np.linspace(0.0, r_max, 256)
    k1, k2, _, _, k3 = camera.dist
    slope = 1.0 + 3 * k1 * r**2 + 5 * k2 * r**4 + 7 * k3 * r**6
    if err > 1e-3 or slope.min() <= 0:
        raise CameraError(
            "camera.dist",
            f"the distortion {camera.dist.tolist()} cannot be inverted over the "
            f"{camera.width}x{camera.height} image (it folds over: radial slope "
            f"{slope.min():.3f}, re-projection error {err:.3g} px); check the coefficients",
        )
    # Keep the centre's resolution: the raw image is sharpest there.
    f = max(camera.fx, camera.fy)
    sel = np.ones(camera.shape, dtype=bool) if used is None else np.asarray(used, dtype=bool)
    if sel.shape != camera.shape or not sel.any():
        raise CameraError(
            "used", f"expected a non-empty {camera.shape} pixel mask, got {sel.shape}"
        )
    xmin, xmax = float(x[sel].min()), float(x[sel].max())
    ymin, ymax = float(y[sel].min()), float(y[sel].max())
    width = int(math.ceil(f * (xmax - xmin) + 2 * margin_px)) + 1
    height = int(math.ceil(f * (ymax - ymin) + 2 * margin_px)) + 1
    if width * height > max_upscale * camera.width * camera.height:
        raise CameraError(
            "camera.dist",
            f"the distortion {camera.dist.tolist()} spreads the {camera.width}x{camera.height} "
            f"image over an undistorted grid of {width}x{height} pixels, more than "
            f"{max_upscale:g} times the image: refusing (check the coefficients' signs/scale)",
        )
    cx = margin_px - f * xmin
    cy = margin_px - f * ymin
    map_x = (f * x + cx).astype(np.float32)
    map_y = (f * y + cy).astype(np.float32)
    return RenderGrid(width, height, f, cx, cy, map_x, map_y)


def remap_to_camera(image: np.ndarray, grid: RenderGrid, nearest: bool) -> np.ndarray:
    """Resample an image rendered on ``grid`` onto the raw camera pixel grid.

    image : (h, w[, C]) float32 on the grid. Returns (H, W[, C]) float32. ``nearest``
    for depth and masks (never blend a foreground and a background depth).
    """
    if grid.identity:
        return image
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    assert grid.map_x is not None and grid.map_y is not None  # not identity: both maps set
    out = cv2.remap(
        np.ascontiguousarray(image, dtype=np.float32),
        grid.map_x,
        grid.map_y,
        interp,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    return out


def z_depth_from_mitsuba_depth(
    depth_aov: np.ndarray, grid: RenderGrid, near_clip_mm: float
) -> np.ndarray:
    """z-depth from Mitsuba's ``depth`` AOV rendered on ``grid`` (pixel centres, 1 spp).

    depth_aov : (h, w) float, ray length from the near clip plane in mm, 0 on a miss.
    Mitsuba's ray through a pixel starts at ``near_clip / d_z`` along the unit direction
    ``d``, so the z-depth is ``(t + near_clip / d_z) d_z = t d_z + near_clip``.
    Returns (h, w) float32 z-depth in mm on the grid, NaN on a miss.
    """
    rays = grid.rays_cam()
    d_z = 1.0 / np.linalg.norm(rays, axis=-1)
    t = np.asarray(depth_aov, dtype=np.float64)
    z = t * d_z + near_clip_mm
    return np.where(t > 0, z, np.nan).astype(np.float32)
