"""The optimisation both depth trainers share (:func:`chisel.depth.train.train`, the
monocular network; :func:`chisel.depth.change_train.train_change_aware`, the change-aware
one): config checks, optimiser and schedule, train mode, running loss means, keeping the
best validated weights, the wall-time cap and the divergence stop.

The two loops differ in what a batch is and when they validate (per epoch, every N
steps); everything here must stay the same for both, so that a fix made for one network
reaches the other.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping
from typing import Protocol

import torch

from chisel.core.errors import InvalidInputError, TrainingDivergedError
from chisel.depth.checkpoint import nonfinite_tensors


class OptimSettings(Protocol):
    """The fields every trainer's config has (``TrainConfig``, ``ChangeTrainConfig``)."""

    @property
    def batch_size(self) -> int: ...
    @property
    def lr(self) -> float: ...
    @property
    def weight_decay(self) -> float: ...
    @property
    def warmup_fraction(self) -> float: ...
    @property
    def max_minutes(self) -> float | None: ...
    @property
    def num_threads(self) -> int | None: ...


def check_config(cfg: OptimSettings, own: Mapping[str, bool]) -> None:
    """Check the shared optimisation fields, then the config's ``own`` checks (field ->
    passed); raise :class:`InvalidInputError` naming ``Class.field`` at the first failure."""
    checks = {
        "batch_size": cfg.batch_size >= 1,
        "lr": cfg.lr > 0 and math.isfinite(cfg.lr),
        "weight_decay": cfg.weight_decay >= 0,
        "warmup_fraction": 0.0 <= cfg.warmup_fraction < 1.0,
        "max_minutes": cfg.max_minutes is None or cfg.max_minutes > 0,
        "num_threads": cfg.num_threads is None or cfg.num_threads >= 1,
        **own,
    }
    for name, ok in checks.items():
        if not ok:
            raise InvalidInputError(
                f"{type(cfg).__name__}.{name}", f"invalid value {getattr(cfg, name)!r}"
            )


def optimizer(
    net: torch.nn.Module, lr: float, weight_decay: float, warmup_fraction: float, total_steps: int
) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
    """AdamW with a one-cycle schedule (``warmup_fraction`` of the steps warming up), or,
    without warm-up, cosine decay from the peak ``lr`` to 0 over ``total_steps``.

    A one-step run takes the cosine schedule: one-cycle's single step would run at its
    final rate, ``lr / 2.5e5``, i.e. not train at all.
    """
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)
    if warmup_fraction > 0 and total_steps > 1:
        sched: torch.optim.lr_scheduler.LRScheduler = torch.optim.lr_scheduler.OneCycleLR(
            opt, max_lr=lr, total_steps=total_steps, pct_start=warmup_fraction
        )
    else:
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda s: 0.5 * (1.0 + math.cos(math.pi * min(s, total_steps) / total_steps))
        )
    return opt, sched


def set_train_mode(net: torch.nn.Module, freeze_batchnorm: bool) -> None:
    """Train mode; with ``freeze_batchnorm`` the BatchNorm layers keep their statistics
    (fine-tuning on one patient's few frames would otherwise overwrite them)."""
    net.train()
    if freeze_batchnorm:
        for m in net.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.eval()


class RunningMeans:
    """Sums of the loss and its terms over the steps since the last :meth:`pop`."""

    def __init__(self, keys: Iterable[str]) -> None:
        self._sums = dict.fromkeys(keys, 0.0)
        self._count = 0

    def add(self, loss: float, parts: Mapping[str, float]) -> None:
        self._sums["loss"] += loss
        for k, v in parts.items():
            self._sums[k] += v
        self._count += 1

    def pop(self) -> dict[str, float]:
        """The means since the last pop (keys in the order given), then start again."""
        means = {k: v / self._count for k, v in self._sums.items()}
        self._sums = dict.fromkeys(self._sums, 0.0)
        self._count = 0
        return means


class BestWeights:
    """The weights of the best validation so far: the lowest score. A NaN score (no valid
    pixel to validate on) is kept only until a number is offered: ``x < nan`` is False,
    so comparing alone would let a first NaN shut out every later epoch."""

    def __init__(self) -> None:
        self.score = math.inf
        self.at: int | None = None
        self._state: dict[str, torch.Tensor] | None = None

    def offer(self, score: float, at: int, net: torch.nn.Module) -> None:
        if self._state is None or score < self.score or math.isnan(self.score):
            self._state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            self.score, self.at = score, at

    def restore(self, net: torch.nn.Module, last: int) -> int:
        """Load the best weights into ``net`` (if any were offered); the epoch or step
        whose weights ``net`` now holds (``last`` when none were offered)."""
        if self._state is None or self.at is None:
            return last
        net.load_state_dict(self._state)
        return self.at


def out_of_time(t0: float, max_minutes: float | None) -> bool:
    """True once ``max_minutes`` of wall time have passed since ``t0`` (perf_counter)."""
    return max_minutes is not None and time.perf_counter() - t0 > 60.0 * max_minutes


def diverged(where: str, what: str, lr: float) -> TrainingDivergedError:
    """The error that stops a run at a non-finite loss or weights (nothing is returned,
    so nothing is saved and an earlier checkpoint at the output path survives)."""
    return TrainingDivergedError(
        f"training diverged at {where}: {what} (learning rate {lr:g} too high?); "
        "stopped without saving, so an earlier checkpoint at the output path is kept"
    )


def take_step(
    opt: torch.optim.Optimizer,
    sched: torch.optim.lr_scheduler.LRScheduler,
    loss: torch.Tensor,
    where: str,
    lr: float,
) -> float:
    """One optimisation step on ``loss``; its value, or :func:`diverged` when it is NaN or
    infinite (checked before the step, so the weights stay finite)."""
    value = float(loss.detach())
    if not math.isfinite(value):
        raise diverged(where, f"the loss is {value}", lr)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    sched.step()
    return value


def check_weights(net: torch.nn.Module, where: str, lr: float) -> None:
    """Raise :func:`diverged` when a weight tensor holds NaN or inf."""
    bad = nonfinite_tensors(dict(net.state_dict()))
    if bad:
        raise diverged(where, f"{len(bad)} weight tensor(s) hold NaN/inf", lr)
