"""Volumetric scores of the removal: removed-tissue Dice and HD95 (mm).

Per step and method, on the model's voxel grid:

* the model's removal: voxels that are tissue in the preoperative model (tsdf < 0,
  observed) and free in the step's model (tsdf > 0, observed);
* the truth: voxels that are tissue in the preoperative label CT and air in the step's
  label CT, sampled at the model's voxel centres (nearest CT voxel; outside the CT = not
  counted).

Dice = 2 |A ∩ B| / (|A| + |B|). Its two halves say which way a method errs: precision
|A ∩ B| / |A| (what it removed was removed) and recall |A ∩ B| / |B| (what was removed,
it removed); a Dice of 0.5 is an update that carved a third of the removal and nothing
else, or one that carved all of it and twice as much again elsewhere. HD95 is the
symmetric 95th percentile of the distances between the two volumes' boundary voxels
(scipy's Euclidean distance transform, voxel size honoured), mm. Video-based CT-update
work reports these on cadavers (Dice 0.88, HD95 0.69 mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, invert_rigid, transform_points
from chisel.fusion import nearest_pixels
from chisel.model import TsdfModel


@dataclass(frozen=True)
class RemovalScores:
    """Removed-tissue agreement of one method at one step."""

    dice: float | None
    """Dice of model vs true removal (None when both are empty)."""
    hd95_mm: float | None
    """Symmetric 95th-percentile boundary distance, mm (None when either is empty)."""
    model_mm3: float
    """Removed volume in the model, mm^3."""
    truth_mm3: float
    """True removed volume on the model's grid, mm^3."""
    precision: float | None
    """Share of the model's removal that was truly removed (None when it removed nothing)."""
    recall: float | None
    """Share of the true removal that the model removed (None when nothing was removed)."""


def model_removal(preop: TsdfModel, now: TsdfModel) -> np.ndarray:
    """(X, Y, Z) bool voxels tissue in ``preop`` and free in ``now`` (both observed)."""
    if preop.shape != now.shape or not np.allclose(
        preop.T_world_from_voxel, now.T_world_from_voxel
    ):
        raise InvalidInputError("model", "the step's model is not on the preoperative model's grid")
    return (preop.tsdf < 0) & (preop.weight > 0) & (now.tsdf > 0) & (now.weight > 0)


def labels_on_grid(
    labels: np.ndarray,
    T_world_from_ct: np.ndarray,
    T_world_from_voxel: np.ndarray,
    shape: tuple[int, int, int],
) -> np.ndarray:
    """A label volume sampled (nearest) at a grid's voxel centres; -1 outside the CT."""
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), axis=-1)
    world = transform_points(T_world_from_voxel, ijk.reshape(-1, 3).astype(np.float64))
    c = np.rint(transform_points(np.linalg.inv(T_world_from_ct), world)).astype(np.int64)
    lab = np.asarray(labels)
    inside = np.all((c >= 0) & (c < np.array(lab.shape)), axis=1)
    out = np.full(len(c), -1, dtype=np.int64)
    out[inside] = lab[c[inside, 0], c[inside, 1], c[inside, 2]]
    return out.reshape(shape)


def true_removal(
    labels_preop: np.ndarray,
    labels_now: np.ndarray,
    T_world_from_ct: np.ndarray,
    model: TsdfModel,
    tissue_labels: Sequence[int] = (1, 2),
) -> np.ndarray:
    """(X, Y, Z) bool on the model's grid: tissue in the preop label CT, air (0) now.

    labels_preop, labels_now : (I, J, K) integer label CTs on the same grid
    ``T_world_from_ct`` (voxel index -> world mm).
    """
    if np.shape(labels_preop) != np.shape(labels_now):
        raise InvalidInputError("labels", "the preop and step label CTs differ in shape")
    pre = labels_on_grid(labels_preop, T_world_from_ct, model.T_world_from_voxel, model.shape)
    now = labels_on_grid(labels_now, T_world_from_ct, model.T_world_from_voxel, model.shape)
    return np.isin(pre, list(tissue_labels)) & (now == 0)


def dice(a: np.ndarray, b: np.ndarray) -> float | None:
    """Dice of two boolean volumes; None when both are empty."""
    n = int(a.sum()) + int(b.sum())
    return None if n == 0 else 2.0 * int((a & b).sum()) / n


def _boundary(a: np.ndarray) -> np.ndarray:
    return a & ~ndimage.binary_erosion(a, border_value=0)


def hd95_mm(a: np.ndarray, b: np.ndarray, voxel_mm: float) -> float | None:
    """Symmetric 95th percentile of boundary-to-boundary distances, mm; None if one is empty."""
    if not a.any() or not b.any():
        return None
    ba, bb = _boundary(a), _boundary(b)
    to_b = ndimage.distance_transform_edt(~bb, sampling=voxel_mm)
    to_a = ndimage.distance_transform_edt(~ba, sampling=voxel_mm)
    d = np.concatenate([to_b[ba], to_a[bb]])
    return float(np.percentile(d, 95))


def removal_scores(
    model_removed: np.ndarray, truth_removed: np.ndarray, voxel_mm: float
) -> RemovalScores:
    """Dice, HD95, precision and recall of a model's removal against the truth (same grid)."""
    if model_removed.shape != truth_removed.shape:
        raise InvalidInputError(
            "removal", f"shapes differ: {model_removed.shape} vs {truth_removed.shape}"
        )
    v3 = voxel_mm**3
    n_model, n_truth = int(model_removed.sum()), int(truth_removed.sum())
    n_both = int((model_removed & truth_removed).sum())
    return RemovalScores(
        dice=dice(model_removed, truth_removed),
        hd95_mm=hd95_mm(model_removed, truth_removed, voxel_mm),
        model_mm3=float(n_model * v3),
        truth_mm3=float(n_truth * v3),
        precision=n_both / n_model if n_model else None,
        recall=n_both / n_truth if n_truth else None,
    )


def seen_free(
    points_mm: np.ndarray,
    camera: Camera,
    poses: np.ndarray,
    depths_mm: np.ndarray,
    margin_mm: float,
) -> np.ndarray:
    """Which world points some frame sees as free space: (N,) bool.

    A frame sees a point free when the point projects into its image (the pixel fusion and
    carving map a voxel to, :func:`chisel.fusion.nearest_pixels`) and lies in front of the
    frame's depth there by more than ``margin_mm`` (z-depth). A removed voxel that no frame
    sees so lies behind tissue that stays: only inference frees it, so the seen voxels are a
    reference for what a method that carves what it sees can reach.

    points_mm : (N, 3) world mm; poses : (F, 4, 4) ``T_world_from_cam`` (the frames' true
    poses); depths_mm : (F, H, W) z-depth, NaN = nothing seen.
    """
    P = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    D = np.asarray(depths_mm)
    if D.ndim != 3 or D.shape[1:] != camera.shape or len(D) != len(poses):
        raise InvalidInputError(
            "depths_mm",
            f"expected ({len(poses)}, {camera.shape[0]}, {camera.shape[1]}), got {D.shape}",
        )
    out = np.zeros(len(P), dtype=bool)
    for T, depth in zip(poses, D, strict=True):
        pc = transform_points(invert_rigid(T), P)
        uv = nearest_pixels(pc, camera)
        ok = uv[:, 0] >= 0
        d = np.full(len(P), np.nan)
        d[ok] = depth[uv[ok, 1], uv[ok, 0]]
        with np.errstate(invalid="ignore"):
            out |= ok & (d > pc[:, 2] + margin_mm)
    return out
