"""Training and per-patient fine-tuning of the change-aware network on in-memory pairs.

Pure functions over :class:`PriorSet` tensors (building them from sequences and meshes is
``chisel.depth.prior_data``; checkpoints are written by the CLI). Seeded end to end like
the monocular trainer (``chisel.depth.train.deterministic``): same data, config and
thread count -> same weights.

Loss, over pixels where the render, the target and the frame mask are all valid:

- ``|log(depth) - log(target)|`` (L1 on the log-ratio; metric, not scale-invariant: the
  render carries the scale), weighted ``1 + change_weight`` on changed pixels so the few
  pixels of a removal are not drowned by the unchanged ones;
- ``bce_weight *`` binary cross-entropy of the change logit against the change label
  (target deeper than the previous surface seen from the *true* pose by more than
  ``PriorSet``'s threshold).
"""

from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from chisel.core.errors import InvalidInputError
from chisel.depth.change_aware import ChangeAwarePredictor, ChangeNet, ChangeNetConfig
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
from chisel.depth.train import deterministic, resolve_device

log = logging.getLogger(__name__)


@dataclass
class PriorSet:
    """Frames with their prior (the previous surface rendered at the tracked pose)."""

    rgb: torch.Tensor
    """(N, H, W, 3) uint8 RGB."""
    prior_mm: torch.Tensor
    """(N, H, W) float32 z-depth of the previous surface at the *tracked* pose, NaN = miss."""
    target_mm: torch.Tensor
    """(N, H, W) float32 true z-depth, mm, NaN = invalid (or outside the frame mask)."""
    changed: torch.Tensor
    """(N, H, W) bool: the target lies deeper than the previous surface seen from the
    true pose by more than the change threshold (tissue removed at this pixel)."""
    sources: list[str]
    """``"<sequence folder>#<frame>"`` per frame."""
    true_mm: torch.Tensor | None = None
    """(N, H, W) float32 the frames' true depth (true pose), mm, NaN = invalid, when known
    (reporting only; the target may be the tracked-pose render instead)."""

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    def __post_init__(self) -> None:
        n, h, w = self.prior_mm.shape
        for name, t in (("target_mm", self.target_mm), ("changed", self.changed)):
            if tuple(t.shape) != (n, h, w):
                raise InvalidInputError(
                    f"PriorSet.{name}", f"shape {tuple(t.shape)} != {(n, h, w)}"
                )
        if tuple(self.rgb.shape) != (n, h, w, 3):
            raise InvalidInputError(
                "PriorSet.rgb", f"shape {tuple(self.rgb.shape)} != {(n, h, w, 3)}"
            )


