"""What an update step did, frame by frame: the JSON report of ``chisel update``."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from chisel.update_config import UpdateConfig


@dataclass(frozen=True)
class FrameReport:
    """What happened to one frame of a step (the work in flight is a
    :class:`chisel.detect.Detection`; this is its outcome)."""

    index: int
    used: bool
    reason: str = ""
    scale: float = float("nan")
    registration: dict | None = None
    shift_mm: float = 0.0
    """Depth shift fitted to a relative estimate after its scale, mm (0 = none)."""
    changed_fraction: float = 0.0
    voxels_updated: int = 0
    unconfirmed_px: int = 0
    """Changed pixels dropped because other frames did not confirm them (batch)."""
    threshold_mm: float = float("nan")
    """The change threshold used for this frame, mm (see ``ChangeConfig.noise_k``); where it
    grows with depth, its value at the render's median depth ..."""
    threshold_per_mm: float = 0.0
    """... and its growth, mm per mm of depth (``ChangeConfig.noise_with_depth``; 0 = none)."""
    deleted_px: int = 0
    """Changed pixels whose first layer was deleted up to a surface the model holds (for a
    noisy frame with ``UpdateConfig.noisy_votes`` > 1: voted for deletion; the voxels go at
    their last vote, counted in ``voxels_deleted`` of that frame)."""
    uncarved_px: int = 0
    """Changed pixels that deletion-first carving left alone (``chisel.carve.CARVE_NONE``);
    they are not in the carved ``mask`` nor in ``changed_fraction``."""
    voxels_deleted: int = 0
    """Voxels set free by deletion-first carving (included in ``voxels_updated``)."""
    mask: np.ndarray | None = field(default=None, repr=False, compare=False)
    """(H, W) bool change mask that was carved, when the caller asked to keep it
    (``keep_maps``); an output for ``chisel update --masks``, not serialised."""
    mask_T_world_from_cam: np.ndarray | None = field(default=None, repr=False, compare=False)
    """(4, 4) the pose whose image ``mask`` lies in: the tracked pose, or the tracked pose
    with the step's shading correction (``UpdateConfig.shading``); kept with ``mask``."""

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "used": self.used,
            "reason": self.reason,
            "scale": None if not np.isfinite(self.scale) else float(self.scale),
            "registration": self.registration,
            "shift_mm": float(self.shift_mm),
            "changed_fraction": float(self.changed_fraction),
            "voxels_updated": int(self.voxels_updated),
            "unconfirmed_px": int(self.unconfirmed_px),
            "threshold_mm": None if not np.isfinite(self.threshold_mm) else self.threshold_mm,
            "threshold_per_mm": float(self.threshold_per_mm),
            "deleted_px": int(self.deleted_px),
            "uncarved_px": int(self.uncarved_px),
            "voxels_deleted": int(self.voxels_deleted),
        }


@dataclass(frozen=True)
class StepReport:
    """Summary of one update step (serialised as the JSON report of ``chisel update``)."""

    step: int
    frames: list[FrameReport]
    sequence_registration: dict | None
    config: dict
    pose_correction: dict | None = None
    """The correction applied to every tracked pose before anything else saw it (the
    frames' odometry, ``UpdateConfig.odometry``, then their shading,
    ``UpdateConfig.shading``), or None. Streaming
    (:class:`chisel.updater.ChiselUpdater`): the median at the step's end; each frame was
    corrected by the median of the frames two or more before it (the first two not at
    all)."""

    @classmethod
    def of(
        cls, step: int, frames: list[FrameReport], sequence_registration: dict | None,
        cfg: UpdateConfig, pose_correction: dict | None = None,
    ) -> StepReport:  # fmt: skip
        return cls(step, frames, sequence_registration, asdict(cfg), pose_correction)

    @property
    def frames_used(self) -> list[int]:
        return [f.index for f in self.frames if f.used]

    @property
    def frames_skipped(self) -> list[dict]:
        return [{"index": f.index, "reason": f.reason} for f in self.frames if not f.used]

    def to_dict(self) -> dict:
        used = [f for f in self.frames if f.used]
        return {
            "step": self.step,
            "num_frames": len(self.frames),
            "frames_used": self.frames_used,
            "frames_skipped": self.frames_skipped,
            "frames_unregistered": [
                f.index for f in self.frames if f.used and "fallback" in (f.registration or {})
            ],
            "changed_pixel_fraction_mean": float(np.mean([f.changed_fraction for f in used]))
            if used
            else 0.0,
            "sequence_registration": self.sequence_registration,
            "pose_correction": self.pose_correction,
            "frames": [f.to_dict() for f in self.frames],
            "config": self.config,
        }


def shading_report(F: np.ndarray, n_found: int, n_frames: int, before: dict | None = None) -> dict:
    """The report's ``pose_correction`` for a step corrected by its frames' shading;
    ``before``: the odometry's account (:func:`odometry_report`) when it came first."""
    out: dict = {
        "by": "shading" if before is None else "odometry+shading",
        "translation_mm": [round(float(v), 4) for v in F[:3, 3]],
        "frames_found": n_found,
        "frames": n_frames,
    }
    if before is not None:
        out["odometry"] = before["odometry"]
    return out


def odometry_report(pairs_used: int, pairs: int, moved_mm: list[float]) -> dict:
    """The report's ``pose_correction`` for a step whose poses the frames' odometry moved
    (``UpdateConfig.odometry``): how many consecutive pairs did, and by how much."""
    return {
        "by": "odometry",
        "odometry": {
            "pairs_used": pairs_used,
            "pairs": pairs,
            "moved_mm_mean": round(float(np.mean(moved_mm)), 4) if moved_mm else 0.0,
            "moved_mm_max": round(float(np.max(moved_mm)), 4) if moved_mm else 0.0,
        },
    }
