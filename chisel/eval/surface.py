"""Surface metrics inside the ROI box: accuracy, completeness, HD95, chamfer and F-score
from area-uniform samples and exact point-to-triangle distances (docs/evaluation.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from chisel.core.config import is_integer
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.raycast import SurfaceQueries
from chisel.eval.metrics import RoiBox, _check_mesh

FSCORE_THRESHOLD_MM = 1.0
"""Distance threshold of the F-score (and its precision/recall) in the tables, mm."""
MIN_SAMPLES = 100
"""Fewest surface samples per mesh (a 95th percentile of fewer says little)."""
MAX_SAMPLES = 10_000_000
"""Most surface samples per mesh: 200x the default. Sampling holds ~160 bytes per sample at
once (1.6 GB measured at 10^7, so 10^8 would need ~16 GB), and every sample is a distance
query; 99999999999999999999 died of ``OverflowError`` inside numpy."""


@dataclass(frozen=True)
class SurfaceMetricConfig:
    """How surfaces are sampled for the accuracy / completeness / F-score metrics."""

    n_samples: int = 50_000
    """Points sampled uniformly by area on each mesh's part inside the box (100 to 10^7)."""
    seed: int = 0
    """Seed of the area-uniform sampling (same seed, same samples)."""

    def __post_init__(self) -> None:
        n = self.n_samples
        if not is_integer(n) or not MIN_SAMPLES <= n <= MAX_SAMPLES:
            raise InvalidInputError(
                "n_samples", f"must be an integer in [{MIN_SAMPLES}, {MAX_SAMPLES}], got {n!r}"
            )


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
    queries = SurfaceQueries.from_trimesh(_check_mesh(mesh, "mesh"))
    return queries.distance(np.asarray(points_mm).reshape(-1, 3)).astype(np.float64)


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