@dataclass(frozen=True)
class ChangeTrainConfig:
    """Optimisation settings for :func:`train_change_aware`."""

    steps: int = 600
    """Optimisation steps (batches); the run is bounded by steps, not epochs."""
    batch_size: int = 8
    """Frames per step."""
    lr: float = 3e-3
    """Peak learning rate (AdamW, one-cycle)."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    warmup_fraction: float = 0.1
    """Fraction of the steps warming the learning rate up (0: cosine decay from the peak)."""
    change_weight: float = 4.0
    """Extra weight of changed pixels in the depth loss."""
    bce_weight: float = 0.1
    """Weight of the change-logit cross-entropy."""
    freeze_batchnorm: bool = False
    """Keep BatchNorm statistics fixed (fine-tuning on one patient's few frames)."""
    flips: bool = True
    """Seeded horizontal/vertical flips of frame, prior and target together."""
    photometric: float = 0.2
    """Gain and contrast jitter U(1 - a, 1 + a) of the RGB (0: none)."""
    seed: int = 0
    """Seeds the weights, the batch draws and the augmentation."""
    max_minutes: float | None = None
    """Stop after the step that passes this wall time (recorded as ``stopped_early``)."""
    eval_every: int = 100
    """Validate every this many steps (with validation pairs); the best is returned."""
    num_threads: int | None = 2
    """``torch.set_num_threads`` while training (None: leave as is)."""
    device: str = "cpu"
    """Torch device: "cpu", "cuda", "cuda:1", ..."""

    def __post_init__(self) -> None:
        check_config(
            self,
            {
                "steps": self.steps >= 1,
                "change_weight": self.change_weight >= 0,
                "bce_weight": self.bce_weight >= 0,
                "photometric": 0.0 <= self.photometric < 1.0,
                "eval_every": self.eval_every >= 1,
            },
        )

    @classmethod
    def finetune_defaults(cls, **overrides: Any) -> ChangeTrainConfig:
        """Per-patient fine-tuning: few steps, small learning rate, frozen BatchNorm, and no
        change-logit loss: the preop sweep has no change, so that loss would only teach the
        head "nothing ever changes" (on the smoke experiment it drove the change probability
        from <= 0.59 to <= 0.29 in 60 steps, and the gated output with it)."""
        base = cls(steps=60, lr=2e-4, warmup_fraction=0.0, freeze_batchnorm=True, bce_weight=0.0)
        return replace(base, **overrides)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class ChangeTrainResult:
    """What :func:`train_change_aware` returns."""

    net: ChangeNet
    """The trained network (best validation when there is validation), eval mode, CPU."""
    history: list[dict[str, float]]
    """Per evaluation point: step, mean train loss since the last point, val metrics."""
    val_metrics: dict[str, float] | None
    """Validation metrics of the returned weights (:func:`change_metrics`)."""
    best_step: int
    """Step whose weights were returned."""
    stopped_early: bool
    """True if ``max_minutes`` cut training short."""
    seconds: float
    """Wall time of the run."""


def change_loss(
    r: torch.Tensor,
    c: torch.Tensor,
    prior_mm: torch.Tensor,
    target_mm: torch.Tensor,
    changed: torch.Tensor,
    cfg: ChangeTrainConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of one batch. r, c : (B, 1, H, W) from :meth:`ChangeAwarePredictor.raw`;
    prior_mm, target_mm : (B, H, W) mm, NaN = invalid; changed : (B, H, W) bool."""
    valid = torch.isfinite(prior_mm) & (prior_mm > 0) & torch.isfinite(target_mm) & (target_mm > 0)
    if not bool(valid.any()):
        zero = (r.sum() + c.sum()) * 0.0
        return zero, {"depth": 0.0, "bce": 0.0}
    one = torch.ones_like(prior_mm)
    log_ratio = torch.log(torch.where(valid, target_mm, one)) - torch.log(
        torch.where(valid, prior_mm, one)
    )
    w = valid.float() * (1.0 + cfg.change_weight * changed.float())
    depth = (w * (r[:, 0] - log_ratio).abs()).sum() / w.sum()
    bce_map = F.binary_cross_entropy_with_logits(c[:, 0], changed.float(), reduction="none")
    bce = (bce_map * valid.float()).sum() / valid.float().sum()
    loss = depth + cfg.bce_weight * bce
    return loss, {"depth": float(depth.detach()), "bce": float(bce.detach())}


def _augment(
    rgb: torch.Tensor,
    prior: torch.Tensor,
    target: torch.Tensor,
    changed: torch.Tensor,
    cfg: ChangeTrainConfig,
    gen: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    b = rgb.shape[0]
    u = torch.rand(b, 4, generator=gen)
    x = rgb.float()
    if cfg.flips:
        for dim_img, dim_map, col in ((2, 2, 0), (1, 1, 1)):
            f = u[:, col] < 0.5
            if bool(f.any()):
                x[f] = x[f].flip(dim_img)
                prior, target, changed = prior.clone(), target.clone(), changed.clone()
                prior[f] = prior[f].flip(dim_map)
                target[f] = target[f].flip(dim_map)
                changed[f] = changed[f].flip(dim_map)
    if cfg.photometric > 0:
        gain = 1.0 + cfg.photometric * (2.0 * u[:, 2] - 1.0)
        contrast = 1.0 + cfg.photometric * (2.0 * u[:, 3] - 1.0)
        mean = x.mean(dim=(1, 2, 3), keepdim=True)
        x = ((x - mean) * contrast.view(b, 1, 1, 1) + mean) * gain.view(b, 1, 1, 1)
    return x.clamp(0.0, 255.0), prior, target, changed


def change_metrics(
    depth_mm: np.ndarray,
    target_mm: np.ndarray,
    changed: np.ndarray,
    near_px: int = 8,
) -> dict[str, float]:
    """Per-frame abs-rel of metric depth near the change and on unchanged tissue.

    depth_mm, target_mm : (H, W) float32 mm, NaN = invalid. changed : (H, W) bool.
    "near" = the changed pixels dilated by ``near_px`` (a square); "unchanged" = the
    valid pixels outside it. No scale is solved (the depth is metric). NaN when a region
    has no valid pixel.
    """
    import cv2  # noqa: PLC0415

    valid = np.isfinite(depth_mm) & np.isfinite(target_mm) & (target_mm > 0)
    k = 2 * near_px + 1
    near = cv2.dilate(changed.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    rel = np.abs(depth_mm - target_mm) / np.where(valid, target_mm, 1.0)
    out = {}
    for name, region in (("near", near & valid), ("unchanged", ~near & valid)):
        out[f"abs_rel_{name}"] = float(rel[region].mean()) if region.any() else float("nan")
        out[f"pixels_{name}"] = int(region.sum())
    return out


@torch.inference_mode()
def evaluate_pairs(
    predictor: ChangeAwarePredictor,
    pairs: PriorSet,
    batch_size: int = 8,
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """Mean per-frame abs-rel near the change and on unchanged tissue (NaN-frames skipped).

    device : where ``predictor`` is; the pairs stay in host memory and go there by batch."""
    device = torch.device(device)
    was = predictor.training
    predictor.eval()
    near, unch = [], []
    for a in range(0, len(pairs), batch_size):
        depth, _ = predictor(
            pairs.rgb[a : a + batch_size].to(device), pairs.prior_mm[a : a + batch_size].to(device)
        )
        for d, t, ch in zip(
            depth.float().cpu().numpy(), pairs.target_mm[a : a + batch_size].numpy(),
            pairs.changed[a : a + batch_size].numpy(), strict=True,
        ):  # fmt: skip
            m = change_metrics(d, t, ch)
            if math.isfinite(m["abs_rel_near"]) and ch.any():
                near.append(m["abs_rel_near"])
            if math.isfinite(m["abs_rel_unchanged"]):
                unch.append(m["abs_rel_unchanged"])
    predictor.train(was)
    n = float(np.mean(near)) if near else float("nan")
    u = float(np.mean(unch)) if unch else float("nan")
    score = (n if near else 0.0) + (u if unch else 0.0)
    return {"abs_rel_near": n, "abs_rel_unchanged": u, "frames_near": len(near), "score": score}


def train_change_aware(
    pairs: PriorSet,
    cfg: ChangeTrainConfig,
    net_config: ChangeNetConfig | None = None,
    init: ChangeNet | None = None,
    val_pairs: PriorSet | None = None,
    progress: bool = False,
) -> ChangeTrainResult:
    """Train the change-aware network (from scratch, or a copy of ``init`` to fine-tune).

    Batches are drawn by a seeded permutation (epochs without end until ``cfg.steps``).
    A non-finite loss (or weights at the end) stops with
    :class:`~chisel.core.errors.TrainingDivergedError`, as in the monocular trainer.
    """
    if len(pairs) == 0:
        raise InvalidInputError("pairs", "no training frames")
    device = resolve_device(cfg.device)
    t0 = time.perf_counter()
    with deterministic(cfg.seed, device, cfg.num_threads):
        net = copy.deepcopy(init) if init is not None else ChangeNet(net_config)
        net = net.to(device)
        predictor = ChangeAwarePredictor(net).to(device)
        n = len(pairs)
        bs = min(cfg.batch_size, n)
        opt, sched = optimizer(net, cfg.lr, cfg.weight_decay, cfg.warmup_fraction, cfg.steps)
        gen = torch.Generator().manual_seed(cfg.seed)
        perm = torch.randperm(n, generator=gen)
        cursor = 0
        history: list[dict[str, float]] = []
        best = BestWeights()
        means = RunningMeans(("loss", "depth", "bce"))
        stopped_early = False
        last_step = 0
        bar = tqdm(range(1, cfg.steps + 1), desc="change-aware train", disable=not progress)
        set_train_mode(net, cfg.freeze_batchnorm)
        for step in bar:
            if cursor + bs > n:
                perm, cursor = torch.randperm(n, generator=gen), 0
            idx = perm[cursor : cursor + bs]
            cursor += bs
            rgb, prior, target, changed = _augment(
                pairs.rgb[idx], pairs.prior_mm[idx], pairs.target_mm[idx], pairs.changed[idx],
                cfg, gen,
            )  # fmt: skip
            rgb, prior, target, changed = (t.to(device) for t in (rgb, prior, target, changed))
            r, c = predictor.raw(rgb, prior)
            loss, parts = change_loss(r, c, prior, target, changed, cfg)
            means.add(take_step(opt, sched, loss, f"step {step}", cfg.lr), parts)
            last_step = step
            timed_out = out_of_time(t0, cfg.max_minutes)
            if step % cfg.eval_every == 0 or step == cfg.steps or timed_out:
                row = means.pop()
                row["step"] = step
                row["lr"] = float(opt.param_groups[0]["lr"])
                row["seconds"] = time.perf_counter() - t0
                if val_pairs is not None and len(val_pairs) > 0:
                    m = evaluate_pairs(predictor, val_pairs, device=device)
                    set_train_mode(net, cfg.freeze_batchnorm)
                    row.update({f"val_{k}": float(v) for k, v in m.items()})
                    best.offer(m["score"], step, net)
                history.append(row)
                log.info("step %d/%d %s", step, cfg.steps, {k: round(v, 5) for k, v in row.items()})
                bar.set_postfix(loss=f"{row['loss']:.4f}")
            if timed_out:
                stopped_early = step < cfg.steps
                log.warning("max_minutes=%s reached after step %d", cfg.max_minutes, step)
                break
        check_weights(net, f"step {last_step}", cfg.lr)
        best_step = best.restore(net, last=last_step)
        net = net.to("cpu").eval()
        val_metrics = None
        if val_pairs is not None and len(val_pairs) > 0:
            val_metrics = evaluate_pairs(ChangeAwarePredictor(net).eval(), val_pairs)
    return ChangeTrainResult(
        net=net,
        history=history,
        val_metrics=val_metrics,
        best_step=int(best_step),
        stopped_early=stopped_early,
        seconds=time.perf_counter() - t0,
    )
