"""Evaluation of updated models against ground truth (the paper's Table 1, and more).

Protocol (docs/evaluation.md has the full definition):

- **Correspondence error** (the paper's metric). At fixed evaluation poses that view the
  ROI box, render z-depth from the ground-truth mesh of the step and from a method's mesh,
  back-project both to world points and take, pixel by pixel, the distance between the two
  points. A pixel counts when its ground-truth point lies inside the box and the method's
  render has a surface there; the mean ± std (population, ``ddof=0``) over all counted
  pixels of all poses is reported in mm, with the count and the fraction of ground-truth
  in-box pixels where the method has no surface (``missing_fraction``).
- **Surface metrics** inside the box: points sampled uniformly by area (seeded) on each
  mesh's part inside the box (rejection sampling); exact point-to-triangle distances to the *whole* other
  mesh (Open3D ``RaycastingScene.compute_distance``). Accuracy = predicted -> GT,
  completeness = GT -> predicted (mean and 95th percentile), HD95 = max of the two 95th
  percentiles, chamfer = (accuracy + completeness) / 2, F-score at 1 mm from precision
  (fraction of predicted samples closer than 1 mm to GT) and recall (GT samples closer than
  1 mm to the prediction).
- **Change masks**: per-frame predicted change masks against the true change, i.e. the
  ground-truth depth of step t+1 exceeding that of step t by more than 1 mm at the same
  pose (or the surface vanishing along the ray); precision and recall over all pixels.

Pure functions work on arrays and ``trimesh.Trimesh`` objects; :func:`evaluate_step` is the
one file-level wrapper, and the table writers go through :mod:`chisel.atomic`.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import jsonschema
import numpy as np
import open3d as o3d
import trimesh

from chisel.atomic import atomic_write_text
from chisel.errors import EmptyResultError, InvalidInputError
from chisel.geometry import Camera, check_rigid, transform_points
from chisel.raycast import MeshRaycaster
from chisel.sequence import Sequence as SequenceFolder

log = logging.getLogger(__name__)

METHODS: tuple[str, ...] = ("no_update", "updated", "depth_ablation", "registration_ablation")
"""The paper's methods, in table order. Other method names are allowed and sort after these."""

FSCORE_THRESHOLD_MM = 1.0
"""Distance threshold of the F-score (and its precision/recall) in the tables, mm."""

CHANGE_THRESHOLD_MM = 1.0
"""A pixel's true change: GT depth grows by more than this between steps (the paper's 1 mm)."""

METRICS_FORMAT = "endoscopic-chisel/metrics"
STEP_METRICS_FORMAT = "endoscopic-chisel/step-metrics"
SEED_METRICS_FORMAT = "endoscopic-chisel/metrics-seeds"
METRICS_VERSION = 1

METRIC_KEYS: tuple[str, ...] = (
    "mean_mm",
    "std_mm",
    "median_mm",
    "n_points",
    "n_gt_in_box",
    "missing_fraction",
    "accuracy_mm",
    "completeness_mm",
    "accuracy_hd95_mm",
    "completeness_hd95_mm",
    "hd95_mm",
    "chamfer_mm",
    "precision_1mm",
    "recall_1mm",
    "fscore_1mm",
    "mask_precision",
    "mask_recall",
)
"""Every key of a method's cell in ``metrics.json``; a value is a number or null."""

_NUM_OR_NULL = {"type": ["number", "null"]}
_METHOD_CELL_SCHEMA = {
    "type": "object",
    "required": list(METRIC_KEYS),
    "properties": {
        **{k: _NUM_OR_NULL for k in METRIC_KEYS},
        "n_points": {"type": "integer", "minimum": 1},
        "n_gt_in_box": {"type": "integer", "minimum": 1},
        "mean_mm": {"type": "number", "minimum": 0},
        "std_mm": {"type": "number", "minimum": 0},
    },
}
_STEP_SCHEMA = {
    "type": "object",
    "required": ["step", "label", "methods"],
    "properties": {
        "step": {"type": "integer", "minimum": 0},
        "label": {"type": "string"},
        "methods": {
            "type": "object",
            "minProperties": 1,
            "additionalProperties": _METHOD_CELL_SCHEMA,
        },
    },
}
METRICS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "metrics.json: evaluation of one experiment (rows = steps, columns = methods)",
    "type": "object",
    "required": ["format", "version", "experiment", "steps"],
    "properties": {
        "format": {"const": METRICS_FORMAT},
        "version": {"const": METRICS_VERSION},
        "experiment": {"type": "string"},
        "protocol": {"type": "object"},
        "steps": {"type": "array", "minItems": 1, "items": _STEP_SCHEMA},
    },
}
"""JSON schema of ``metrics.json`` (validated on write and on read)."""

STEP_METRICS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "step_metrics.json: evaluation of one surgical step",
    "type": "object",
    "required": ["format", "version", "step", "label", "methods"],
    "properties": {
        "format": {"const": STEP_METRICS_FORMAT},
        "version": {"const": METRICS_VERSION},
        **_STEP_SCHEMA["properties"],
        "protocol": {"type": "object"},
    },
}
"""JSON schema of one step's metrics (what ``chisel evaluate`` writes)."""


# --------------------------------------------------------------------------------------
# The ROI box


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


@dataclass(frozen=True)
class SurfaceMetricConfig:
    """How surfaces are sampled for the accuracy / completeness / F-score metrics."""

    n_samples: int = 50_000
    """Points sampled uniformly by area on each mesh's part inside the box (>= 100)."""
    seed: int = 0
    """Seed of the area-uniform sampling (same seed, same samples)."""

    def __post_init__(self) -> None:
        if isinstance(self.n_samples, bool) or int(self.n_samples) < 100:
            raise InvalidInputError("n_samples", f"must be an integer >= 100, got {self.n_samples}")


