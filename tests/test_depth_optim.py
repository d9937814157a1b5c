"""chisel.depth.optim: the optimisation both depth trainers share (hand values, and the
divergence stop seen through each trainer)."""

from __future__ import annotations

import math

import pytest
import torch

from chisel.core.errors import InvalidInputError, TrainingDivergedError
from chisel.depth.change_aware import ChangeNet
from chisel.depth.change_train import ChangeTrainConfig, train_change_aware
from chisel.depth.optim import BestWeights, RunningMeans, check_config, optimizer
from chisel.depth.train import TrainConfig


def _lrs(warmup: float, total: int, lr: float = 0.1) -> list[float]:
    net = torch.nn.Linear(2, 1)
    opt, sched = optimizer(net, lr, 0.0, warmup, total)
    out = []
    for _ in range(total):
        out.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    return out


def test_cosine_schedule_hand_values() -> None:
    # 0.5 * (1 + cos(pi * s / 4)) for s = 0..3
    expected = [0.1 * 0.5 * (1 + math.cos(math.pi * s / 4)) for s in range(4)]
    assert _lrs(0.0, 4) == pytest.approx(expected, rel=1e-12)


def test_one_cycle_peaks_at_the_end_of_warmup() -> None:
    lrs = _lrs(0.25, 8)
    # torch's one-cycle: starts at lr / 25, peaks at step pct_start * total - 1 = 1
    assert lrs[0] == pytest.approx(0.1 / 25)
    assert max(lrs) == pytest.approx(0.1) and lrs.index(max(lrs)) == 1


def test_a_single_step_runs_at_the_peak_rate() -> None:
    # one-cycle over one step would run at lr / 2.5e5; the cosine schedule starts at lr
    assert _lrs(0.1, 1) == [pytest.approx(0.1)]


def test_running_means_and_reset() -> None:
    m = RunningMeans(("loss", "a"))
    m.add(1.0, {"a": 2.0})
    m.add(3.0, {"a": 6.0})
    assert m.pop() == {"loss": 2.0, "a": 4.0}
    m.add(5.0, {"a": 1.0})
    assert m.pop() == {"loss": 5.0, "a": 1.0}


def test_best_weights_keeps_the_lowest_and_restores_it() -> None:
    net = torch.nn.Linear(1, 1, bias=False)
    best = BestWeights()
    assert best.restore(net, last=9) == 9  # nothing offered: the last weights stay
    for at, (w, score) in enumerate([(1.0, float("nan")), (2.0, 0.5), (3.0, 0.7)], start=1):
        net.weight.data.fill_(w)
        best.offer(score, at, net)
    assert best.restore(net, last=3) == 2 and float(net.weight) == 2.0


def test_config_checks_name_the_field() -> None:
    with pytest.raises(InvalidInputError, match=r"TrainConfig\.lr: invalid value -1"):
        TrainConfig(lr=-1.0)
    with pytest.raises(InvalidInputError, match=r"ChangeTrainConfig\.eval_every"):
        ChangeTrainConfig(eval_every=0)
    # The shared fields are checked alike for both (the monocular config took lr=inf).
    for cls in (TrainConfig, ChangeTrainConfig):
        with pytest.raises(InvalidInputError, match=rf"{cls.__name__}\.lr: invalid value inf"):
            cls(lr=math.inf)
        with pytest.raises(InvalidInputError, match=rf"{cls.__name__}\.num_threads"):
            cls(num_threads=0)
    with pytest.raises(InvalidInputError, match=r"TrainConfig\.epochs"):
        check_config(TrainConfig(), {"epochs": False})  # a config's own check


def test_change_aware_training_stops_at_a_nan_loss() -> None:
    from test_change_depth import TINY, wall_pairs

    init = ChangeNet(TINY)
    with torch.no_grad():
        next(init.parameters()).fill_(float("nan"))
    cfg = ChangeTrainConfig(steps=3, batch_size=4, num_threads=1)
    with pytest.raises(TrainingDivergedError, match="training diverged at step 1: the loss is nan"):
        train_change_aware(wall_pairs(4, seed=0), cfg, init=init)
