"""Two finished `table` runs compared cell by cell: a new network, checkpoint or setting
against the one before, on the same renders.

    .venv/bin/python benchmarks/compare_runs.py FIRST/results/EXP SECOND/results/EXP
        [--seeds 0-4] [--methods updated change_aware]

Each run is a results folder of the workflow's `table` target (`seed_N/base/metrics.json`
per phantom seed). A cell is one (seed, step >= 1, method); its figure is the paper's
metric as a fraction of no update's in the same run (`mean_mm / no_update mean_mm`), so
that two runs on different renders stay comparable. Per method present in both runs, for
each run: that ratio's mean, worst and worst at steps 2+, removed-tissue Dice, precision
and recall (mean and min; NaN for runs older than the last two), change-mask precision /
recall mean and min, the largest `missing_fraction`; then second / first cell by cell:
range, geometric mean, cells better, cells with a better Dice. Prints `name: value`
lines; last, `second_over_first_geomean` over every compared cell (< 1: the second run
is better). A network row moves by itself by up to ~40 % at a single cell when only its
fine-tuning's seed changes (docs/results.md, twenty-first and twenty-second sessions):
read single cells against that.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from sim.dataset import parse_seeds

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fidelity import NONE, _cells, _num  # noqa: E402

Cell = dict[str, float]
"""ratio and the optional scores (NaN where a run holds none)."""
SCORES = (
    "removed_dice",
    "removed_precision",
    "removed_recall",
    "mask_precision",
    "mask_recall",
    "missing_fraction",
)


def read_run(results: Path, seeds: list[int] | None) -> dict[tuple[int, int, str], Cell]:
    """(seed, step, method) -> cell for every method but no update, steps >= 1."""
    paths = sorted(results.glob("seed_*/base/metrics.json"))
    found = {int(p.parent.parent.name.split("_", 1)[1]): p for p in paths}
    if seeds is not None:
        missing = [s for s in seeds if s not in found]
        if missing:
            raise SystemExit(
                f"{results}: no seed_N/base/metrics.json for seeds {missing} (found {sorted(found)})"
            )
        found = {s: found[s] for s in seeds}
    if not found:
        raise SystemExit(f"{results}: no seed_N/base/metrics.json (not a `table` results folder)")
    cells: dict[tuple[int, int, str], Cell] = {}
    for seed, path in sorted(found.items()):
        for step, methods in _cells(json.loads(path.read_text())).items():
            if NONE not in methods:
                raise SystemExit(f"{path}: step {step} has no {NONE} row to divide by")
            base_mm = float(methods[NONE]["mean_mm"])
            for name, c in methods.items():
                if name == NONE or c.get("mean_mm") is None:
                    continue
                cell = {"ratio": float(c["mean_mm"]) / base_mm}
                cell.update({k: _num(c.get(k)) for k in SCORES})
                cells[(seed, step, name)] = cell
    return cells


def _finite(values: list[float]) -> list[float]:
    return [v for v in values if not math.isnan(v)]


def summarise(cells: dict[tuple[int, int, str], Cell], method: str) -> dict[str, float]:
    """One run's figures for one method (NaN where no cell holds the score)."""
    own = {k: c for k, c in cells.items() if k[2] == method}
    ratios = [c["ratio"] for c in own.values()]
    later = [c["ratio"] for k, c in own.items() if k[1] >= 2]
    out = {
        "ratio_mean": sum(ratios) / len(ratios),
        "ratio_worst": max(ratios),
        "ratio_worst_steps_2_on": max(later) if later else float("nan"),
    }
    for key, name in (
        ("removed_dice", "dice"),
        ("removed_precision", "removed_precision"),
        ("removed_recall", "removed_recall"),
        ("mask_precision", "precision"),
        ("mask_recall", "recall"),
    ):
        v = _finite([c[key] for c in own.values()])
        out[f"{name}_mean"] = sum(v) / len(v) if v else float("nan")
        out[f"{name}_min"] = min(v) if v else float("nan")
    miss = _finite([c["missing_fraction"] for c in own.values()])
    out["missing_fraction_max"] = max(miss) if miss else float("nan")
    return out


def compare(
    first: dict[tuple[int, int, str], Cell], second: dict[tuple[int, int, str], Cell], method: str
) -> dict[str, float]:
    """second / first over the cells both runs hold for ``method``."""
    keys = sorted(k for k in first if k[2] == method and k in second)
    if not keys:
        raise SystemExit(f"no (seed, step) cell of {method!r} is in both runs")
    q = [second[k]["ratio"] / first[k]["ratio"] for k in keys]
    dice_better = sum(second[k]["removed_dice"] > first[k]["removed_dice"] for k in keys)
    return {
        "cells": float(len(q)),
        "min": min(q),
        "max": max(q),
        "geomean": math.exp(sum(math.log(x) for x in q) / len(q)),
        "better": float(sum(x < 1.0 for x in q)),
        "dice_better": float(dice_better),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("first", type=Path, help="results folder of the first run")
    p.add_argument("second", type=Path, help="results folder of the second run")
    p.add_argument("--seeds", help="phantom seeds, e.g. '0-4' (default: those of the first run)")
    p.add_argument("--methods", nargs="+", help="method rows (default: every one both runs hold)")
    a = p.parse_args(argv)
    seeds = parse_seeds(a.seeds) if a.seeds else None
    first = read_run(a.first, seeds)
    if seeds is None:
        seeds = sorted({k[0] for k in first})
    second = read_run(a.second, seeds)
    shared = sorted({k[2] for k in first} & {k[2] for k in second})
    methods = a.methods or shared
    absent = [m for m in methods if m not in shared]
    if absent:
        raise SystemExit(f"methods {absent} are not in both runs (both hold {shared})")
    print(f"seeds: {','.join(str(s) for s in seeds)}")
    logs: list[float] = []
    for m in methods:
        for tag, run in (("first", first), ("second", second)):
            for name, value in summarise(run, m).items():
                print(f"{tag}_{m}_{name}: {value:.3f}")
        c = compare(first, second, m)
        print(f"{m}_second_over_first_min: {c['min']:.3f}")
        print(f"{m}_second_over_first_max: {c['max']:.3f}")
        print(f"{m}_cells_better: {int(c['better'])} of {int(c['cells'])}")
        print(f"{m}_cells_dice_better: {int(c['dice_better'])} of {int(c['cells'])}")
        print(f"{m}_second_over_first_geomean: {c['geomean']:.3f}")
        logs += [math.log(c["geomean"])] * int(c["cells"])
    print(f"second_over_first_geomean: {math.exp(sum(logs) / len(logs)):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
