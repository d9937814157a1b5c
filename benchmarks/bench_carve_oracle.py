"""Benchmark: what limits a network row's removal: the network's depth, where it decides
"changed", or the carving a noisy estimate gets.

For each seed and step of a finished `table` run with the row (``--method``:
``change_aware``, the default; ``updated``, the paper's monocular row; or ``updated_sweep``,
the same network on the sweep-only model, whose removal is read on that model's grid), the
step is run again from that row's own model before it (the preoperative model at step 1),
with the run's update config, once per depth source:

- ``network``: the row's own depth, run again: the per-patient change-aware network, or
  the monocular network's predictions the run stored (``depth/pred/step_KK``);
- ``decision_true_depth`` (change-aware): the network's decision (change probability >=
  0.5) with the frame's true depth behind it, the render elsewhere: perfect depth where it
  says "changed";
- ``above_noise_true_depth`` (monocular; runs ``network`` first): the frame's true depth
  where it lies deeper than the render by more than the change threshold the network's
  frame had in that run (3 sigma of its noise, ``change.noise_k``), the render elsewhere:
  a perfect estimate that sees no more than the network's noise lets a frame see;
- ``true_depth_noisy``: the frame's true depth, declared an estimate, so carved as the
  network is (``UpdateConfig.noisy_*``: votes, one layer, the cavity-middle rule, no cut
  inside held tissue): a perfect estimate under the noisy carving's guards;
- ``true_depth``: the frame's true depth carved as precise (the exact-depth row's carving
  from the same start model);
- ``network_oracle_reliable`` (change-aware; not run unless named in ``--sources``): the
  network's own depth, carved as precise exactly where it lies within ``--oracle-tol-mm``
  (0.5) of the truth and as a noisy estimate elsewhere: what a perfect per-pixel
  reliability head would give (``last_reliable_px``, :mod:`chisel.depth_source`).

Each row's removed-tissue Dice, precision and recall against the truth (tissue in the
preoperative label CT, air in the step's; :mod:`chisel.eval.volume`) is printed per seed
and step as ``seed_S_step_K_SOURCE_dice: ...``. ``network`` to ``decision_true_depth`` is
what the network's depth costs, ``decision_true_depth`` to ``true_depth_noisy`` what its
decision costs, ``above_noise_true_depth`` to ``true_depth_noisy`` what the network's noise
floor alone would cost, ``true_depth_noisy`` to ``true_depth`` what the noisy carving's
guards cost. ``--true-poses`` gives every frame its true pose (no tracking error): what the
tracker's error costs; ``--true-poses translation`` (``rotation``) gives only the true
camera centre (orientation), and ``--true-poses hand_eye`` takes away only the constant
hand-eye error, keeping each frame's jitter (:func:`remove_tracking_error`). Prints each
source's mean Dice, ``cpu_simd``, ``elapsed_s``, ``noise_floor_dice_cost`` (mean Dice of
``true_depth_noisy`` minus that of ``above_noise_true_depth``, when both run) and, last,
``noisy_carving_dice_cost``: the mean Dice of ``true_depth`` minus that of
``true_depth_noisy`` (when both run: ``--sources``).
``--config`` runs a variant of the update config instead of the run's. About 10-25 s per
source and step on this 2-core machine for the change-aware row, 4 s for the monocular one
(its depth is read, not inferred).

    .venv/bin/python benchmarks/bench_carve_oracle.py --run RUN/results/default --seeds 0-4 --steps 1
    .venv/bin/python benchmarks/bench_carve_oracle.py --run RUN/results/default --seeds 0-4 \
        --steps 1-5 --method updated
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
from chisel.core.geometry import invert_rigid  # noqa: E402
from chisel.depth_source import (  # noqa: E402
    GroundTruthDepth,
    SequenceDepth,
    load_change_aware_source,
)
from chisel.eval.volume import model_removal, removal_scores, true_removal  # noqa: E402
from chisel.io.ct import read_ct_volume  # noqa: E402
from chisel.io.sequence import Frame, Sequence  # noqa: E402
from chisel.model import TsdfModel  # noqa: E402
from chisel.registration import robust_mean_transform  # noqa: E402
from chisel.update_config import UpdateConfig  # noqa: E402
from sim.dataset import parse_seeds  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from host import cpu_simd  # noqa: E402

METHODS = ("change_aware", "updated", "updated_sweep")
MONOCULAR = ("updated", "updated_sweep")
"""The rows whose depth is the monocular network's (stored in ``depth/pred/step_KK``)."""
SOURCES = (
    "network",
    "decision_true_depth",
    "above_noise_true_depth",
    "true_depth_noisy",
    "true_depth",
    "network_oracle_reliable",
)
ONLY_FOR = {
    "decision_true_depth": ("change_aware",),
    "network_oracle_reliable": ("change_aware",),
    "above_noise_true_depth": MONOCULAR,
}
"""Sources that need what only one kind of network gives: a change probability and a
metric output (change-aware), or a change threshold measured from relative depth."""
POSE_ERRORS = ("all", "translation", "rotation", "hand_eye")
"""What ``--true-poses`` takes away from the tracked poses (:func:`remove_tracking_error`)."""
DEFAULT_SOURCES = {
    "change_aware": ("network", "decision_true_depth", "true_depth_noisy", "true_depth"),
    **dict.fromkeys(
        MONOCULAR, ("network", "above_noise_true_depth", "true_depth_noisy", "true_depth")
    ),
}


