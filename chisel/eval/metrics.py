"""The paper's correspondence metric: the ROI box, depth renders at the evaluation
poses, and the per-pixel distance between ground-truth and method points inside the box
(docs/evaluation.md)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.geometry import Camera, check_rigid, transform_points
from chisel.core.raycast import MeshRaycaster


@dataclass(frozen=True)
class RoiBox:
    """Axis-aligned box in world mm; a point on the boundary counts as inside."""

    min_mm: np.ndarray
    """(3,) float64 lower corner (xmin, ymin, zmin), world mm."""
    max_mm: np.ndarray
    """(3,) float64 upper corner (xmax, ymax, zmax), world mm."""

    def __post_init__(self) -> None:
        lo = np.asarray(self.min_mm, dtype=np.float64).ravel()
        hi = np.asarray(self.max_mm, dtype=np.float64).ravel()
        if lo.shape != (3,) or hi.shape != (3,):
            raise InvalidInputError(
                "roi_box_mm", f"expected 3 + 3 corner coordinates, got {lo.shape} and {hi.shape}"
            )
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise InvalidInputError("roi_box_mm", "corners contain NaN/inf")
        if not np.all(hi > lo):
            raise InvalidInputError(
                "roi_box_mm",
                f"max corner {hi.tolist()} must exceed min corner {lo.tolist()} on every axis",
            )
        object.__setattr__(self, "min_mm", lo)
        object.__setattr__(self, "max_mm", hi)

    @classmethod
    def from_values(cls, values: Sequence[float], source: str = "roi_box_mm") -> RoiBox:
        """Box from six numbers ``xmin, ymin, zmin, xmax, ymax, zmax`` (mm)."""
        arr = np.asarray(values, dtype=np.float64).ravel()
        if arr.shape != (6,):
            raise InvalidInputError(
                source, f"expected 6 numbers xmin,ymin,zmin,xmax,ymax,zmax, got {arr.size}"
            )
        try:
            return cls(arr[:3], arr[3:])
        except InvalidInputError as exc:
            raise InvalidInputError(source, exc.problem) from None

    @classmethod
    def parse(cls, text: str, source: str = "--roi") -> RoiBox:
        """Box from the string ``"xmin,ymin,zmin,xmax,ymax,zmax"`` (mm)."""
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            raise InvalidInputError(
                source,
                f"expected 6 comma-separated numbers xmin,ymin,zmin,xmax,ymax,zmax, got {text!r}",
            ) from None
        return cls.from_values(values, source)

    def to_list(self) -> list[float]:
        """``[xmin, ymin, zmin, xmax, ymax, zmax]`` in mm."""
        return [float(v) for v in np.concatenate([self.min_mm, self.max_mm])]

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        """Which points lie inside the box (boundary included); NaN points are outside.

        points_mm : (..., 3) float, world mm. Returns (...,) bool.
        """
        p = np.asarray(points_mm, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return np.all((p >= self.min_mm) & (p <= self.max_mm), axis=-1)


# --------------------------------------------------------------------------------------
# Rendering and the paper's correspondence error


def _check_mesh(mesh: trimesh.Trimesh, source: str) -> trimesh.Trimesh:
    if not isinstance(mesh, trimesh.Trimesh):
        raise InvalidInputError(source, f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise InvalidInputError(source, "mesh is empty (no faces)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise InvalidInputError(source, "mesh vertices contain NaN/inf")
    return mesh


def _check_poses(poses: np.ndarray, source: str = "poses") -> np.ndarray:
    arr = check_rigid(poses, source)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or len(arr) == 0:
        raise InvalidInputError(source, f"expected (N>0, 4, 4) poses, got shape {arr.shape}")
    return arr


def render_depths(mesh: trimesh.Trimesh, camera: Camera, poses: np.ndarray) -> np.ndarray:
    """z-depth of ``mesh`` at every pose.

    mesh : triangle mesh in world mm.
    poses : (N, 4, 4) float64 ``T_world_from_cam``.
    Returns (N, H, W) float32 z-depth in mm, NaN where the ray misses.
    """
    _check_mesh(mesh, "mesh")
    poses = _check_poses(poses)
    rc = MeshRaycaster.from_trimesh(mesh)
    return np.stack([rc.render_depth(camera, T) for T in poses])


def _check_depth_stack(depths: np.ndarray, camera: Camera, n: int, source: str) -> np.ndarray:
    d = np.asarray(depths, dtype=np.float32)
    if d.shape != (n, *camera.shape):
        raise InvalidInputError(
            source, f"expected depth of shape {(n, *camera.shape)} (N, H, W), got {d.shape}"
        )
    return d


@dataclass(frozen=True)
class CorrespondenceError:
    """The paper's metric for one method at one step."""

    mean_mm: float
    """Mean distance between corresponding (same-pixel) world points, mm."""
    std_mm: float
    """Population standard deviation (``ddof=0``) of those distances, mm."""
    median_mm: float
    """Median of those distances, mm."""
    n_points: int
    """Counted pixels: GT point inside the box and the method has a surface there."""
    n_gt_in_box: int
    """Pixels whose GT point lies inside the box (over all poses)."""

    @property
    def missing_fraction(self) -> float:
        """Fraction of GT-in-box pixels where the method's render has no surface."""
        return 1.0 - self.n_points / self.n_gt_in_box


