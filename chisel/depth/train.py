"""Training and per-patient fine-tuning of the depth network on in-memory frames.

Pure functions over :class:`~chisel.depth.data.FrameSet` tensors; reading sequences and
writing checkpoints live in ``chisel.cli.cmd_depth``. Seeded end to end: the weights
init (``torch.manual_seed``), the shuffling and the augmentation (a ``torch.Generator``)
all derive from ``TrainConfig.seed``, with ``torch.use_deterministic_algorithms`` on, so
the same data, config and thread count give the same weights.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import torch
from tqdm import tqdm

from chisel.core.errors import InvalidInputError
from chisel.depth.data import AugmentConfig, FrameSet, augment, downsample_targets
from chisel.depth.losses import depth_loss
from chisel.depth.metrics import DepthMetrics, MetricAccumulator
from chisel.depth.network import DepthNet, DepthNetConfig, DepthPredictor
from chisel.depth.optim import (
    BestWeights,
    RunningMeans,
    check_config,
    check_weights,
    optimizer,
    out_of_time,
    set_train_mode,
    take_step,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings for :func:`train` (defaults: training from scratch)."""

    epochs: int = 30
    """Passes over the training frames."""
    batch_size: int = 8
    """Frames per optimisation step."""
    lr: float = 2e-3
    """Peak learning rate (AdamW, one-cycle schedule)."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    warmup_fraction: float = 0.1
    """Fraction of the steps spent warming the learning rate up (one-cycle)."""
    si_lambda: float = 0.85
    """Eigen's lambda in the scale-invariant loss (1 = fully scale-invariant)."""
    grad_weight: float = 0.5
    """Weight of the multi-scale gradient-matching term."""
    grad_scales: int = 4
    """Scales of the gradient-matching term."""
    freeze_batchnorm: bool = False
    """Keep BatchNorm statistics fixed (fine-tuning on few frames)."""
    seed: int = 0
    """Seeds weights init, shuffling and augmentation."""
    augment: AugmentConfig | None = field(default_factory=AugmentConfig)
    """Augmentation, or None for none."""
    max_minutes: float | None = None
    """Stop after the epoch that passes this wall time (a safety cap; breaks determinism
    only when it triggers, which the result records)."""
    num_threads: int | None = 2
    """``torch.set_num_threads`` while training (None: leave as is)."""
    device: str = "cpu"
    """Torch device: "cpu", "cuda", "cuda:1", ..."""

    def __post_init__(self) -> None:
        check_config(
            self,
            {
                "epochs": self.epochs >= 1,
                "si_lambda": 0.0 <= self.si_lambda <= 1.0,
                "grad_weight": self.grad_weight >= 0,
                "grad_scales": self.grad_scales >= 1,
            },
        )

    @classmethod
    def finetune_defaults(cls, **overrides: Any) -> TrainConfig:
        """Per-patient fine-tuning: few epochs, small learning rate, frozen BatchNorm."""
        base = cls(epochs=3, lr=1e-4, warmup_fraction=0.0, freeze_batchnorm=True)
        return replace(base, **overrides)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class TrainResult:
    """What :func:`train` returns."""

    net: DepthNet
    """The trained network (best validation epoch when there is validation), eval mode."""
    history: list[dict[str, float]]
    """Per epoch: train loss and its terms, validation metrics, learning rate, seconds."""
    val_metrics: DepthMetrics | None
    """Validation metrics of the returned weights (None without validation frames)."""
    best_epoch: int
    """Epoch (1-based) whose weights were returned."""
    stopped_early: bool
    """True if ``max_minutes`` cut training short."""
    seconds: float
    """Wall time of the whole run."""
    cpu_seconds: float
    """CPU time of this process over the run (all threads); on a shared machine the wall
    time grows with the load, this does not as much."""


def resolve_device(name: str) -> torch.device:
    """A torch device from a name; a CUDA device must actually be available."""
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise InvalidInputError("--device", f"unknown device {name!r}: {exc}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InvalidInputError("--device", f"{name!r} requested but CUDA is not available here")
    if device.type not in ("cpu", "cuda"):
        raise InvalidInputError("--device", f"expected cpu or cuda[:N], got {name!r}")
    return device


@contextlib.contextmanager
def deterministic(seed: int, device: torch.device, num_threads: int | None) -> Iterator[None]:
    """Seed torch, turn deterministic algorithms on (warn-only on CUDA), restore after."""
    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    prev_threads = torch.get_num_threads()
    # fill_uninitialized_memory is a property of the module's class (torch swaps it in),
    # which type checkers cannot see: hence the attr-defined ignores.
    prev_fill = torch.utils.deterministic.fill_uninitialized_memory  # type: ignore[attr-defined]
    torch.use_deterministic_algorithms(True, warn_only=device.type == "cuda")
    # Deterministic mode NaN-fills every new empty tensor (a quarter of a CPU training step
    # here); results never read uninitialised memory, so the fill buys nothing.
    torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]
    if num_threads is not None:
        torch.set_num_threads(num_threads)
    torch.manual_seed(seed)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev_det, warn_only=prev_warn)
        torch.set_num_threads(prev_threads)
        torch.utils.deterministic.fill_uninitialized_memory = prev_fill  # type: ignore[attr-defined]