def check_sources(method: str, sources: tuple[str, ...]) -> None:
    """Refuse a source that ``method``'s network cannot drive, naming both."""
    for name in sources:
        if method not in ONLY_FOR.get(name, METHODS):
            only = " or ".join(ONLY_FOR[name])
            raise SystemExit(f"--sources {name}: only with --method {only}, not {method}")
    if "above_noise_true_depth" in sources and "network" not in sources:
        raise SystemExit(
            "--sources above_noise_true_depth needs network too (its frames' change thresholds)"
        )


def true_depth(frame: Frame) -> np.ndarray:
    """The frame's true depth, mm; a sequence without it cannot drive an oracle source."""
    if frame.depth_mm is None:
        raise SystemExit(f"frame {frame.index}: no true depth (a rendered sequence is needed)")
    return frame.depth_mm


def true_depth_where(frame: Frame, where: np.ndarray, prior_mm: np.ndarray) -> np.ndarray:
    """The frame's true depth where ``where``, the prior (the model's render) elsewhere,
    NaN at the pixels the frame's mask leaves out."""
    out = np.where(where, true_depth(frame), prior_mm).astype(np.float32)
    if frame.mask is not None:
        out[~frame.mask] = np.nan
    return out


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
        true_depth(frame)
        self.network(frame, prior_mm=prior_mm)
        p = getattr(self.network, "last_change_probability", None)
        if p is None:
            raise SystemExit(f"{self.network!r} keeps no change probability")
        return true_depth_where(frame, p >= 0.5, prior_mm)


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
        depth_mm = true_depth(frame)
        out = self.network(frame, prior_mm=prior_mm)
        with np.errstate(invalid="ignore"):
            self.last_reliable_px = np.abs(out - depth_mm) <= self.tol_mm
        return out


class TrueDepthAboveNoise:
    """The frame's true depth where it lies deeper than the render by more than the
    network frame's change threshold (``thresholds_mm``: frame index -> mm, from the
    network's run of the step), the render elsewhere; carved as the network is. A frame
    the network's run did not use has no threshold and sees no change."""

    is_metric = True
    wants_prior = True
    is_estimate = True

    def __init__(self, thresholds_mm: dict[int, float]) -> None:
        self.thresholds_mm = thresholds_mm

    def __call__(self, frame: Frame, prior_mm: np.ndarray) -> np.ndarray:
        threshold_mm = self.thresholds_mm.get(frame.index, np.inf)
        with np.errstate(invalid="ignore"):
            seen = true_depth(frame) - prior_mm > threshold_mm
        return true_depth_where(frame, seen, prior_mm)


class TrueDepthAsEstimate(GroundTruthDepth):
    """The frame's true depth, carved as a learnt estimate (``is_estimate``)."""

    is_estimate = True


def with_true_pose(frame: Frame) -> Frame:
    """The frame as a tracker without error would report it."""
    return dataclasses.replace(frame, T_world_from_cam=true_pose(frame))


def true_pose(frame: Frame) -> np.ndarray:
    """The frame's true ``T_world_from_cam`` (exits when the sequence has none)."""
    if frame.T_world_from_cam_true is None:
        raise SystemExit(f"frame {frame.index}: no true pose (a rendered sequence is needed)")
    return frame.T_world_from_cam_true


def remove_tracking_error(frames: list[Frame], part: str) -> list[Frame]:
    """The step's frames with ``part`` (:data:`POSE_ERRORS`) of the tracker's error taken away.

    ``all``: the true pose; ``translation``: the true camera centre, the tracked
    orientation; ``rotation``: the reverse; ``hand_eye``: the tracked pose with the step's
    constant camera-side error E undone (``T_tracked @ E^-1``, E the robust mean of
    ``T_true^-1 @ T_tracked`` over the frames), so each frame keeps its own jitter.
    """
    if part == "all":
        return [with_true_pose(f) for f in frames]
    if part == "hand_eye":
        E = robust_mean_transform([invert_rigid(true_pose(f)) @ f.T_world_from_cam for f in frames])
        undo = invert_rigid(E)
        return [dataclasses.replace(f, T_world_from_cam=f.T_world_from_cam @ undo) for f in frames]
    out = []
    for f in frames:
        T = f.T_world_from_cam.copy()
        if part == "translation":
            T[:3, 3] = true_pose(f)[:3, 3]
        else:
            T[:3, :3] = true_pose(f)[:3, :3]
        out.append(dataclasses.replace(f, T_world_from_cam=T))
    return out


