"""Monocular depth estimation: a small CPU-friendly network trained on simulated renders.

Public API (see docs/depth.md):

- :class:`DepthNetConfig`, :class:`DepthNet`, :class:`DepthPredictor` -- the network;
- :func:`train`, :class:`TrainConfig` -- training and per-patient fine-tuning;
- :func:`save_checkpoint`, :func:`load_checkpoint` -- ``.pt`` state_dict + JSON config;
- :func:`load_depth_source` -- a checkpoint or TorchScript file as the updater's depth
  source, a callable ``Frame -> (H, W) float32`` relative depth (NaN = invalid);
- :func:`predict_sequence`, :func:`export_model`, :func:`evaluate_source`;
- :data:`DEFAULT_CHECKPOINT` -- the checkpoint the project ships.
"""

from __future__ import annotations

from pathlib import Path

from chisel.depth.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from chisel.depth.data import (
    RESERVED_EVAL_SEEDS,
    AugmentConfig,
    FrameSet,
    SequenceRef,
    check_training_seeds,
    find_sequences,
    load_frames,
    split_by_group,
)
from chisel.depth.infer import (
    NetworkDepthSource,
    evaluate_source,
    export_model,
    load_depth_source,
    load_predictor,
    predict_sequence,
)
from chisel.depth.losses import depth_loss, gradient_matching_loss, scale_invariant_log_loss
from chisel.depth.metrics import DepthMetrics, MetricAccumulator, frame_metrics
from chisel.depth.network import DepthNet, DepthNetConfig, DepthPredictor
from chisel.depth.train import TrainConfig, TrainResult, evaluate_frames, train

DEFAULT_CHECKPOINT = Path(__file__).with_name("checkpoints") / "default.pt"
"""The depth checkpoint shipped with the package (trained by its own workflow)."""
EFFECTS_CHECKPOINT = Path(__file__).with_name("checkpoints") / "effects.pt"
"""A second shipped checkpoint, trained on frames with intraoperative effects (tools,
blood, smoke, blur, lens smears; ``config/sim_train_effects.yaml``, docs/depth.md)."""

__all__ = [
    "DEFAULT_CHECKPOINT",
    "EFFECTS_CHECKPOINT",
    "RESERVED_EVAL_SEEDS",
    "AugmentConfig",
    "CheckpointError",
    "DepthMetrics",
    "DepthNet",
    "DepthNetConfig",
    "DepthPredictor",
    "FrameSet",
    "MetricAccumulator",
    "NetworkDepthSource",
    "SequenceRef",
    "TrainConfig",
    "TrainResult",
    "depth_loss",
    "evaluate_frames",
    "evaluate_source",
    "export_model",
    "find_sequences",
    "frame_metrics",
    "gradient_matching_loss",
    "load_checkpoint",
    "load_depth_source",
    "load_frames",
    "load_predictor",
    "predict_sequence",
    "save_checkpoint",
    "scale_invariant_log_loss",
    "split_by_group",
    "train",
    "check_training_seeds",
]
