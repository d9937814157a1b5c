"""Wall time of training the default depth model from scratch (goal: <= 20 min on 2 cores).

    python benchmarks/bench_depth_train.py [--workdir DIR] [--epochs 36] [--phantoms 16]

Runs the two commands recorded in the shipped checkpoint's sidecar
(``chisel/depth/checkpoints/default.json``): ``python -m sim dataset`` on training seeds
1000-1015 (disjoint from every evaluation seed), then ``chisel depth train`` with the same
options, into a temporary folder; the shipped checkpoint is not touched. Prints
``name: value`` lines: the rendering time, the per-epoch times, the best validation
abs-rel, and last ``train_min`` (wall minutes of the training command alone, the figure
the goal is about). Heavy (minutes); not part of the test suite. Run it alone: on a shared
machine the epoch times grow several-fold.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--workdir", type=Path, help="keep data and checkpoint here (default: temp)")
    ap.add_argument("--epochs", type=int, default=36)
    ap.add_argument("--phantoms", type=int, default=16, help="training seeds 1000..1000+N-1")
    args = ap.parse_args()
    if args.phantoms < 2:
        ap.error("--phantoms must be >= 2: validation holds out whole phantoms")
    if args.epochs < 1:
        ap.error("--epochs must be >= 1")
    if args.workdir is not None:
        args.workdir.mkdir(parents=True, exist_ok=True)
        return run(args, args.workdir)
    with tempfile.TemporaryDirectory(prefix="chisel-train-") as tmp:
        return run(args, Path(tmp))


def run(args: argparse.Namespace, work: Path) -> int:
    """Render the training set into ``work``, train on it, print the figures."""
    data, ck = work / "data", work / "default.pt"
    seeds = f"1000-{1000 + args.phantoms - 1}"
    py = sys.executable
    t0 = time.perf_counter()
    subprocess.run(
        [py, "-m", "sim", "dataset", "--seeds", seeds, "--out", str(data), "--bites", "1",
         "--frames", "40", "--preop-frames", "40", "--quiet"],
        check=True,
    )  # fmt: skip
    dataset_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    subprocess.run(
        [py, "-m", "chisel", "depth", "train", "--data", str(data), "--out", str(ck),
         "--epochs", str(args.epochs), "--batch-size", "8", "--lr", "0.002", "--seed", "0",
         "--val-fraction", "0.15", "--frame-step", "2", "--threads", "2", "--device", "cpu"],
        check=True,
    )  # fmt: skip
    train_s = time.perf_counter() - t0
    info = json.loads(ck.with_suffix(".json").read_text())["info"]
    hist = info.get("history", [])
    epoch_s = [h["seconds"] for h in hist if "seconds" in h]
    print(f"phantoms: {args.phantoms}")
    print(f"train_frames: {info['num_train_frames']}")
    print(f"val_frames: {info['num_val_frames']}")
    print(f"dataset_min: {dataset_s / 60:.2f}")
    if epoch_s:
        print(f"epoch_s_median: {sorted(epoch_s)[len(epoch_s) // 2]:.1f}")
    print(f"best_epoch: {info['best_epoch']}")
    print(f"val_abs_rel: {info['val_metrics']['abs_rel']:.4f}")
    print(f"load_average_1min: {os.getloadavg()[0]:.1f}")
    print(f"train_min: {train_s / 60:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