def gt_points_in_box(
    gt_depths_mm: np.ndarray,
    camera: Camera,
    poses: np.ndarray,
    box: RoiBox,
    pixel_mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project GT depth to world points and select the pixels whose point is in the box.

    gt_depths_mm : (N, H, W) float32 z-depth, mm, NaN = no surface.
    poses : (N, 4, 4) float64 ``T_world_from_cam``.
    pixel_mask : (H, W) bool or None; False pixels never count (e.g. outside the field stop).
    Returns ``(points_world_mm, in_box)``: (N, H, W, 3) float64 mm (NaN where invalid) and
    (N, H, W) bool.
    """
    poses = _check_poses(poses)
    gt = _check_depth_stack(gt_depths_mm, camera, len(poses), "gt_depths_mm")
    if pixel_mask is not None:
        pixel_mask = np.asarray(pixel_mask, dtype=bool)
        camera.check_image(pixel_mask, "pixel_mask")
    points = np.stack(
        [transform_points(T, camera.backproject(d)) for T, d in zip(poses, gt, strict=True)]
    )
    in_box = box.contains(points)
    if pixel_mask is not None:
        in_box &= pixel_mask[None]
    return points, in_box


def correspondence_error(
    gt_depths_mm: np.ndarray,
    method_depths_mm: np.ndarray,
    camera: Camera,
    poses: np.ndarray,
    box: RoiBox,
    pixel_mask: np.ndarray | None = None,
    source: str = "method",
) -> CorrespondenceError:
    """The paper's error: distance between same-pixel world points of GT and method renders.

    gt_depths_mm, method_depths_mm : (N, H, W) float32 z-depth, mm, NaN = no surface.
    poses : (N, 4, 4) float64 ``T_world_from_cam`` (the evaluation poses).
    pixel_mask : (H, W) bool or None; False pixels never count.
    A pixel counts when its GT point is inside ``box`` and the method depth is valid.
    Raises :class:`EmptyResultError` when no GT point is in the box (the poses do not view
    it) or when the method has no surface at any such pixel.
    """
    poses = _check_poses(poses)
    gt_points, in_box = gt_points_in_box(gt_depths_mm, camera, poses, box, pixel_mask)
    method = _check_depth_stack(method_depths_mm, camera, len(poses), f"{source} depths")
    n_gt = int(in_box.sum())
    if n_gt == 0:
        raise EmptyResultError(
            "no ground-truth surface point inside the ROI box at any evaluation pose: the "
            f"poses do not view the box {box.to_list()}"
        )
    counted = in_box & np.isfinite(method)
    n = int(counted.sum())
    if n == 0:
        raise EmptyResultError(
            f"{source}: no surface at any of the {n_gt} pixels whose ground-truth point is "
            "inside the ROI box"
        )
    method_points = np.stack(
        [transform_points(T, camera.backproject(d)) for T, d in zip(poses, method, strict=True)]
    )
    dist = np.linalg.norm(gt_points[counted] - method_points[counted], axis=-1)
    return CorrespondenceError(
        mean_mm=float(dist.mean()),
        std_mm=float(dist.std()),
        median_mm=float(np.median(dist)),
        n_points=n,
        n_gt_in_box=n_gt,
    )


# --------------------------------------------------------------------------------------
# Surface metrics inside the box
