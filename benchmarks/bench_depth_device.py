"""The depth networks on a torch device (a GPU) against this host's CPU, in the same run.

    python benchmarks/bench_depth_device.py [--device cuda] [--threads N] [--steps 40]

Needs only torch, numpy and ``chisel.depth`` (it runs on a GPU machine without the
renderer's packages). On synthetic 320x256 frames (a smooth random texture and a tilted
plane 15-25 mm away as the render; speed does not depend on the content), for the shipped
monocular (``mono``) and change-aware (``change_aware``) checkpoints:

- ``{net}_infer_fps_{cpu,device}``: frames/s at batch 1, scripted, as the updater runs
  them (``load_depth_source`` / ``load_change_aware_source``), host copies included;
- ``{net}_batch16_fps_device``: frames/s at batch 16 (dataset-scale inference);
- ``{net}_device_vs_cpu_rel_p50/p999``: the relative difference of the two devices'
  depths on the same frames (TF32 convolutions on CUDA round to ~1e-3);
- ``change_aware_train_steps_per_s_{cpu,device}``: ``train_change_aware`` steps/s at the
  shipped widths, batch 8, 320x256 (``chisel depth train --kind change-aware --device``).

Prints ``name: value`` lines, ``cpu_simd`` and the torch thread count beside the CPU
figures, and last ``change_aware_train_speedup`` (device steps/s over CPU steps/s).
Without the device it says so and exits 0 having printed the CPU figures only.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from chisel.depth import DEFAULT_CHECKPOINT, load_depth_source
from chisel.depth.change_aware import DEFAULT_CHANGE_CHECKPOINT, load_change_checkpoint
from chisel.depth.change_source import fp32_convolutions, load_change_aware_source
from chisel.depth.change_train import ChangeTrainConfig, PriorSet, train_change_aware

sys.path.insert(0, str(Path(__file__).resolve().parent))
from host import cpu_simd  # noqa: E402

H, W = 256, 320


def frames(n: int, seed: int) -> PriorSet:
    """Smooth random RGB and a tilted plane as the render; the target 5 mm deeper in a
    quarter of each frame (only training reads it)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    rgb = np.empty((n, H, W, 3), np.uint8)
    prior = np.empty((n, H, W), np.float32)
    for i in range(n):
        k = rng.uniform(0.02, 0.08, 3)
        phase = rng.uniform(0, 2 * np.pi, 3)
        gray = 0.5 + 0.25 * np.sin(k[0] * xx + phase[0]) * np.cos(k[1] * yy + phase[1])
        rgb[i] = (np.stack([gray, 0.6 * gray, 0.5 * gray], -1) * 255).astype(np.uint8)
        prior[i] = rng.uniform(15, 25) + 0.02 * (xx - W / 2) + 0.01 * (yy - H / 2)
    target = prior.copy()
    changed = np.zeros_like(prior, bool)
    changed[:, : H // 2, : W // 2] = True
    target[changed] += 5.0
    return PriorSet(
        torch.from_numpy(rgb), torch.from_numpy(prior), torch.from_numpy(target),
        torch.from_numpy(changed), [f"synthetic#{i}" for i in range(n)],
    )  # fmt: skip


def rate(call: Callable[[int], object], n: int, seconds: float, sync: Callable[[], None]) -> float:
    """Calls per second of ``call(i)`` after a warm-up, for about ``seconds``."""
    for i in range(3):
        call(i)
    sync()
    t0, done = time.perf_counter(), 0
    while done < 3 or time.perf_counter() - t0 < seconds:
        call(done % n)
        done += 1
    sync()
    return done / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda", help="torch device to compare with the CPU")
    ap.add_argument("--threads", type=int, default=None, help="CPU torch threads (default: all)")
    ap.add_argument("--steps", type=int, default=40, help="training steps timed per device")
    ap.add_argument("--seconds", type=float, default=3.0, help="inference timing per figure")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    dev = torch.device(args.device)
    has_dev = dev.type == "cuda" and torch.cuda.is_available()
    print(f"cpu_simd: {cpu_simd()}")
    print(f"torch: {torch.__version__}")
    print(f"cpu_threads: {threads}")
    print(f"device: {torch.cuda.get_device_name(dev) if has_dev else 'none'}")

    def sync() -> None:
        if has_dev:
            torch.cuda.synchronize(dev)

    data = frames(16, seed=0)
    rgb, prior = data.rgb.numpy(), data.prior_mm.numpy()
    on = ["cpu"] + [args.device] * has_dev

    def mono_one(s: Any, i: int) -> np.ndarray:
        return s.predict(rgb[i])

    def change_one(s: Any, i: int) -> np.ndarray:
        return s.predict(rgb[i], prior[i])[0]

    def mono_batch(s: Any, i: int) -> object:
        return s.predict_batch(rgb)

    def change_batch(s: Any, i: int) -> object:
        with fp32_convolutions(s.device):  # as ChangeAwareDepthSource runs it
            return s.module(data.rgb.to(s.device), data.prior_mm.to(s.device))

    for name, load, ckpt, one, batch in (
        ("mono", load_depth_source, DEFAULT_CHECKPOINT, mono_one, mono_batch),
        ("change_aware", load_change_aware_source, DEFAULT_CHANGE_CHECKPOINT, change_one,
         change_batch),
    ):  # fmt: skip
        sources = {d: load(ckpt, device=d) for d in on}
        for d, s in sources.items():
            fps = rate(partial(one, s), 16, args.seconds, sync)
            print(f"{name}_infer_fps_{'cpu' if d == 'cpu' else 'device'}: {fps:.1f}")
        if has_dev:
            s = sources[args.device]
            with torch.inference_mode():
                fps = 16 * rate(partial(batch, s), 1, args.seconds, sync)
            print(f"{name}_batch16_fps_device: {fps:.1f}")
            a = np.stack([one(sources["cpu"], i) for i in range(16)])
            b = np.stack([one(s, i) for i in range(16)])
            rel = np.abs(b / a - 1.0)
            rel = rel[np.isfinite(rel)]
            print(f"{name}_device_vs_cpu_rel_p50: {np.median(rel):.2e}")
            print(f"{name}_device_vs_cpu_rel_p999: {np.quantile(rel, 0.999):.2e}")

    net, _ = load_change_checkpoint(DEFAULT_CHANGE_CHECKPOINT)
    steps = {}
    for d in on:
        cfg = ChangeTrainConfig(steps=args.steps, batch_size=8, seed=0, num_threads=threads,
                                eval_every=args.steps, device=d)  # fmt: skip
        train_change_aware(data, ChangeTrainConfig(steps=2, batch_size=8, device=d), net.config)
        result = train_change_aware(data, cfg, net.config)
        steps[d] = args.steps / result.seconds
        print(f"change_aware_train_steps_per_s_{'cpu' if d == 'cpu' else 'device'}: {steps[d]:.2f}")
    if not has_dev:
        print(f"device_missing: {args.device} (torch sees no such device; CPU figures only)")
        return
    print(f"change_aware_train_speedup: {steps[args.device] / steps['cpu']:.1f}")


if __name__ == "__main__":
    main()