def make_source(
    name: str,
    net: Callable[..., np.ndarray] | None,
    pred: Path,
    seq: Sequence,
    thresholds_mm: dict[int, float],
    oracle_tol_mm: float,
) -> Callable[..., np.ndarray]:
    """Source ``name`` for one step: ``net`` is the change-aware network (None: the row is
    the monocular one, whose depth the run stored in ``pred``); ``thresholds_mm`` are the
    network's frames' change thresholds in its run of this step."""
    if name == "network":
        return net if net is not None else SequenceDepth(pred, of=seq)
    if name == "true_depth_noisy":
        return TrueDepthAsEstimate()
    if name == "true_depth":
        return GroundTruthDepth()
    if name == "above_noise_true_depth":
        return TrueDepthAboveNoise(thresholds_mm)
    if net is None:  # check_sources refuses these for the monocular row
        raise SystemExit(f"--sources {name}: only with --method change_aware")
    if name == "decision_true_depth":
        return DecisionTrueDepth(net)
    return OracleReliable(net, oracle_tol_mm)


def seed_scores(
    seed_dir: Path,
    steps: list[int],
    cfg: UpdateConfig,
    sources: tuple[str, ...] = DEFAULT_SOURCES["change_aware"],
    oracle_tol_mm: float = 0.5,
    true_poses: str | None = None,
    method: str = "change_aware",
) -> dict[int, dict[str, float]]:
    """Removed-tissue scores of each of ``steps`` of one seed, run again with each source.

    The preoperative model, the preoperative label CT and the change-aware network are
    read once."""
    check_sources(method, sources)
    # The sweep-only row starts from its own build, and its removal is read on its grid.
    preop_path = (
        seed_dir / "preop" / ("model_sweep.npz" if method == "updated_sweep" else "model.npz")
    )
    pre = TsdfModel.load(preop_path)
    ct = seed_dir / "phantom" / "ct"
    c0 = read_ct_volume(ct / "step_00_label.nii.gz", "label")
    net = (
        load_change_aware_source(seed_dir / "depth" / "change_aware_finetuned.pt")
        if method == "change_aware"
        else None
    )
    scores: dict[int, dict[str, float]] = {}
    for k in steps:
        start_path = (
            preop_path if k == 1 else seed_dir / "base" / method / f"step_{k - 1:02d}" / "model.npz"
        )
        if not start_path.is_file():
            raise SystemExit(
                f"{start_path}: missing (a `table` run with the {method} row is needed)"
            )
        start = pre if k == 1 else TsdfModel.load(start_path)
        ck = read_ct_volume(ct / f"step_{k:02d}_label.nii.gz", "label")
        truth = true_removal(c0.data, ck.data, c0.T_world_from_voxel, pre)
        seq = Sequence(seed_dir / "render" / f"step_{k:02d}")
        frames = [seq.frame(i) for i in range(len(seq))]
        if true_poses is not None:
            frames = remove_tracking_error(frames, true_poses)
        pred_dir = seed_dir / "depth" / "pred" / f"step_{k:02d}"
        # The network's own run comes first: its frames' thresholds drive above_noise.
        thresholds_mm: dict[int, float] = {}
        out: dict[str, float] = {}
        for name in sorted(sources, key=SOURCES.index):
            source = make_source(name, net, pred_dir, seq, thresholds_mm, oracle_tol_mm)
            model, report = update_step(start, seq.camera, frames, source, cfg)
            if name == "network":
                thresholds_mm = {
                    f.index: f.threshold_mm
                    for f in report.frames
                    if f.used and np.isfinite(f.threshold_mm)
                }
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
        help="default: network, decision_true_depth (change-aware) or above_noise_true_depth "
        "(monocular rows), true_depth_noisy, true_depth",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="change_aware",
        help="the row: the change-aware network, or the paper's monocular network on the "
        "whole-CT model (updated) or on the sweep-only one (updated_sweep)",
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
        nargs="?",
        const="all",
        choices=POSE_ERRORS,
        help="take the tracker's error away: all of it (no value), the translation, the "
        "rotation, or the constant hand-eye error alone (each frame's jitter kept)",
    )
    args = parser.parse_args()
    sources = tuple(args.sources or DEFAULT_SOURCES[args.method])
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
            args.method,
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
    if "above_noise_true_depth" in sources and "true_depth_noisy" in sources:
        floor = np.mean(dices["true_depth_noisy"]) - np.mean(dices["above_noise_true_depth"])
        print(f"noise_floor_dice_cost: {floor:.3f}")
    if "true_depth" in sources and "true_depth_noisy" in sources:
        cost = np.mean(dices["true_depth"]) - np.mean(dices["true_depth_noisy"])
        print(f"noisy_carving_dice_cost: {cost:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
