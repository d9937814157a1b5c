"""Configuration of the camera's motion: its paths and the tracker that reports them.

Sections ``paths`` (:class:`PathConfig`: preoperative sweep, intraoperative sequences,
evaluation poses; ``sim/paths.py``) and ``tracking`` (:class:`TrackingConfig`: how the
reported poses differ from the true ones; ``sim/tracking.py``) of
:class:`sim.config.SimConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chisel.core.config import check_fields
from sim.config_checks import Range, check, check_range
from sim.errors import ConfigError

MAX_FRAMES = 100_000
"""Largest number of frames (or evaluation poses) of one sequence."""
MIN_CLEARANCE_MM = 0.1
"""Smallest camera-to-tissue clearance of the paths, mm."""
MAX_LATENCY_FRAMES = 10_000
"""Largest tracking latency, frames (beyond a sequence's length every frame reports its
first pose)."""
TRACKING_LIMITS = (
    ("jitter_mm", 100.0, "mm"),
    ("jitter_deg", 180.0, "degrees"),
    ("handeye_mm", 1000.0, "mm"),
    ("handeye_deg", 180.0, "degrees"),
    ("latency_frames", MAX_LATENCY_FRAMES, "frames"),
)
"""``tracking`` fields and their largest values: errors far beyond any real navigation
system (a 1e300 degree rotation is no rotation NumPy can build; 1e20 frames overflow)."""
TRACKING_OPTIONS = {
    "jitter_mm": "sim render --pose-noise-mm, sim retrack --jitter-mm",
    "jitter_deg": "sim render --pose-noise-deg, sim retrack --jitter-deg",
    "handeye_mm": "sim retrack --handeye-mm",
    "handeye_deg": "sim retrack --handeye-deg",
    "latency_frames": "sim retrack --latency-frames",
}
"""The command-line options that set each ``tracking`` field."""


@dataclass(frozen=True)
class PathConfig:
    """Camera paths: preoperative sweep, intraoperative sequences, evaluation poses."""

    clearance_mm: float = 2.0
    """Minimum distance of the optical centre from tissue, mm (4 mm scope shaft)."""
    preop_frames: int = 60
    """Frames of the preoperative sweep along the airway."""
    intraop_frames: int = 80
    """Frames per intraoperative sequence (one per surgical step)."""
    eval_poses: int = 8
    """Fixed evaluation poses viewing the ROI, the same for every step."""
    lookahead_mm: float = 10.0
    """During the sweep the camera looks at the path point this far ahead, mm."""
    turn_fraction: float = 0.3
    """Last fraction of the sweep over which the view turns from ahead to the target."""
    view_distance_mm: Range = (6.0, 16.0)
    """Distance of intraoperative/evaluation viewpoints from the target centre, mm."""
    viewpoint_spread_mm: float = 6.0
    """Radius of the ball around the approach point where viewpoints are drawn, mm."""
    aim_jitter_mm: float = 2.0
    """Random offset of the aim point around the target (kept inside the ROI box), mm."""
    keyframes: int = 5
    """Keyframes of an intraoperative path (a smooth spline runs through them)."""
    roll_deg: float = 20.0
    """Amplitude of the smooth roll of the scope about its axis, degrees."""
    up_hint: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """World direction the image's up (-y) starts closest to (then transported smoothly)."""
    max_tries: int = 200
    """Attempts at drawing a collision-free intraoperative path before giving up."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="paths")
        # Paths are sampled every clearance / 4 mm: a near-zero clearance would mean
        # millions of collision queries (and the scope tip is ~2 mm in radius anyway).
        check(
            self.clearance_mm >= MIN_CLEARANCE_MM,
            "paths.clearance_mm",
            f"must be >= {MIN_CLEARANCE_MM} mm, got {self.clearance_mm}",
        )
        for name in ("preop_frames", "intraop_frames", "eval_poses", "keyframes", "max_tries"):
            check(
                getattr(self, name) >= 1,
                f"paths.{name}",
                f"must be >= 1, got {getattr(self, name)}",
            )
        for name in ("preop_frames", "intraop_frames", "eval_poses"):
            check(
                getattr(self, name) <= MAX_FRAMES,
                f"paths.{name}",
                f"must be at most {MAX_FRAMES}, got {getattr(self, name)}",
            )
        check(self.keyframes >= 2, "paths.keyframes", f"must be >= 2, got {self.keyframes}")
        check(self.lookahead_mm > 0, "paths.lookahead_mm", f"must be > 0, got {self.lookahead_mm}")
        check(
            0.0 <= self.turn_fraction <= 1.0,
            "paths.turn_fraction",
            f"must be in [0, 1], got {self.turn_fraction}",
        )
        check_range("paths.view_distance_mm", self.view_distance_mm, 0.5, 200.0)
        check(
            self.viewpoint_spread_mm >= 0 and self.aim_jitter_mm >= 0,
            "paths.*_mm",
            "spreads must be >= 0",
        )
        check(
            0.0 <= self.roll_deg <= 180.0,
            "paths.roll_deg",
            f"must be in [0, 180], got {self.roll_deg}",
        )
        check(float(np.linalg.norm(self.up_hint)) > 0, "paths.up_hint", "must be a non-zero vector")


@dataclass(frozen=True)
class TrackingConfig:
    """How the navigation system's reported poses differ from the true ones."""

    jitter_mm: float = 0.2
    """Per-frame optical-tracking jitter: std per axis of the translation, mm."""
    jitter_deg: float = 0.1
    """Per-frame jitter: std per axis of the rotation vector, degrees."""
    handeye_mm: float = 0.5
    """Constant hand-eye calibration error: translation magnitude, mm (random direction)."""
    handeye_deg: float = 0.5
    """Constant hand-eye calibration error: rotation angle, degrees (random axis)."""
    latency_frames: int = 0
    """Tracking latency: frame i reports the true pose of frame max(i - latency, 0)."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="tracking")
        for name, hi, unit in TRACKING_LIMITS:
            v = getattr(self, name)
            check(
                0 <= v <= hi,
                f"tracking.{name}",
                f"must be in [0, {hi:g}] {unit} ({TRACKING_OPTIONS[name]}), got {v}",
            )
