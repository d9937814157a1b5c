"""The depth networks on a CUDA device (``--device cuda``): skipped where torch sees none.

CI has no GPU, so these run only where one is lent (docs/depth.md, "On a GPU"). Each
compares the GPU against the CPU, an independent implementation of the same convolutions
(cuDNN against oneDNN), or against the loss before training. Only torch, numpy,
``chisel.depth`` and ``tests/wall_scenes.py`` are imported, so the file runs on a machine
that has a GPU build of torch and none of the renderer's packages
(``pytest --noconftest tests/test_depth_cuda.py``).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from wall_scenes import wall_pairs

from chisel.depth import DEFAULT_CHECKPOINT, load_depth_source
from chisel.depth.change_aware import (
    DEFAULT_CHANGE_CHECKPOINT,
    ChangeAwarePredictor,
    ChangeNet,
    ChangeNetConfig,
)
from chisel.depth.change_source import load_change_aware_source
from chisel.depth.change_train import ChangeTrainConfig, PriorSet, change_loss, train_change_aware
from chisel.depth.data import FrameSet
from chisel.depth.network import DepthNetConfig
from chisel.depth.train import TrainConfig, train

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

TINY_CHANGE = ChangeNetConfig(widths=(8, 12), input_scale=1.0)
TINY_MONO = DepthNetConfig(widths=(8, 12), blocks=(1, 1), input_scale=1.0)


def test_change_aware_trains_and_validates_on_cuda() -> None:
    pairs, val = wall_pairs(32, seed=1), wall_pairs(8, seed=2)
    cfg = ChangeTrainConfig(
        steps=60, batch_size=8, lr=1e-2, seed=0, num_threads=1, eval_every=30, device="cuda",
        flips=False, photometric=0.0,
    )  # fmt: skip

    def loss_on_cpu(net: ChangeNet) -> float:
        with torch.no_grad():
            r, c = ChangeAwarePredictor(net).eval().raw(val.rgb, val.prior_mm)
        return float(change_loss(r, c, val.prior_mm, val.target_mm, val.changed, cfg)[0])

    torch.manual_seed(0)
    before = loss_on_cpu(ChangeNet(TINY_CHANGE))
    result = train_change_aware(pairs, cfg, TINY_CHANGE, val_pairs=val)
    assert all(p.device.type == "cpu" for p in result.net.parameters())
    assert all(np.isfinite(row["val_abs_rel_near"]) for row in result.history)
    assert result.val_metrics is not None
    assert loss_on_cpu(result.net) < 0.7 * before


def test_monocular_trains_and_validates_on_cuda() -> None:
    def frames(p: PriorSet) -> FrameSet:
        return FrameSet(p.rgb, p.target_mm, torch.ones_like(p.changed), p.sources)

    train_set, val = frames(wall_pairs(32, seed=3)), frames(wall_pairs(8, seed=4))
    cfg = TrainConfig(epochs=6, batch_size=8, lr=1e-2, augment=None, num_threads=1, device="cuda")
    result = train(train_set, cfg, TINY_MONO, val_frames=val)
    assert all(p.device.type == "cpu" for p in result.net.parameters())
    assert result.val_metrics is not None and np.isfinite(result.val_metrics.abs_rel)
    assert result.history[-1]["loss"] < result.history[0]["loss"]


def test_shipped_monocular_network_agrees_on_cuda_and_cpu() -> None:
    rgb = wall_pairs(4, seed=5, h=256, w=320).rgb.numpy()
    cpu = load_depth_source(DEFAULT_CHECKPOINT, device="cpu").predict_batch(rgb)
    gpu = load_depth_source(DEFAULT_CHECKPOINT, device="cuda").predict_batch(rgb)
    rel = np.abs(gpu / cpu - 1.0)
    # TF32 convolutions (torch's default on CUDA) round to ~1e-3; the updater's change
    # threshold is ~3 % of a relative estimate's depth, thirty times more.
    assert np.median(rel) < 1e-3 and np.quantile(rel, 0.999) < 1e-2


def test_shipped_change_aware_network_agrees_on_cuda_and_cpu() -> None:
    pairs = wall_pairs(4, seed=6, h=256, w=320)
    sources = [
        load_change_aware_source(DEFAULT_CHANGE_CHECKPOINT, device=d) for d in ("cpu", "cuda")
    ]
    for rgb, prior in zip(pairs.rgb.numpy(), pairs.prior_mm.numpy(), strict=True):
        (d_cpu, p_cpu), (d_gpu, p_gpu) = (s.predict(rgb, prior) for s in sources)
        assert np.abs(p_gpu - p_cpu).max() < 1e-3
        # In float32 (the source turns cuDNN's TF32 off) no pixel's change decision
        # (p >= 0.5) flips between the devices; TF32 flipped some, up to 9 mm apart.
        ok = np.isfinite(d_cpu)
        assert np.array_equal(ok, np.isfinite(d_gpu))
        assert np.abs(d_gpu - d_cpu)[ok].max() < 0.01
    assert torch.backends.cudnn.allow_tf32  # the global setting is restored
