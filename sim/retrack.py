"""Re-track a rendered sequence: same frames, tracked poses drawn with another noise model.

The tracking-noise sweep needs the same images and ground truth with different amounts of
navigation error; rendering again would only reproduce the frames. The true poses of the
input sequence are kept, and ``poses.txt`` is redrawn with :func:`sim.tracking.tracked_poses`.
"""

from __future__ import annotations

from pathlib import Path

from chisel.core.atomic import check_output_outside
from chisel.core.errors import InvalidInputError
from chisel.io.sequence import Frame, Sequence, SequenceWriter
from sim.config import TrackingConfig
from sim.tracking import tracked_poses


def retrack_sequence(
    sequence_path: str | Path, out_path: str | Path, tracking: TrackingConfig, seed: int
) -> Path:
    """Write ``out_path`` (atomically): ``sequence_path`` with new tracked poses.

    Raises :class:`InvalidInputError` when the input has no true poses (real data), is
    malformed, or when ``out_path`` is, holds or lies inside ``sequence_path``.
    """
    # The atomic write replaces out_path whole: refuse before it could delete the input.
    check_output_outside(out_path, sequence_path)
    seq = Sequence(sequence_path)
    if seq.true_poses is None:
        raise InvalidInputError(
            seq.path,
            "has no true poses (poses_true.txt): only synthetic sequences can be re-tracked",
        )
    poses = tracked_poses(seq.true_poses, tracking, seed)
    meta = {
        **seq.meta,
        "retracked_from": str(seq.path),
        "tracking": vars(tracking) | {"seed": seed},
    }
    with SequenceWriter(out_path, seq.camera, meta, seq.camera_mask, seq.undistorted) as w:
        for i in range(len(seq)):
            f = seq.frame(i)
            # The per-frame mask already includes the camera mask; store the per-frame part.
            mask = None
            if seq.has_mask:
                mask = f.mask if seq.camera_mask is None else (f.mask | ~seq.camera_mask)
            w.add(Frame(i, poses[i], f.rgb, f.depth_mm, mask, f.T_world_from_cam_true))
    return Path(out_path)