@dataclass(frozen=True)
class SurfaceMetrics:
    """Surface distances between a predicted and a GT mesh inside the ROI box, mm."""

    accuracy_mm: float
    """Mean distance from predicted samples (in the box) to the GT surface."""
    completeness_mm: float
    """Mean distance from GT samples (in the box) to the predicted surface."""
    accuracy_hd95_mm: float
    """95th percentile of the predicted -> GT distances."""
    completeness_hd95_mm: float
    """95th percentile of the GT -> predicted distances."""
    hd95_mm: float
    """Symmetric 95 % Hausdorff distance: max of the two 95th percentiles."""
    chamfer_mm: float
    """(accuracy + completeness) / 2."""
    precision: float
    """Fraction of predicted samples closer than the threshold to GT."""
    recall: float
    """Fraction of GT samples closer than the threshold to the prediction."""
    fscore: float
    """2 P R / (P + R); 0 when both are 0."""
    threshold_mm: float
    """The F-score threshold, mm."""


def _sample_triangles(
    triangles: np.ndarray, areas: np.ndarray, n: int, rng: np.random.Generator
) -> np.ndarray:
    """``n`` points uniform by area on (F, 3, 3) triangles; returns (n, 3) float64."""
    face = rng.choice(len(triangles), size=n, p=areas / areas.sum())
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    t = triangles[face]
    # Uniform barycentric coordinates (Osada et al. 2002): (1 - sqrt r1, sqrt r1 (1 - r2), sqrt r1 r2).
    return (
        (1.0 - r1)[:, None] * t[:, 0]
        + (r1 * (1.0 - r2))[:, None] * t[:, 1]
        + (r1 * r2)[:, None] * t[:, 2]
    )


_MAX_SAMPLE_BATCH = 2_000_000
_MAX_SAMPLE_ROUNDS = 20


def sample_surface_in_box(
    mesh: trimesh.Trimesh, box: RoiBox, n_samples: int, seed: int, source: str = "mesh"
) -> np.ndarray:
    """Points uniformly distributed by area on the part of ``mesh`` inside ``box``.

    Samples the triangles whose bounding box meets the box uniformly by area and keeps the
    points inside (rejection), which is uniform by area on the clipped surface; repeats until
    ``n_samples`` are kept. Deterministic for a given ``seed``.
    Returns (n_samples, 3) float64 world mm. Raises :class:`EmptyResultError` if the mesh
    has no (samplable) area inside the box.
    """
    _check_mesh(mesh, source)
    n_samples = int(n_samples)
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    cand = np.all((tri.max(axis=1) >= box.min_mm) & (tri.min(axis=1) <= box.max_mm), axis=1)
    tri = tri[cand]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if len(tri) == 0 or areas.sum() <= 0.0:
        raise EmptyResultError(f"{source}: no surface inside the ROI box {box.to_list()}")
    rng = np.random.default_rng(seed)
    kept: list[np.ndarray] = []
    n_kept = n_drawn = 0
    batch = n_samples
    for _ in range(_MAX_SAMPLE_ROUNDS):
        pts = _sample_triangles(tri, areas, batch, rng)
        inside = pts[box.contains(pts)]
        kept.append(inside)
        n_kept += len(inside)
        n_drawn += batch
        if n_kept >= n_samples:
            return np.concatenate(kept)[:n_samples]
        accept = max(n_kept / n_drawn, 1e-3)
        batch = int(min((n_samples - n_kept) / accept * 1.2 + 100, _MAX_SAMPLE_BATCH))
    raise EmptyResultError(
        f"{source}: only {n_kept} of {n_samples} samples fell inside the ROI box "
        f"{box.to_list()} after {n_drawn} draws; the surface inside the box is (almost) empty"
    )


