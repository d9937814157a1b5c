"""Benchmark: what limits the change-aware row's removal: the network's depth, where it
decides "changed", or the carving a noisy estimate gets.

For each seed and step of a finished `table` run with the `change_aware` row, the step is
run again from that row's own model before it (the preoperative model at step 1), with
the run's update config, once per depth source:

- ``network``: the per-patient change-aware network (the row itself, run again);
- ``decision_true_depth``: the network's decision (change probability >= 0.5) with the
  frame's true depth behind it, the render elsewhere: perfect depth where it says
  "changed";
- ``true_depth_noisy``: the frame's true depth, declared an estimate, so carved as the
  network is (``UpdateConfig.noisy_*``: votes, one layer, the cavity-middle rule, no cut
  inside held tissue): a perfect estimate under the noisy carving's guards;
- ``true_depth``: the frame's true depth carved as precise (the exact-depth row's carving
  from the same start model);
- ``network_oracle_reliable`` (not run unless named in ``--sources``): the network's own
  depth, carved as precise exactly where it lies within ``--oracle-tol-mm`` (0.5) of the
  truth and as a noisy estimate elsewhere: what a perfect per-pixel reliability head
  would give (``last_reliable_px``, :mod:`chisel.depth_source`).

Each row's removed-tissue Dice, precision and recall against the truth (tissue in the
preoperative label CT, air in the step's; :mod:`chisel.eval.volume`) is printed per seed
and step as ``seed_S_step_K_SOURCE_dice: ...``. ``network`` to ``decision_true_depth`` is
what the network's depth costs, ``decision_true_depth`` to ``true_depth_noisy`` what its
decision costs, ``true_depth_noisy`` to ``true_depth`` what the noisy carving's guards
cost. ``--true-poses`` gives every frame its true pose (no tracking error): what the
tracker's error costs. Prints each source's mean Dice, ``cpu_simd``, ``elapsed_s`` and,
last, ``noisy_carving_dice_cost``: the mean Dice of ``true_depth`` minus that of
``true_depth_noisy`` (when both run: ``--sources``). ``--config`` runs a variant of the
update config instead of the run's. About 10-25 s per source and step on this 2-core
machine.

    .venv/bin/python benchmarks/bench_carve_oracle.py --run RUN/results/default --seeds 0-4 --steps 1
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chisel.batch import update_step  # noqa: E402
from chisel.core.config import load_config_file  # noqa: E402
from chisel.depth_source import GroundTruthDepth, load_change_aware_source  # noqa: E402
from chisel.eval.volume import model_removal, removal_scores, true_removal  # noqa: E402
from chisel.io.ct import read_ct_volume  # noqa: E402
from chisel.io.sequence import Frame, Sequence  # noqa: E402
from chisel.model import TsdfModel  # noqa: E402
from chisel.update_config import UpdateConfig  # noqa: E402
from sim.dataset import parse_seeds  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from host import cpu_simd  # noqa: E402

METHOD = "change_aware"
SOURCES = (
    "network",
    "decision_true_depth",
    "true_depth_noisy",
    "true_depth",
    "network_oracle_reliable",
)
DEFAULT_SOURCES = SOURCES[:4]


class DecisionTrueDepth:
    """The frame's true depth where ``network`` decides "changed" (its last change
    probability >= 0.5), the prior (the model's render) elsewhere; carved as the network
    is. ``network`` is a change-aware source: ``network(frame, prior_mm=R)`` sets
    ``network.last_change_probability``."""

    is_metric = True
    wants_prior = True
    needs_rgb = True
    is_estimate = True

    def __init__(self, network: Callable[..., np.ndarray]) -> None:
        self.network = network

    def __call__(self, frame: Frame, prior_mm: np.ndarray) -> np.ndarray:
        if frame.depth_mm is None:
            raise SystemExit(f"frame {frame.index}: no true depth (a rendered sequence is needed)")
        self.network(frame, prior_mm=prior_mm)
        p = getattr(self.network, "last_change_probability", None)
        if p is None:
            raise SystemExit(f"{self.network!r} keeps no change probability")
        out = np.where(p >= 0.5, frame.depth_mm, prior_mm).astype(np.float32)
        if frame.mask is not None:
            out[~frame.mask] = np.nan
        return out


class OracleReliable:
    """The network's own depth, declared reliable (carved as precise) exactly where it lies
    within ``tol_mm`` of the frame's true depth: what a perfect reliability head would give."""

    is_metric = True
    wants_prior = True
    needs_rgb = True
    is_estimate = True

    def __init__(self, network: Callable[..., np.ndarray], tol_mm: float) -> None:
        self.network = network
        self.tol_mm = tol_mm
        self.last_reliable_px: np.ndarray | None = None

    def __call__(self, frame: Frame, prior_mm: np.ndarray) -> np.ndarray:
        if frame.depth_mm is None:
            raise SystemExit(f"frame {frame.index}: no true depth (a rendered sequence is needed)")
        out = self.network(frame, prior_mm=prior_mm)
        with np.errstate(invalid="ignore"):
            self.last_reliable_px = np.abs(out - frame.depth_mm) <= self.tol_mm
        return out


class TrueDepthAsEstimate(GroundTruthDepth):
    """The frame's true depth, carved as a learnt estimate (``is_estimate``)."""

    is_estimate = True


def with_true_pose(frame: Frame) -> Frame:
    """The frame as a tracker without error would report it."""
    if frame.T_world_from_cam_true is None:
        raise SystemExit(f"frame {frame.index}: no true pose (a rendered sequence is needed)")
    return dataclasses.replace(frame, T_world_from_cam=frame.T_world_from_cam_true)


def seed_scores(
    seed_dir: Path,
    steps: list[int],
    cfg: UpdateConfig,
    sources: tuple[str, ...] = DEFAULT_SOURCES,
    oracle_tol_mm: float = 0.5,
    true_poses: bool = False,
) -> dict[int, dict[str, float]]:
    """Removed-tissue scores of each of ``steps`` of one seed, run again with each source.

    The preoperative model, the preoperative label CT and the network are read once."""
    pre = TsdfModel.load(seed_dir / "preop" / "model.npz")
    ct = seed_dir / "phantom" / "ct"
    c0 = read_ct_volume(ct / "step_00_label.nii.gz", "label")
    net = load_change_aware_source(seed_dir / "depth" / "change_aware_finetuned.pt")
    make: dict[str, Callable[[], Callable[..., np.ndarray]]] = {
        "network": lambda: net,
        "decision_true_depth": lambda: DecisionTrueDepth(net),
        "true_depth_noisy": TrueDepthAsEstimate,
        "true_depth": GroundTruthDepth,
        "network_oracle_reliable": lambda: OracleReliable(net, oracle_tol_mm),
    }
    scores: dict[int, dict[str, float]] = {}
    for k in steps:
        start_path = (
            seed_dir / "preop" / "model.npz"
            if k == 1
            else seed_dir / "base" / METHOD / f"step_{k - 1:02d}" / "model.npz"
        )
        if not start_path.is_file():
            raise SystemExit(
                f"{start_path}: missing (a `table` run with the {METHOD} row is needed)"
            )
        start = pre if k == 1 else TsdfModel.load(start_path)
        ck = read_ct_volume(ct / f"step_{k:02d}_label.nii.gz", "label")
        truth = true_removal(c0.data, ck.data, c0.T_world_from_voxel, pre)
        seq = Sequence(seed_dir / "render" / f"step_{k:02d}")
        frames = [seq.frame(i) for i in range(len(seq))]
        if true_poses:
            frames = [with_true_pose(f) for f in frames]
        out: dict[str, float] = {}
        for name in sources:
            model, _ = update_step(start, seq.camera, frames, make[name](), cfg)
            s = removal_scores(model_removal(pre, model), truth, pre.voxel_size_mm)
            out[f"{name}_dice"] = s.dice if s.dice is not None else 0.0
            out[f"{name}_precision"] = s.precision if s.precision is not None else float("nan")
            out[f"{name}_recall"] = s.recall if s.recall is not None else 0.0
        scores[k] = out
    return scores


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", type=Path, required=True, help="results/EXPERIMENT of a run")
    parser.add_argument("--seeds", required=True, help="phantom seeds, e.g. '0-4'")
    parser.add_argument("--steps", default="1", help="steps, e.g. '1' (default) or '1-5'")
    parser.add_argument(
        "--sources",
        nargs="+",
        choices=SOURCES,
        default=list(DEFAULT_SOURCES),
        help="default: the first four",
    )
    parser.add_argument(
        "--oracle-tol-mm",
        type=float,
        default=0.5,
        help="network_oracle_reliable: carve as precise where the network is this near the truth",
    )
    parser.add_argument(
        "--config", type=Path, help="update config to use instead of the run's (a variant)"
    )
    parser.add_argument(
        "--true-poses",
        action="store_true",
        help="give every frame its true pose (no tracking error): what tracking error costs",
    )
    args = parser.parse_args()
    sources = tuple(args.sources)
    cfg_path = args.config or args.run / "update_config.yaml"
    cfg = load_config_file(UpdateConfig, cfg_path) if cfg_path.is_file() else UpdateConfig()
    # One step that no frame could use is scored as "no update", as the workflow does.
    cfg = dataclasses.replace(cfg, allow_unused_step=True)
    t0 = time.perf_counter()
    dices: dict[str, list[float]] = {name: [] for name in sources}
    for seed in parse_seeds(args.seeds):
        per_step = seed_scores(
            args.run / f"seed_{seed}",
            parse_seeds(args.steps),
            cfg,
            sources,
            args.oracle_tol_mm,
            args.true_poses,
        )
        for k, figs in per_step.items():
            for name, value in figs.items():
                print(f"seed_{seed}_step_{k}_{name}: {value:.3f}")
            for name in sources:
                dices[name].append(figs[f"{name}_dice"])
    for name in sources:
        print(f"{name}_dice_mean: {np.mean(dices[name]):.3f}")
    print(f"cpu_simd: {cpu_simd()}")
    print(f"elapsed_s: {time.perf_counter() - t0:.1f}")
    if "true_depth" in sources and "true_depth_noisy" in sources:
        cost = np.mean(dices["true_depth"]) - np.mean(dices["true_depth_noisy"])
        print(f"noisy_carving_dice_cost: {cost:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
