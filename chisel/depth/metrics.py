"""Depth-estimation metrics after per-frame median scaling (the monocular-depth standard).

A relative prediction is scaled by ``median(gt) / median(pred)`` over the valid pixels of
its frame, then compared with the truth: abs-rel, RMSE in mm, and the fraction of pixels
with ``max(p/g, g/p) < 1.25``. Frame metrics are averaged over frames (each frame counts
once, whatever its number of valid pixels).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chisel.core.errors import EmptyResultError, InvalidInputError

DELTA_THRESHOLD = 1.25


@dataclass(frozen=True)
class DepthMetrics:
    """Median-scaled depth errors (mean over frames)."""

    abs_rel: float
    """mean |s p - g| / g, dimensionless."""
    rmse_mm: float
    """sqrt(mean (s p - g)**2), mm (per frame, then averaged)."""
    delta_1_25: float
    """fraction of pixels with max(s p / g, g / (s p)) < 1.25."""
    num_frames: int
    """frames with at least one valid pixel."""

    def to_dict(self) -> dict[str, float | int]:
        return {
            "abs_rel": self.abs_rel,
            "rmse_mm": self.rmse_mm,
            "delta_1_25": self.delta_1_25,
            "num_frames": self.num_frames,
        }


def frame_metrics(
    pred: np.ndarray, gt_mm: np.ndarray, valid: np.ndarray | None = None
) -> tuple[float, float, float] | None:
    """Median-scaled (abs_rel, rmse_mm, delta_1_25) of one frame, or None if nothing is valid.

    pred : (H, W) float relative depth (> 0 where usable, NaN = invalid).
    gt_mm : (H, W) float true z-depth, mm, NaN/0 = invalid.
    valid : optional (H, W) bool, pixels to score (ANDed with finite, positive pred and gt).
    """
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt_mm, dtype=np.float64)
    if p.shape != g.shape or p.ndim != 2:
        raise InvalidInputError(
            "pred/gt_mm", f"expected two (H, W) maps of one shape, got {p.shape}, {g.shape}"
        )
    ok = np.isfinite(p) & np.isfinite(g) & (p > 0) & (g > 0)
    if valid is not None:
        if np.shape(valid) != p.shape:
            raise InvalidInputError("valid", f"expected shape {p.shape}, got {np.shape(valid)}")
        ok &= np.asarray(valid, dtype=bool)
    if not ok.any():
        return None
    p = p[ok]
    g = g[ok]
    p = p * (np.median(g) / np.median(p))
    abs_rel = float(np.mean(np.abs(p - g) / g))
    rmse = float(np.sqrt(np.mean((p - g) ** 2)))
    delta = float(np.mean(np.maximum(p / g, g / p) < DELTA_THRESHOLD))
    return abs_rel, rmse, delta


class MetricAccumulator:
    """Collects :func:`frame_metrics` over frames; :meth:`result` averages them."""

    def __init__(self) -> None:
        self._rows: list[tuple[float, float, float]] = []

    def add(self, pred: np.ndarray, gt_mm: np.ndarray, valid: np.ndarray | None = None) -> None:
        row = frame_metrics(pred, gt_mm, valid)
        if row is not None:
            self._rows.append(row)

    def __len__(self) -> int:
        return len(self._rows)

    def result(self) -> DepthMetrics:
        if not self._rows:
            raise EmptyResultError("no frame had a valid pixel to score")
        a = np.asarray(self._rows)
        return DepthMetrics(
            abs_rel=float(a[:, 0].mean()),
            rmse_mm=float(a[:, 1].mean()),
            delta_1_25=float(a[:, 2].mean()),
            num_frames=len(a),
        )
