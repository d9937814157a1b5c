"""Benchmark: how much of the removal the frames see, the removed-tissue Dice that bounds,
beside the exact-depth row's Dice.

An update carves what its frames see. A truly removed voxel (tissue in the preoperative
label CT, air in the step's) that no frame of the steps so far sees in front of the
visible surface (true pose, true depth, by more than half a voxel) lies behind tissue
that stays; only inference frees it (the rim rule, fusion's truncation band), so the
Dice of carving exactly the seen voxels is a reference for what the views allow, not a
strict bound. For each seed and step of a finished workflow run (`table` or `all`), on
the preoperative model's grid (`chisel.eval.volume`, the evaluation's truth):

- ``removed_seen_fraction``: the seen share of the removal;
- ``dice_bound``: the Dice of carving exactly the seen voxels and nothing else;
- ``exact_dice``: the `depth_ablation` row's removed-tissue Dice (the peer, same run);
- ``seen_left``: seen voxels the exact row left as tissue.

Prints ``name: value`` lines per seed and step, then ``cpu_simd``, ``elapsed_s`` and, last,
``removal_dice_bound_min`` (the lowest bound of any seed and step; issue 19 asks exact
depth for Dice >= 0.85).

    .venv/bin/python benchmarks/bench_removal_bound.py --run /tmp/fid/results/table --seeds 0-4
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chisel.core.geometry import transform_points  # noqa: E402
from chisel.eval.volume import dice, model_removal, seen_free, true_removal  # noqa: E402
from chisel.io.ct import read_ct_volume  # noqa: E402
from chisel.io.sequence import Sequence  # noqa: E402
from chisel.model import TsdfModel  # noqa: E402
from sim.dataset import parse_seeds  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from host import cpu_simd  # noqa: E402

EXACT = "depth_ablation"


def seed_bounds(seed_dir: Path, steps: list[int]) -> dict[str, float]:
    """Figures of one seed's steps (see the module doc)."""
    pre = TsdfModel.load(seed_dir / "preop" / "model.npz")
    ct = seed_dir / "phantom" / "ct"
    c0 = read_ct_volume(ct / "step_00_label.nii.gz", "label")
    margin_mm = 0.5 * float(pre.voxel_size_mm)
    out: dict[str, float] = {}
    views: list[tuple[Sequence, np.ndarray, np.ndarray]] = []  # each step's frames, read once
    for k in range(1, max(steps) + 1):
        seq = Sequence(seed_dir / "render" / f"step_{k:02d}")
        if seq.true_poses is None:
            raise SystemExit(f"{seq.path}: no true poses (a rendered sequence is needed)")
        views.append((seq, seq.true_poses, np.stack([seq.depth_mm(i) for i in range(len(seq))])))
        if k not in steps:
            continue
        ck = read_ct_volume(ct / f"step_{k:02d}_label.nii.gz", "label")
        truth = true_removal(c0.data, ck.data, c0.T_world_from_voxel, pre)
        # Only a voxel the preoperative model holds as tissue can be counted as removed.
        idx = np.argwhere(truth & (pre.tsdf < 0) & (pre.weight > 0))
        pts = transform_points(pre.T_world_from_voxel, idx.astype(np.float64))
        seen = np.zeros(len(pts), dtype=bool)
        for seq, poses, depths in views:
            seen |= seen_free(pts, seq.camera, poses, depths, margin_mm)
        seen_mask = np.zeros(truth.shape, dtype=bool)
        seen_mask[tuple(idx[seen].T)] = True
        key = f"seed_{seed_dir.name.split('_', 1)[1]}_step_{k}"
        out[f"{key}_removed_seen_fraction"] = float(seen.sum() / max(int(truth.sum()), 1))
        out[f"{key}_dice_bound"] = float(dice(truth, seen_mask) or 0.0)
        model_path = seed_dir / "base" / EXACT / f"step_{k:02d}" / "model.npz"
        if model_path.exists():
            got = model_removal(pre, TsdfModel.load(model_path))
            out[f"{key}_exact_dice"] = float(dice(truth, got) or 0.0)
            out[f"{key}_seen_left"] = float((seen_mask & ~got).sum())
    return out


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", type=Path, required=True, help="results/EXPERIMENT of a run")
    parser.add_argument("--seeds", required=True, help="phantom seeds, e.g. '0-4'")
    parser.add_argument("--steps", default="1-5", help="steps, e.g. '1' or '1-5' (default)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    bounds: list[float] = []
    for seed in parse_seeds(args.seeds):
        figs = seed_bounds(args.run / f"seed_{seed}", parse_seeds(args.steps))
        for name, value in figs.items():
            print(f"{name}: {value:.3f}" if "left" not in name else f"{name}: {value:.0f}")
            if name.endswith("_dice_bound"):
                bounds.append(value)
    print(f"cpu_simd: {cpu_simd()}")
    print(f"elapsed_s: {time.perf_counter() - t0:.1f}")
    print(f"removal_dice_bound_min: {min(bounds):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
