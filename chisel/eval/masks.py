"""Change masks scored against the true change: GT depth beyond a reference depth (the
model the step began from, or the previous GT step) by more than the paper's 1 mm, at
the same pose (docs/evaluation.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera
from chisel.eval.metrics import render_depths

CHANGE_THRESHOLD_MM = 1.0
"""A pixel's true change: GT depth grows by more than this between steps (the paper's 1 mm)."""


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
    """The true change between two depth stacks rendered at the same poses.

    before_depths_mm : (N, H, W) float32 z-depth, mm, NaN = no surface: the reference (a
    method's start model, or the previous GT step). after_depths_mm : the same, the GT.
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
