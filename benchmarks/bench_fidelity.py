"""The update's goals over phantom seeds (issue 19): runs the workflow's `table` target and
prints each goal's figure per seed and over all seeds, and, last,
`updated_vs_no_update_worst_ratio: ...` (the network row's worst step of any seed, as a
fraction of no update's error; goal <= 0.5 at steps 2+, never > 1).

    python benchmarks/bench_fidelity.py                       # config/config.yaml, its table_seeds
    python benchmarks/bench_fidelity.py --seeds 0-4 --workdir /tmp/fid
    python benchmarks/bench_fidelity.py --configfile config/smoke.yaml --seeds 0

Goals (the issue's): exact depth (`depth_ablation`) <= 0.3 mm at every step and <= 0.15x
no update at the last step; `updated` <= 0.5x no update at steps 2+ and never worse than
no update; its change masks' precision and recall >= 0.7; removed-tissue Dice >= 0.85
(exact) and >= 0.7 (network); HD95 <= 1.0 mm (exact); missing_fraction <= 1 % for every
method and step. With `change_aware` in the config's methods, issue 20's goals for its row
too: <= 0.3x no update at steps 2+, never worse; mask precision and recall >= 0.85;
removed-tissue Dice >= 0.8. A seed that misses a goal is printed, never dropped.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from sim.dataset import parse_seeds

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_workflow import run_workflow, work_folder  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXACT, NETWORK, NONE = "depth_ablation", "updated", "no_update"
CHANGE_AWARE = "change_aware"
NETWORK_ROWS = (NETWORK, CHANGE_AWARE)
"""Rows of a learnt depth source, scored alike (figures prefixed with the method)."""


def _cells(metrics: Mapping[str, Any]) -> dict[int, dict[str, dict[str, Any]]]:
    """step -> method -> cell, steps >= 1 only (step 0 is the preoperative model)."""
    return {int(s["step"]): s["methods"] for s in metrics["steps"] if int(s["step"]) >= 1}


def _num(x: Any) -> float:
    return float("nan") if x is None else float(x)


def _min(values: Any) -> float:
    """min, NaN when any value is NaN (a step that could not be scored fails the goal)."""
    v = list(values)
    return float("nan") if any(x != x for x in v) else min(v)


def _max(values: Any) -> float:
    v = list(values)
    return float("nan") if any(x != x for x in v) else max(v)


def _network_figures(
    cells: Mapping[int, Mapping[str, Mapping[str, Any]]],
    steps: list[int],
    method: str,
    ratio: Callable[[str, int], float],
) -> dict[str, float]:
    later = [s for s in steps if s >= 2] or steps

    def worst_of(key: str) -> float:
        return _min(_num(cells[s][method].get(key)) for s in steps)

    return {
        f"{method}_ratio_steps2_max": _max(ratio(method, s) for s in later),
        f"{method}_ratio_max": _max(ratio(method, s) for s in steps),
        f"{method}_mask_precision_min": worst_of("mask_precision"),
        f"{method}_mask_recall_min": worst_of("mask_recall"),
        f"{method}_removed_dice_min": worst_of("removed_dice"),
    }


def seed_figures(metrics: Mapping[str, Any]) -> dict[str, float]:
    """One seed's goal figures from its ``metrics.json`` (the base variant's table)."""
    cells = _cells(metrics)
    steps = sorted(cells)
    last = steps[-1]

    def ratio(method: str, step: int) -> float:
        return _num(cells[step][method]["mean_mm"]) / max(_num(cells[step][NONE]["mean_mm"]), 1e-9)

    out: dict[str, float] = {}
    if EXACT in cells[last]:
        out["exact_max_mean_mm"] = _max(_num(cells[s][EXACT]["mean_mm"]) for s in steps)
        out["exact_last_step_ratio"] = ratio(EXACT, last)
        out["exact_removed_dice_min"] = _min(
            _num(cells[s][EXACT].get("removed_dice")) for s in steps
        )
        out["exact_removed_hd95_max_mm"] = _max(
            _num(cells[s][EXACT].get("removed_hd95_mm")) for s in steps
        )
    for method in NETWORK_ROWS:
        if method in cells[last]:
            out.update(_network_figures(cells, steps, method, ratio))
    out["missing_fraction_max"] = _max(
        _num(c.get("missing_fraction")) for s in steps for c in cells[s].values()
    )
    return out


GOALS: dict[str, tuple[str, float]] = {
    "exact_max_mean_mm": ("<=", 0.3),
    "exact_last_step_ratio": ("<=", 0.15),
    "exact_removed_dice_min": (">=", 0.85),
    "exact_removed_hd95_max_mm": ("<=", 1.0),
    "updated_ratio_steps2_max": ("<=", 0.5),
    "updated_ratio_max": ("<=", 1.0),
    "updated_mask_precision_min": (">=", 0.7),
    "updated_mask_recall_min": (">=", 0.7),
    "updated_removed_dice_min": (">=", 0.7),
    # issue 20's goals for the change-aware network's row
    "change_aware_ratio_steps2_max": ("<=", 0.3),
    "change_aware_ratio_max": ("<=", 1.0),
    "change_aware_mask_precision_min": (">=", 0.85),
    "change_aware_mask_recall_min": (">=", 0.85),
    "change_aware_removed_dice_min": (">=", 0.8),
    "missing_fraction_max": ("<=", 0.01),
}


def meets(name: str, value: float) -> bool:
    """Whether ``value`` meets the goal ``name`` (a NaN, e.g. no mask to score, does not)."""
    op, bound = GOALS[name]
    return value <= bound if op == "<=" else value >= bound


def worst(per_seed: Mapping[int, Mapping[str, float]], name: str) -> float:
    """The worst value of a figure over seeds (largest for "<=" goals, smallest for ">=")."""
    values = [f[name] for f in per_seed.values() if name in f]
    if any(v != v for v in values):  # NaN: some step could not be scored
        return float("nan")
    return max(values) if GOALS[name][0] == "<=" else min(values)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--configfile", type=Path, default=ROOT / "config" / "config.yaml")
    parser.add_argument(
        "--seeds", help="phantom seeds, e.g. '0-4' (default: the config's table_seeds)"
    )
    parser.add_argument(
        "--workdir", type=Path, help="results folder, reused (default: a temp dir, removed at exit)"
    )
    parser.add_argument("--cores", type=int, default=2)
    args = parser.parse_args()
    with work_folder(args.workdir, "chisel-fidelity-") as workdir:
        return report(args, workdir)


def report(args: argparse.Namespace, workdir: Path) -> int:
    wanted = parse_seeds(args.seeds) if args.seeds else None
    overrides = {"table_seeds": wanted} if wanted else None
    ran = run_workflow("table", workdir, args.configfile, args.cores, overrides)
    if ran is None:
        return 1
    experiment, wall_s = ran
    results = workdir / "results" / experiment
    per_seed: dict[int, dict[str, float]] = {}
    for path in sorted(results.glob("seed_*/base/metrics.json")):
        seed = int(path.parent.parent.name.split("_", 1)[1])
        if wanted is not None and seed not in wanted:
            continue
        per_seed[seed] = seed_figures(json.loads(path.read_text()))
    print(f"experiment: {experiment}")
    print(f"workdir: {workdir if args.workdir else '(removed; --workdir keeps it)'}")
    print(f"seeds: {','.join(str(s) for s in sorted(per_seed))}")
    for seed, figs in sorted(per_seed.items()):
        for name, value in figs.items():
            print(f"seed_{seed}_{name}: {value:.3f}")
    for name in GOALS:
        if any(name in f for f in per_seed.values()):
            op, bound = GOALS[name]
            failing = [
                s for s, f in sorted(per_seed.items()) if name in f and not meets(name, f[name])
            ]
            print(
                f"# goal {name} {op} {bound}: "
                + (f"NOT MET on seeds {failing}" if failing else "met")
            )
            print(f"{name}_worst: {worst(per_seed, name):.3f}")
    print(f"workflow_s: {wall_s:.1f}")
    if any("change_aware_ratio_max" in f for f in per_seed.values()):
        ratio = worst(per_seed, "change_aware_ratio_max")
        print(f"change_aware_vs_no_update_worst_ratio: {ratio:.3f}")
    if any("updated_ratio_max" in f for f in per_seed.values()):
        print(f"updated_vs_no_update_worst_ratio: {worst(per_seed, 'updated_ratio_max'):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
