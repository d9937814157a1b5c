"""benchmarks/compare_runs.py on two hand-written `table` runs whose figures are known."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from benchmark_module import load_benchmark


def _write(root: Path, seed: int, rows: dict[str, list[tuple[float, float | None]]]) -> None:
    """rows: method -> [(mean_mm, removed_dice)] for steps 1, 2; no update is 2.0 mm."""
    base = root / f"seed_{seed}" / "base"
    base.mkdir(parents=True)
    steps = [{"step": 0, "methods": {"no_update": {"mean_mm": 0.1}}}]
    for i in (0, 1):
        methods = {"no_update": {"mean_mm": 2.0, "removed_dice": 0.0}}
        for m, v in rows.items():
            methods[m] = {
                "mean_mm": v[i][0],
                "removed_dice": v[i][1],
                "mask_precision": 0.9,
                "mask_recall": None,  # nothing scored: NaN, left out of mean and min
                "missing_fraction": 0.01 * (i + 1),
            }
        steps.append({"step": i + 1, "methods": methods})
    (base / "metrics.json").write_text(json.dumps({"steps": steps}))


def test_figures_and_cell_by_cell_ratios(tmp_path: Path, capsys) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, 0, {"updated": [(0.4, 0.8), (0.2, 0.9)], "change_aware": [(0.2, 0.9), (0.2, 0.9)]})
    _write(a, 1, {"updated": [(0.6, 0.7), (0.4, 0.6)], "change_aware": [(0.2, 0.9), (0.2, 0.9)]})
    _write(b, 0, {"updated": [(0.2, 0.9), (0.2, 0.8)]})
    _write(b, 1, {"updated": [(1.2, 0.8), (0.1, 0.5)]})
    mod = load_benchmark("compare_runs")
    assert mod.main([str(a), str(b)]) == 0
    out = dict(line.split(": ", 1) for line in capsys.readouterr().out.splitlines())
    # first run's ratios 0.2, 0.1, 0.3, 0.2; second's 0.1, 0.1, 0.6, 0.05
    assert float(out["first_updated_ratio_mean"]) == pytest.approx(0.2, abs=1e-3)
    assert float(out["first_updated_ratio_worst"]) == pytest.approx(0.3, abs=1e-3)
    assert float(out["first_updated_ratio_worst_steps_2_on"]) == pytest.approx(0.2, abs=1e-3)
    assert float(out["second_updated_ratio_worst"]) == pytest.approx(0.6, abs=1e-3)
    assert float(out["first_updated_dice_min"]) == pytest.approx(0.6, abs=1e-3)
    assert out["first_updated_recall_mean"] == "nan"
    assert float(out["first_updated_missing_fraction_max"]) == pytest.approx(0.02, abs=1e-3)
    # per cell 0.5, 1.0, 2.0, 0.25: geometric mean 0.5 ** 0.5
    assert float(out["updated_second_over_first_min"]) == pytest.approx(0.25, abs=1e-3)
    assert float(out["updated_second_over_first_max"]) == pytest.approx(2.0, abs=1e-3)
    assert out["updated_cells_better"] == "2 of 4"
    assert out["updated_cells_dice_better"] == "2 of 4"
    assert float(out["second_over_first_geomean"]) == pytest.approx(math.sqrt(0.5), abs=1e-3)
    assert "change_aware_cells_better" not in out  # only in the first run
    assert list(out)[-1] == "second_over_first_geomean"


def test_a_missing_seed_or_method_is_named(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, 0, {"updated": [(0.4, 0.8), (0.2, 0.9)]})
    _write(b, 0, {"updated": [(0.4, 0.8), (0.2, 0.9)]})
    mod = load_benchmark("compare_runs")
    with pytest.raises(SystemExit, match=r"seeds \[1\]"):
        mod.main([str(a), str(b), "--seeds", "0-1"])
    with pytest.raises(SystemExit, match="change_aware"):
        mod.main([str(a), str(b), "--methods", "change_aware"])
    with pytest.raises(SystemExit, match="not a `table` results folder"):
        mod.main([str(tmp_path / "empty"), str(b)])