@torch.inference_mode()
def evaluate_frames(
    predictor: DepthPredictor | torch.nn.Module,
    frames: FrameSet,
    device: torch.device | str = "cpu",
    batch_size: int = 8,
) -> DepthMetrics:
    """Median-scaled metrics of ``predictor`` on in-memory frames (see ``metrics``)."""
    device = torch.device(device)
    was_training = predictor.training
    predictor.eval()
    acc = MetricAccumulator()
    for start in range(0, len(frames), batch_size):
        rgb = frames.rgb[start : start + batch_size].to(device)
        pred = predictor(rgb).float().cpu().numpy()
        gt = frames.depth_mm[start : start + batch_size].numpy()
        valid = frames.valid[start : start + batch_size].numpy()
        for p, g, v in zip(pred, gt, valid, strict=True):
            acc.add(p, g, v)
    predictor.train(was_training)
    return acc.result()


def train(
    frames: FrameSet,
    cfg: TrainConfig,
    net_config: DepthNetConfig | None = None,
    init: DepthNet | None = None,
    val_frames: FrameSet | None = None,
    progress: bool = False,
) -> TrainResult:
    """Train a depth network (from scratch, or from ``init`` to fine-tune it).

    frames : training frames (RGB uint8, depth mm, validity). val_frames : optional
    held-out frames; the epoch with the lowest validation abs-rel is returned.
    net_config : architecture for a new network (ignored when ``init`` is given).
    ``init`` is not modified; a copy is trained. A non-finite loss or weights stop the
    run with :class:`~chisel.core.errors.TrainingDivergedError` (nothing is returned to
    save, so an earlier checkpoint is kept).
    """
    if len(frames) == 0:
        raise InvalidInputError("frames", "no training frames")
    device = resolve_device(cfg.device)
    t0 = time.perf_counter()
    c0 = time.process_time()
    with deterministic(cfg.seed, device, cfg.num_threads):
        net = copy.deepcopy(init) if init is not None else DepthNet(net_config)
        # Module.to accepts memory_format at run time; torch's overloads of it omit it
        net = net.to(device).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        predictor = DepthPredictor(net).to(device)
        n = len(frames)
        bs = min(cfg.batch_size, n)
        steps_per_epoch = n // bs  # the incomplete last batch is dropped (BatchNorm, speed)
        opt, sched = optimizer(
            net, cfg.lr, cfg.weight_decay, cfg.warmup_fraction, steps_per_epoch * cfg.epochs
        )
        # The loss is computed on the network's own (coarser) grid: cheaper, and the
        # bilinear upsampling to full size adds nothing to learn.
        net_hw = predictor.net_size(int(frames.rgb.shape[1]), int(frames.rgb.shape[2]))
        depth_t, valid_t = downsample_targets(frames.depth_mm, frames.valid, net_hw)
        gen = torch.Generator().manual_seed(cfg.seed)
        history: list[dict[str, float]] = []
        best = BestWeights()
        means = RunningMeans(("loss", "si", "grad"))
        stopped_early = False
        epochs = tqdm(range(1, cfg.epochs + 1), desc="depth train", disable=not progress)
        for epoch in epochs:
            te = time.perf_counter()
            set_train_mode(net, cfg.freeze_batchnorm)
            perm = torch.randperm(n, generator=gen)
            for s in range(steps_per_epoch):
                idx = perm[s * bs : (s + 1) * bs]
                rgb, depth, valid = frames.rgb[idx], depth_t[idx], valid_t[idx]
                if cfg.augment is not None:
                    rgb, depth, valid = augment(rgb, depth, valid, cfg.augment, gen)
                rgb, depth, valid = rgb.to(device), depth.to(device), valid.to(device)
                log_pred = predictor.log_depth(rgb, full_res=False)[:, 0]
                loss, parts = depth_loss(
                    log_pred, depth, valid, cfg.si_lambda, cfg.grad_weight, cfg.grad_scales
                )
                loss_value = take_step(opt, sched, loss, f"epoch {epoch}, step {s + 1}", cfg.lr)
                means.add(loss_value, parts)
            check_weights(net, f"epoch {epoch}", cfg.lr)
            row = means.pop()
            row["epoch"] = epoch
            row["lr"] = float(opt.param_groups[0]["lr"])
            if val_frames is not None and len(val_frames) > 0:
                m = evaluate_frames(predictor, val_frames, device)
                row.update({f"val_{k}": float(v) for k, v in m.to_dict().items()})
                best.offer(m.abs_rel, epoch, net)
            row["seconds"] = time.perf_counter() - te
            history.append(row)
            log.info(
                "epoch %d/%d loss %.4f (si %.4f grad %.4f)%s %.1f s",
                epoch,
                cfg.epochs,
                row["loss"],
                row["si"],
                row["grad"],
                f" val abs_rel {row['val_abs_rel']:.4f}" if "val_abs_rel" in row else "",
                row["seconds"],
            )
            epochs.set_postfix(loss=f"{row['loss']:.4f}")
            if out_of_time(t0, cfg.max_minutes):
                stopped_early = epoch < cfg.epochs
                if stopped_early:
                    log.warning("max_minutes=%s reached after epoch %d", cfg.max_minutes, epoch)
                break
        best_epoch = best.restore(net, last=int(history[-1]["epoch"]))
        net = net.to("cpu").to(memory_format=torch.contiguous_format).eval()
        val_metrics = None
        if val_frames is not None and len(val_frames) > 0:
            val_metrics = evaluate_frames(DepthPredictor(net).eval(), val_frames, "cpu")
    return TrainResult(
        net=net,
        history=history,
        val_metrics=val_metrics,
        best_epoch=int(best_epoch),
        stopped_early=stopped_early,
        seconds=time.perf_counter() - t0,
        cpu_seconds=time.process_time() - c0,
    )