def point_to_mesh_distance(points_mm: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """Exact unsigned distance from each point to the nearest point of ``mesh``'s triangles.

    points_mm : (P, 3) float, world mm. Returns (P,) float64 mm (Open3D, float32 inside).
    """
    rc = MeshRaycaster.from_trimesh(_check_mesh(mesh, "mesh"), backend="open3d")
    pts = o3d.core.Tensor(np.asarray(points_mm, dtype=np.float32).reshape(-1, 3))
    return rc.scene.compute_distance(pts).numpy().astype(np.float64)


def distance_metrics(
    pred_to_gt_mm: np.ndarray, gt_to_pred_mm: np.ndarray, threshold_mm: float
) -> SurfaceMetrics:
    """Surface metrics from the two sets of sample distances.

    pred_to_gt_mm : (P,) float, mm, predicted samples to the GT surface.
    gt_to_pred_mm : (Q,) float, mm, GT samples to the predicted surface.
    """
    a = np.asarray(pred_to_gt_mm, dtype=np.float64).ravel()
    c = np.asarray(gt_to_pred_mm, dtype=np.float64).ravel()
    for name, arr in (("pred_to_gt_mm", a), ("gt_to_pred_mm", c)):
        if arr.size == 0:
            raise InvalidInputError(name, "no distances given")
        if not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise InvalidInputError(name, "distances must be finite and non-negative")
    if not threshold_mm > 0:
        raise InvalidInputError("threshold_mm", f"must be positive, got {threshold_mm}")
    precision = float(np.mean(a < threshold_mm))
    recall = float(np.mean(c < threshold_mm))
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    acc95 = float(np.percentile(a, 95))
    comp95 = float(np.percentile(c, 95))
    return SurfaceMetrics(
        accuracy_mm=float(a.mean()),
        completeness_mm=float(c.mean()),
        accuracy_hd95_mm=acc95,
        completeness_hd95_mm=comp95,
        hd95_mm=max(acc95, comp95),
        chamfer_mm=float((a.mean() + c.mean()) / 2),
        precision=precision,
        recall=recall,
        fscore=float(f),
        threshold_mm=float(threshold_mm),
    )


def surface_metrics(
    pred_mesh: trimesh.Trimesh,
    gt_mesh: trimesh.Trimesh,
    box: RoiBox,
    cfg: SurfaceMetricConfig = SurfaceMetricConfig(),  # noqa: B008 - frozen, immutable
    gt_samples_mm: np.ndarray | None = None,
    source: str = "method",
    threshold_mm: float = FSCORE_THRESHOLD_MM,
) -> SurfaceMetrics:
    """Accuracy, completeness, HD95, chamfer and F-score of ``pred_mesh`` inside ``box``.

    Samples are drawn on each mesh's part inside the box; distances go to the whole other mesh
    (so a sample near the box wall is not penalised for a partner just outside it).
    gt_samples_mm : (Q, 3) float mm, precomputed GT samples (reuse across methods) or None.
    """
    _check_mesh(pred_mesh, source)
    _check_mesh(gt_mesh, "gt_mesh")
    if gt_samples_mm is None:
        gt_samples_mm = sample_surface_in_box(gt_mesh, box, cfg.n_samples, cfg.seed, "gt_mesh")
    # A different seed for the prediction: identical meshes must not get identical samples
    # by construction, or a test of "identical -> 0" could not fail.
    pred_samples = sample_surface_in_box(pred_mesh, box, cfg.n_samples, cfg.seed + 1, source)
    return distance_metrics(
        point_to_mesh_distance(pred_samples, gt_mesh),
        point_to_mesh_distance(gt_samples_mm, pred_mesh),
        threshold_mm,
    )


# --------------------------------------------------------------------------------------
# Change masks


@dataclass(frozen=True)
class MaskScores:
    """Pixel-wise precision / recall of predicted change masks (NaN where undefined)."""

    precision: float
    """TP / (TP + FP); NaN when nothing is predicted as changed."""
    recall: float
    """TP / (TP + FN); NaN when nothing truly changed."""
    n_true_positive: int
    n_false_positive: int
    n_false_negative: int


def _check_masks(masks: np.ndarray, source: str) -> np.ndarray:
    m = np.asarray(masks)
    if m.ndim == 2:
        m = m[None]
    if m.ndim != 3:
        raise InvalidInputError(source, f"expected (N, H, W) masks, got shape {m.shape}")
    if m.dtype != bool:
        if m.dtype.kind not in "iu" or not np.isin(np.unique(m), [0, 1, 255]).all():
            raise InvalidInputError(
                source, f"expected bool masks (or 0/1/255 integers), got dtype {m.dtype}"
            )
        m = m > 0
    return m


def mask_precision_recall(
    pred_masks: np.ndarray, true_masks: np.ndarray, valid: np.ndarray | None = None
) -> MaskScores:
    """Precision and recall of predicted change masks over all pixels of all frames.

    pred_masks, true_masks : (N, H, W) bool, True = changed.
    valid : (N, H, W) or (H, W) bool or None; only True pixels are scored.
    """
    pred = _check_masks(pred_masks, "pred_masks")
    true = _check_masks(true_masks, "true_masks")
    if pred.shape != true.shape:
        raise InvalidInputError(
            "pred_masks", f"shape {pred.shape} differs from true_masks {true.shape}"
        )
    if valid is not None:
        v = np.broadcast_to(np.asarray(valid, dtype=bool), pred.shape)
        pred = pred & v
        true = true & v
    tp = int(np.count_nonzero(pred & true))
    fp = int(np.count_nonzero(pred & ~true))
    fn = int(np.count_nonzero(~pred & true))
    return MaskScores(
        precision=tp / (tp + fp) if tp + fp else float("nan"),
        recall=tp / (tp + fn) if tp + fn else float("nan"),
        n_true_positive=tp,
        n_false_positive=fp,
        n_false_negative=fn,
    )


def true_change_masks_from_depths(
    before_depths_mm: np.ndarray,
    after_depths_mm: np.ndarray,
    threshold_mm: float = CHANGE_THRESHOLD_MM,
) -> np.ndarray:
    """The true change between two GT depth stacks rendered at the same poses.

    before_depths_mm, after_depths_mm : (N, H, W) float32 z-depth, mm, NaN = no surface.
    Returns (N, H, W) bool: depth grew by more than ``threshold_mm``, or the surface seen
    before is gone after (tissue removed along the whole ray).
    """
    b = np.asarray(before_depths_mm, dtype=np.float32)
    a = np.asarray(after_depths_mm, dtype=np.float32)
    if b.shape != a.shape or b.ndim != 3:
        raise InvalidInputError(
            "after_depths_mm", f"expected (N, H, W) matching before {b.shape}, got {a.shape}"
        )
    if not threshold_mm > 0:
        raise InvalidInputError("threshold_mm", f"must be positive, got {threshold_mm}")
    bv, av = np.isfinite(b), np.isfinite(a)
    with np.errstate(invalid="ignore"):
        grew = bv & av & (a - b > threshold_mm)
    return grew | (bv & ~av)


def true_change_masks(
    mesh_before: trimesh.Trimesh,
    mesh_after: trimesh.Trimesh,
    camera: Camera,
    poses: np.ndarray,
    threshold_mm: float = CHANGE_THRESHOLD_MM,
) -> np.ndarray:
    """True change masks of steps t -> t+1 at ``poses`` (the t+1 sequence's true poses).

    poses : (N, 4, 4) float64 ``T_world_from_cam``. Returns (N, H, W) bool.
    """
    return true_change_masks_from_depths(
        render_depths(mesh_before, camera, poses),
        render_depths(mesh_after, camera, poses),
        threshold_mm,
    )


# --------------------------------------------------------------------------------------
# One step, all methods


def step_label(step: int) -> str:
    """``"preop"`` for step 0, ``"bite N"`` otherwise (the paper's row names)."""
    return "preop" if step == 0 else f"bite {step}"


def _finite_or_none(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def method_cell(
    corr: CorrespondenceError, surf: SurfaceMetrics, masks: MaskScores | None
) -> dict[str, float | int | None]:
    """One method's cell of ``metrics.json`` (every key of :data:`METRIC_KEYS`)."""
    if surf.threshold_mm != FSCORE_THRESHOLD_MM:
        raise InvalidInputError(
            "surface metrics",
            f"the table reports the F-score at {FSCORE_THRESHOLD_MM} mm, got {surf.threshold_mm} mm",
        )
    return {
        "mean_mm": corr.mean_mm,
        "std_mm": corr.std_mm,
        "median_mm": corr.median_mm,
        "n_points": corr.n_points,
        "n_gt_in_box": corr.n_gt_in_box,
        "missing_fraction": corr.missing_fraction,
        "accuracy_mm": surf.accuracy_mm,
        "completeness_mm": surf.completeness_mm,
        "accuracy_hd95_mm": surf.accuracy_hd95_mm,
        "completeness_hd95_mm": surf.completeness_hd95_mm,
        "hd95_mm": surf.hd95_mm,
        "chamfer_mm": surf.chamfer_mm,
        "precision_1mm": surf.precision,
        "recall_1mm": surf.recall,
        "fscore_1mm": surf.fscore,
        "mask_precision": None if masks is None else _finite_or_none(masks.precision),
        "mask_recall": None if masks is None else _finite_or_none(masks.recall),
    }


@dataclass(frozen=True)
class ChangeMaskInput:
    """Predicted change masks of one method and the truth they are scored against."""

    pred_masks: np.ndarray
    """(N, H, W) bool, True = changed, one per frame of the step's update sequence."""
    true_masks: np.ndarray
    """(N, H, W) bool true change at the same poses (see :func:`true_change_masks`)."""
    valid: np.ndarray | None = None
    """(H, W) or (N, H, W) bool pixels to score (e.g. the camera mask), or None = all."""


def evaluate_methods(
    gt_mesh: trimesh.Trimesh,
    method_meshes: Mapping[str, trimesh.Trimesh],
    camera: Camera,
    poses: np.ndarray,
    box: RoiBox,
    step: int,
    cfg: SurfaceMetricConfig = SurfaceMetricConfig(),  # noqa: B008 - frozen, immutable
    change_masks: Mapping[str, ChangeMaskInput] | None = None,
    pixel_mask: np.ndarray | None = None,
) -> dict[str, Any]:
    """Evaluate every method's mesh against the step's GT mesh; returns a step dict.

    poses : (N, 4, 4) float64 evaluation ``T_world_from_cam`` viewing the box.
    pixel_mask : (H, W) bool or None; False pixels never count in the correspondence error.
    Returns ``{"step", "label", "methods": {name: cell}}`` (cells as in ``metrics.json``).
    """
    if not method_meshes:
        raise InvalidInputError("method_meshes", "no method to evaluate")
    if step < 0:
        raise InvalidInputError("step", f"must be >= 0, got {step}")
    unknown = set(change_masks or {}) - set(method_meshes)
    if unknown:
        raise InvalidInputError(
            "change_masks", f"masks given for methods without a mesh: {sorted(unknown)}"
        )
    _check_mesh(gt_mesh, "gt_mesh")
    poses = _check_poses(poses)
    gt_depths = render_depths(gt_mesh, camera, poses)
    gt_samples = sample_surface_in_box(gt_mesh, box, cfg.n_samples, cfg.seed, "gt_mesh")
    methods: dict[str, Any] = {}
    for name, mesh in method_meshes.items():
        _check_mesh(mesh, f"method {name!r}")
        corr = correspondence_error(
            gt_depths,
            render_depths(mesh, camera, poses),
            camera,
            poses,
            box,
            pixel_mask,
            source=f"method {name!r}",
        )
        surf = surface_metrics(mesh, gt_mesh, box, cfg, gt_samples, source=f"method {name!r}")
        masks = None
        if change_masks and name in change_masks:
            cm = change_masks[name]
            masks = mask_precision_recall(cm.pred_masks, cm.true_masks, cm.valid)
        methods[name] = method_cell(corr, surf, masks)
        log.info(
            "step %d %s: %.3f +- %.3f mm (n=%d), chamfer %.3f mm",
            step,
            name,
            corr.mean_mm,
            corr.std_mm,
            corr.n_points,
            surf.chamfer_mm,
        )
    return {"step": int(step), "label": step_label(step), "methods": methods}


def protocol_dict(
    box: RoiBox, cfg: SurfaceMetricConfig, n_poses: int, pose_source: str
) -> dict[str, Any]:
    """What a step was evaluated with (stored beside the numbers)."""
    return {
        "roi_box_mm": box.to_list(),
        "n_eval_poses": int(n_poses),
        "eval_poses": pose_source,
        "surface_samples": int(cfg.n_samples),
        "surface_seed": int(cfg.seed),
        "fscore_threshold_mm": FSCORE_THRESHOLD_MM,
        "change_threshold_mm": CHANGE_THRESHOLD_MM,
        "std": "population (ddof=0)",
    }


# --------------------------------------------------------------------------------------
# File-level wrapper


def load_mesh(path: str | Path, source: str) -> trimesh.Trimesh:
    """Read a triangle mesh (PLY/STL/OBJ) with trimesh; raise if missing, unreadable or empty."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, f"{source}: mesh file is missing")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types on bad files
        raise InvalidInputError(path, f"{source}: cannot read mesh: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InvalidInputError(path, f"{source}: mesh is empty (no triangles)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise InvalidInputError(path, f"{source}: vertices contain NaN/inf")
    return mesh


def load_change_masks(path: str | Path, n_frames: int, shape: tuple[int, int]) -> np.ndarray:
    """Read predicted change masks: an ``.npz`` with key ``masks`` or a folder of PNGs.

    npz: ``masks`` (N, H, W) bool or uint8 (nonzero = changed), read without pickle; with
    an optional ``frame_index`` (N,) int (as ``chisel update --masks`` writes), the masks are
    placed at those frames of the sequence and the other frames count as unchanged.
    Folder: ``000000.png`` ... one uint8 PNG per frame, 255 = changed.
    Returns (N, H, W) bool, checked against ``n_frames`` and ``shape`` = (H, W).
    """
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.png"))
        if not files:
            raise InvalidInputError(path, "change-mask folder holds no PNG file")
        masks = []
        for f in files:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InvalidInputError(f, "cannot decode change-mask PNG")
            masks.append(img > 127)
        arr = np.stack(masks) if len({m.shape for m in masks}) == 1 else None
        if arr is None:
            raise InvalidInputError(path, "change-mask PNGs differ in size")
    elif path.is_file():
        try:
            z = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise InvalidInputError(path, f"cannot read change masks (npz): {exc}") from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise InvalidInputError(path, "expected an .npz archive with key 'masks'")
        with z:
            if "masks" not in z.files:
                raise InvalidInputError(path, f"expected key 'masks', found {z.files}")
            arr = _check_masks(z["masks"], str(path))
            if "frame_index" in z.files:
                # `chisel update --masks` stores one mask per frame it considered, with the
                # frame's index; frames it did not consider count as "no change".
                idx = np.asarray(z["frame_index"], dtype=np.int64)
                if idx.shape != (len(arr),) or (
                    idx.size and (idx.min() < 0 or idx.max() >= n_frames)
                ):
                    raise InvalidInputError(
                        path, f"frame_index must hold {len(arr)} indices in 0..{n_frames - 1}"
                    )
                full = np.zeros((n_frames, *arr.shape[1:]), dtype=bool)
                full[idx] = arr
                arr = full
    else:
        raise InvalidInputError(path, "change masks are missing (expected an .npz or a folder)")
    if arr.shape != (n_frames, *shape):
        raise InvalidInputError(
            path,
            f"expected {n_frames} masks of {shape[1]}x{shape[0]} (WxH), got shape {arr.shape}",
        )
    return arr


def _eval_poses(seq: SequenceFolder) -> tuple[np.ndarray, str]:
    # The protocol fixes exact camera poses: use the true ones when the sequence has them.
    if seq.true_poses is not None:
        return seq.true_poses, "poses_true.txt"
    log.info("%s has no true poses; evaluating at its tracked poses", seq.path)
    return seq.poses, "poses.txt"


def evaluate_step(
    gt_mesh_path: str | Path,
    method_mesh_paths: Mapping[str, str | Path],
    eval_sequence_path: str | Path,
    roi_box_mm: RoiBox | Sequence[float],
    step: int,
    cfg: SurfaceMetricConfig = SurfaceMetricConfig(),  # noqa: B008 - frozen, immutable
    change_mask_paths: Mapping[str, str | Path] | None = None,
    change_sequence_path: str | Path | None = None,
    prev_gt_mesh_path: str | Path | None = None,
) -> dict[str, Any]:
    """Evaluate one step from files; returns the step-metrics dict (see ``STEP_METRICS_SCHEMA``).

    gt_mesh_path : the step's ground-truth mesh.  method_mesh_paths : name -> mesh file.
    eval_sequence_path : sequence folder whose camera and poses are the evaluation poses
    (true poses when present); its camera mask, if any, limits the counted pixels.
    roi_box_mm : the ROI box, or six numbers xmin, ymin, zmin, xmax, ymax, zmax (mm).
    change_mask_paths : name -> predicted change masks (see :func:`load_change_masks`) of the
    step's update sequence ``change_sequence_path``; scored against the true change between
    ``prev_gt_mesh_path`` (step t-1) and ``gt_mesh_path`` at that sequence's poses.
    """
    box = roi_box_mm if isinstance(roi_box_mm, RoiBox) else RoiBox.from_values(roi_box_mm)
    if not method_mesh_paths:
        raise InvalidInputError("method_mesh_paths", "no method to evaluate")
    gt_mesh = load_mesh(gt_mesh_path, "ground-truth mesh")
    meshes = {name: load_mesh(p, f"method {name!r}") for name, p in method_mesh_paths.items()}
    seq = SequenceFolder(eval_sequence_path)
    poses, pose_source = _eval_poses(seq)

    change_inputs: dict[str, ChangeMaskInput] | None = None
    if change_mask_paths:
        if change_sequence_path is None or prev_gt_mesh_path is None:
            raise InvalidInputError(
                "change_mask_paths",
                "scoring change masks needs change_sequence_path and prev_gt_mesh_path",
            )
        cseq = SequenceFolder(change_sequence_path)
        cposes, _ = _eval_poses(cseq)
        truth = true_change_masks(
            load_mesh(prev_gt_mesh_path, "previous ground-truth mesh"), gt_mesh, cseq.camera, cposes
        )
        change_inputs = {}
        for name, p in change_mask_paths.items():
            if name not in meshes:
                raise InvalidInputError(
                    "change_mask_paths", f"masks for {name!r}, which has no mesh"
                )
            pred = load_change_masks(p, len(cseq), cseq.camera.shape)
            change_inputs[name] = ChangeMaskInput(pred, truth, cseq.camera_mask)

    result = evaluate_methods(
        gt_mesh, meshes, seq.camera, poses, box, step, cfg, change_inputs, seq.camera_mask
    )
    return {
        "format": STEP_METRICS_FORMAT,
        "version": METRICS_VERSION,
        **result,
        "protocol": protocol_dict(box, cfg, len(poses), f"{seq.path}/{pose_source}"),
    }


# --------------------------------------------------------------------------------------
# Tables: assemble, validate, write


def _method_order(names: set[str] | Sequence[str]) -> list[str]:
    known = [m for m in METHODS if m in names]
    return known + sorted(set(names) - set(METHODS))


def validate_step_metrics(d: Mapping[str, Any], source: str = "step metrics") -> None:
    """Raise :class:`InvalidInputError` if ``d`` does not follow ``STEP_METRICS_SCHEMA``."""
    try:
        jsonschema.validate(d, STEP_METRICS_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise InvalidInputError(
            source, f"not a step-metrics file: at {where}: {exc.message}"
        ) from None


def validate_metrics(d: Mapping[str, Any], source: str = "metrics") -> None:
    """Raise :class:`InvalidInputError` if ``d`` does not follow ``METRICS_SCHEMA``."""
    try:
        jsonschema.validate(d, METRICS_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise InvalidInputError(source, f"not a metrics.json: at {where}: {exc.message}") from None
    steps = [s["step"] for s in d["steps"]]
    if len(set(steps)) != len(steps):
        raise InvalidInputError(source, f"duplicate steps {steps}")


def assemble_table(step_results: Sequence[Mapping[str, Any]], experiment: str) -> dict[str, Any]:
    """Combine per-step results into ``metrics.json`` (rows = steps, sorted).

    step_results : step dicts as returned by :func:`evaluate_step` (or ``evaluate_methods``).
    """
    if not step_results:
        raise InvalidInputError("step_results", "no step to tabulate")
    steps: dict[int, dict[str, Any]] = {}
    protocol: dict[str, Any] | None = None
    for i, r in enumerate(step_results):
        if "format" in r:
            validate_step_metrics(r, f"step_results[{i}]")
        s = int(r["step"])
        if s in steps:
            raise InvalidInputError(f"step_results[{i}]", f"step {s} appears twice")
        order = _method_order(list(r["methods"]))
        steps[s] = {
            "step": s,
            "label": step_label(s),
            "methods": {m: dict(r["methods"][m]) for m in order},
        }
        if protocol is None and "protocol" in r:
            protocol = {k: v for k, v in r["protocol"].items() if k != "eval_poses"}
    table = {
        "format": METRICS_FORMAT,
        "version": METRICS_VERSION,
        "experiment": str(experiment),
        "protocol": protocol or {},
        "steps": [steps[s] for s in sorted(steps)],
    }
    validate_metrics(table, "assembled table")
    return table


def _json_text(d: Mapping[str, Any]) -> str:
    return json.dumps(d, indent=2, allow_nan=False) + "\n"


def read_json(path: str | Path, what: str) -> dict[str, Any]:
    """Read a JSON file, raising :class:`InvalidInputError` naming it on any problem."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, f"{what} file is missing")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InvalidInputError(path, f"invalid JSON in {what}: {exc}") from None


def read_metrics(path: str | Path) -> dict[str, Any]:
    """Read and validate a ``metrics.json``."""
    d = read_json(path, "metrics")
    validate_metrics(d, str(path))
    return d


def read_step_metrics(path: str | Path) -> dict[str, Any]:
    """Read and validate a ``step_metrics.json``."""
    d = read_json(path, "step metrics")
    validate_step_metrics(d, str(path))
    return d


def write_step_metrics(path: str | Path, d: Mapping[str, Any]) -> None:
    """Validate and write one step's metrics as JSON (atomically)."""
    validate_step_metrics(d, str(path))
    atomic_write_text(path, _json_text(d))


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}"


def table_methods(metrics: Mapping[str, Any]) -> list[str]:
    """Every method of a ``metrics.json``, in table order."""
    names: set[str] = set()
    for s in metrics["steps"]:
        names |= set(s["methods"])
    return _method_order(names)


def metrics_to_csv(metrics: Mapping[str, Any]) -> str:
    """Long-format CSV: one row per (step, method), every metric a column; empty = null."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["step", "label", "method", *METRIC_KEYS])
    for s in metrics["steps"]:
        for m in _method_order(list(s["methods"])):
            cell = s["methods"][m]
            w.writerow(
                [
                    s["step"],
                    s["label"],
                    m,
                    *("" if cell[k] is None else repr(cell[k]) for k in METRIC_KEYS),
                ]
            )
    return buf.getvalue()


def metrics_to_markdown(metrics: Mapping[str, Any]) -> str:
    """Two Markdown tables: the paper's (mean ± std (n) per step x method) and surface metrics."""
    methods = table_methods(metrics)
    lines = [f"# Evaluation: {metrics['experiment']}", ""]
    lines += [
        "Correspondence error, mm: mean ± std (n points) of same-pixel distances inside the ROI box.",
        "",
        "| step | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for s in metrics["steps"]:
        cells = []
        for m in methods:
            c = s["methods"].get(m)
            cells.append(
                "-" if c is None else f"{c['mean_mm']:.3f} ± {c['std_mm']:.3f} (n={c['n_points']})"
            )
        lines.append(f"| {s['label']} | " + " | ".join(cells) + " |")
    surf_keys = (
        "accuracy_mm",
        "completeness_mm",
        "hd95_mm",
        "chamfer_mm",
        "fscore_1mm",
        "missing_fraction",
        "mask_precision",
        "mask_recall",
    )
    lines += [
        "",
        "Surface metrics inside the ROI box (mm; F-score at 1 mm; mask scores vs the true change).",
        "",
        "| step | method | " + " | ".join(surf_keys) + " |",
        "|---|---|" + "---|" * len(surf_keys),
    ]
    for s in metrics["steps"]:
        for m in _method_order(list(s["methods"])):
            c = s["methods"][m]
            lines.append(
                f"| {s['label']} | {m} | " + " | ".join(_fmt(c[k]) for k in surf_keys) + " |"
            )
    return "\n".join(lines) + "\n"


def write_table(out_dir: str | Path, metrics: Mapping[str, Any]) -> dict[str, Path]:
    """Write ``metrics.json``, ``metrics.csv`` and ``metrics.md`` into ``out_dir`` (atomically each).

    Returns the paths by kind (``json``, ``csv``, ``md``).
    """
    validate_metrics(metrics, "metrics")
    out = Path(out_dir)
    paths = {"json": out / "metrics.json", "csv": out / "metrics.csv", "md": out / "metrics.md"}
    atomic_write_text(paths["json"], _json_text(metrics))
    atomic_write_text(paths["csv"], metrics_to_csv(metrics))
    atomic_write_text(paths["md"], metrics_to_markdown(metrics))
    return paths


# --------------------------------------------------------------------------------------
# Across seeds


def aggregate_seeds(
    tables: Sequence[Mapping[str, Any]], labels: Sequence[str] | None = None
) -> dict[str, Any]:
    """Mean and spread of every metric per (step, method) across several ``metrics.json``.

    tables : one ``metrics.json`` dict per seed (same experiment design).
    labels : a name per table (e.g. ``"seed 0"``), stored in the result.
    Each metric becomes ``{"mean", "std" (population, ddof=0), "min", "max", "n"}`` over
    the tables where it is not null; a metric null everywhere stays null.
    """
    if not tables:
        raise InvalidInputError("tables", "no metrics to aggregate")
    if labels is not None and len(labels) != len(tables):
        raise InvalidInputError("labels", f"{len(labels)} labels for {len(tables)} tables")
    for i, t in enumerate(tables):
        validate_metrics(t, f"tables[{i}]")
    values: dict[int, dict[str, dict[str, list[float]]]] = {}
    for t in tables:
        for s in t["steps"]:
            per_method = values.setdefault(int(s["step"]), {})
            for m, cell in s["methods"].items():
                per_key = per_method.setdefault(m, {k: [] for k in METRIC_KEYS})
                for k in METRIC_KEYS:
                    if cell[k] is not None:
                        per_key[k].append(float(cell[k]))
    steps = []
    for s in sorted(values):
        methods = {}
        for m in _method_order(list(values[s])):
            agg: dict[str, Any] = {}
            for k, vals in values[s][m].items():
                if not vals:
                    agg[k] = None
                    continue
                a = np.asarray(vals)
                agg[k] = {
                    "mean": float(a.mean()),
                    "std": float(a.std()),
                    "min": float(a.min()),
                    "max": float(a.max()),
                    "n": int(a.size),
                }
            methods[m] = agg
        steps.append({"step": s, "label": step_label(s), "methods": methods})
    return {
        "format": SEED_METRICS_FORMAT,
        "version": METRICS_VERSION,
        "experiment": str(tables[0]["experiment"]),
        "inputs": list(labels)
        if labels is not None
        else [f"input {i}" for i in range(len(tables))],
        "steps": steps,
    }


def seeds_to_csv(agg: Mapping[str, Any]) -> str:
    """Long-format CSV of :func:`aggregate_seeds`: step, label, method, metric, mean, std, min, max, n."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["step", "label", "method", "metric", "mean", "std", "min", "max", "n"])
    for s in agg["steps"]:
        for m, cell in s["methods"].items():
            for k in METRIC_KEYS:
                v = cell[k]
                if v is None:
                    w.writerow([s["step"], s["label"], m, k, "", "", "", "", 0])
                else:
                    w.writerow(
                        [
                            s["step"],
                            s["label"],
                            m,
                            k,
                            repr(v["mean"]),
                            repr(v["std"]),
                            repr(v["min"]),
                            repr(v["max"]),
                            v["n"],
                        ]
                    )
    return buf.getvalue()


def seeds_to_markdown(agg: Mapping[str, Any]) -> str:
    """Markdown: the correspondence error per step x method, mean ± std across inputs."""
    names: set[str] = set()
    for s in agg["steps"]:
        names |= set(s["methods"])
    methods = _method_order(names)
    lines = [
        f"# Evaluation across {len(agg['inputs'])} runs: {agg['experiment']}",
        "",
        "Correspondence error, mm: mean over runs of the per-run mean ± std over runs (runs).",
        "",
        "| step | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for s in agg["steps"]:
        cells = []
        for m in methods:
            c = s["methods"].get(m)
            v = None if c is None else c["mean_mm"]
            cells.append("-" if v is None else f"{v['mean']:.3f} ± {v['std']:.3f} ({v['n']})")
        lines.append(f"| {s['label']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_seed_table(out_dir: str | Path, agg: Mapping[str, Any]) -> dict[str, Path]:
    """Write ``metrics_seeds.json``/``.csv``/``.md`` into ``out_dir`` (atomically each)."""
    if agg.get("format") != SEED_METRICS_FORMAT:
        raise InvalidInputError(
            "agg", f"expected format {SEED_METRICS_FORMAT!r}, got {agg.get('format')!r}"
        )
    out = Path(out_dir)
    paths = {
        "json": out / "metrics_seeds.json",
        "csv": out / "metrics_seeds.csv",
        "md": out / "metrics_seeds.md",
    }
    atomic_write_text(paths["json"], _json_text(agg))
    atomic_write_text(paths["csv"], seeds_to_csv(agg))
    atomic_write_text(paths["md"], seeds_to_markdown(agg))
    return paths


# --------------------------------------------------------------------------------------
# Sweeps


SWEEP_COLUMNS: tuple[str, ...] = (
    "param_value",
    "step",
    "method",
    "mean_mm",
    "std_mm",
    "n_points",
    "chamfer_mm",
    "fscore_1mm",
)
"""Columns of a sweep CSV after its first column ``param_name``."""


@dataclass(frozen=True)
class SweepTable:
    """Error against a swept parameter: one row per (value, step, method)."""

    param_name: str
    """The swept parameter with its unit, e.g. ``"pose_noise_mm"`` or ``"frames"``."""
    rows: list[dict[str, Any]] = field(default_factory=list)
    """Dicts with the keys of :data:`SWEEP_COLUMNS`; metric values may be None."""

    def __post_init__(self) -> None:
        if not self.param_name or "," in self.param_name:
            raise InvalidInputError(
                "param_name", f"must be a non-empty name without commas, got {self.param_name!r}"
            )
        if not self.rows:
            raise InvalidInputError(self.param_name, "a sweep needs at least one row")

    def values(self) -> list[float]:
        """The swept values, sorted."""
        return sorted({float(r["param_value"]) for r in self.rows})

    def methods(self) -> list[str]:
        return _method_order({r["method"] for r in self.rows})

    def last_step(self) -> int:
        return max(int(r["step"]) for r in self.rows)


def tabulate_sweep(param_name: str, runs: Sequence[tuple[float, Mapping[str, Any]]]) -> SweepTable:
    """Error against a swept parameter from one ``metrics.json`` per parameter value.

    runs : (value, metrics dict) pairs, e.g. ``[(10, m10), (30, m30), ...]`` for frames.
    """
    if not runs:
        raise InvalidInputError(param_name, "no sweep run given")
    seen: set[float] = set()
    rows = []
    for value, metrics in runs:
        v = float(value)
        if not math.isfinite(v):
            raise InvalidInputError(param_name, f"swept value must be finite, got {value}")
        if v in seen:
            raise InvalidInputError(param_name, f"value {v:g} appears twice")
        seen.add(v)
        validate_metrics(metrics, f"{param_name}={v:g}")
        for s in metrics["steps"]:
            for m in _method_order(list(s["methods"])):
                c = s["methods"][m]
                rows.append(
                    {
                        "param_value": v,
                        "step": int(s["step"]),
                        "method": m,
                        **{k: c[k] for k in SWEEP_COLUMNS[3:]},
                    }
                )
    rows.sort(key=lambda r: (r["param_value"], r["step"]))
    return SweepTable(param_name, rows)


def sweep_to_csv(table: SweepTable) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["param_name", *SWEEP_COLUMNS])
    for r in table.rows:
        w.writerow(
            [
                table.param_name,
                *(
                    "" if r[k] is None else repr(r[k]) if isinstance(r[k], float) else r[k]
                    for k in SWEEP_COLUMNS
                ),
            ]
        )
    return buf.getvalue()


def write_sweep_csv(path: str | Path, table: SweepTable) -> Path:
    """Write a sweep table as CSV (atomically); header ``param_name`` + :data:`SWEEP_COLUMNS`."""
    atomic_write_text(path, sweep_to_csv(table))
    return Path(path)


def read_sweep_csv(path: str | Path) -> SweepTable:
    """Read a CSV written by :func:`write_sweep_csv`."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "sweep CSV is missing")
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        expected = ["param_name", *SWEEP_COLUMNS]
        if reader.fieldnames != expected:
            raise InvalidInputError(path, f"expected columns {expected}, got {reader.fieldnames}")
        raw = list(reader)
    if not raw:
        raise InvalidInputError(path, "sweep CSV has no rows")
    names = {r["param_name"] for r in raw}
    if len(names) != 1:
        raise InvalidInputError(path, f"expected one param_name, got {sorted(names)}")
    rows = []
    for i, r in enumerate(raw, start=2):
        try:
            rows.append(
                {
                    "param_value": float(r["param_value"]),
                    "step": int(r["step"]),
                    "method": r["method"],
                    **{
                        k: (None if r[k] == "" else (int(r[k]) if k == "n_points" else float(r[k])))
                        for k in SWEEP_COLUMNS[3:]
                    },
                }
            )
        except ValueError as exc:
            raise InvalidInputError(path, f"line {i}: {exc}") from None
    return SweepTable(names.pop(), rows)
