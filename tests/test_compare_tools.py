"""benchmarks/compare_tools.py (issue 22) on two hand-written runs: tool statistics, ratios, verdict."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from benchmark_module import load_benchmark
from PIL import Image


def _run(
    root: Path,
    means: dict[str, list[float]],
    tools: bool,
    missing: dict[str, list[float]] | None = None,
) -> None:
    base = root / "seed_0" / "base"
    base.mkdir(parents=True)
    missing = missing or {}
    steps = [
        {
            "step": s,
            "methods": {
                m: {"mean_mm": v[s - 1], "missing_fraction": missing.get(m, [0.0, 0.0])[s - 1]}
                for m, v in means.items()
            },
        }
        for s in (1, 2)
    ]
    (base / "metrics.json").write_text(json.dumps({"steps": steps}))
    for s in (1, 2):
        seq = root / "seed_0" / "render" / f"step_{s:02d}"
        (seq / "rgb").mkdir(parents=True)
        stop = np.zeros((8, 10), np.uint8)
        stop[:, :5] = 255  # a 40-pixel field stop
        Image.fromarray(stop).save(seq / "camera_mask.png")
        for i in range(4):
            Image.fromarray(np.zeros((8, 10, 3), np.uint8)).save(seq / "rgb" / f"{i:06d}.png")
        if not tools:
            continue
        (seq / "tool_mask").mkdir()
        frames = []
        for i in range(4):
            m = np.zeros((8, 10), np.uint8)
            if i == 1:
                m[0:2, 0:2] = 255  # 4 px inside the stop: 10 %
            if i == 2:
                m[:, 8:] = 255  # in a tool episode, but outside the field stop
            Image.fromarray(m).save(seq / "tool_mask" / f"{i:06d}.png")
            frames.append({"index": i, "tool": "forceps" if i in (1, 2) else None})
        (seq / "tools.json").write_text(json.dumps({"frames": frames}))


def test_compare_tools_ratios_verdict_and_tool_statistics(tmp_path: Path, capsys) -> None:
    _run(
        tmp_path / "free",
        {"no_update": [1.0, 2.0], "updated": [0.5, 1.0], "only_free": [1, 1]},
        False,
    )
    _run(tmp_path / "tools", {"no_update": [1.0, 2.0], "updated": [0.5, 1.2]}, True)
    out_json = tmp_path / "out.json"
    rc = load_benchmark("compare_tools").main(
        [
            "--free",
            str(tmp_path / "free"),
            "--tools",
            str(tmp_path / "tools"),
            "--json",
            str(out_json),
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "updated | 0.500, 0.500, 1.00x | 1.000, 1.200, 1.20x | FAIL (steps [2])" in text
    assert "no_update | 1.000, 1.000, 1.00x | 2.000, 2.000, 1.00x | PASS" in text
    got = json.loads(out_json.read_text())
    assert set(got["rows"]) == {"no_update", "updated"}  # rows of both runs only
    st = got["tools"]["1"]
    assert st["episode_frames"] == 2 and st["tool_frames"] == [1]
    assert st["tool_frame_fraction"] == 0.25
    assert abs(st["mean_tool_px_fraction"] - 0.1) < 1e-12
    assert got["tools"]["all"]["tool_frames"] == 2


def test_several_runs_compare_their_means_and_print_the_tool_free_spread(
    tmp_path: Path, capsys
) -> None:
    # Two tool-free runs 0.5 / 0.7 mm at step 2 (their own spread 1.40x), two tools runs
    # 0.6 / 0.66 mm: the means 0.6 and 0.63 give 1.05x, where either pair alone would fail.
    _run(tmp_path / "f0", {"no_update": [1.0, 2.0], "updated": [0.5, 0.5]}, False)
    _run(tmp_path / "f1", {"no_update": [1.0, 2.0], "updated": [0.5, 0.7]}, False)
    _run(tmp_path / "t0", {"no_update": [1.0, 2.0], "updated": [0.5, 0.6]}, True)
    _run(tmp_path / "t1", {"no_update": [1.0, 2.0], "updated": [0.5, 0.66]}, True)
    out_json = tmp_path / "out.json"
    rc = load_benchmark("compare_tools").main(
        ["--free", str(tmp_path / "f0"), str(tmp_path / "f1"),
         "--tools", str(tmp_path / "t0"), str(tmp_path / "t1"), "--json", str(out_json)]
    )  # fmt: skip
    assert rc == 0
    text = capsys.readouterr().out
    assert "updated | 0.500, 0.500, 1.00x | 0.600, 0.630, 1.05x | PASS" in text
    assert "tool-free runs' own spread" in text
    assert "updated | 1.00x | 1.40x" in text
    got = json.loads(out_json.read_text())
    assert got["rows"]["updated"]["free_spread"] == [1.0, 0.7 / 0.5]
    assert got["tools"]["1"]["tool_frames"] == [1]  # read from the first tools run


def test_a_tools_run_that_shows_less_is_flagged_beside_its_verdict(tmp_path: Path, capsys) -> None:
    # The tools run is as accurate at both steps, but at step 2 it shows no surface at 2 %
    # of the pixels against 1 % tool-free (over the half-point tolerance); at step 1
    # 0.4 points more, within it.
    means = {"updated": [0.5, 1.0]}
    _run(tmp_path / "free", means, False, {"updated": [0.010, 0.010]})
    _run(tmp_path / "tools", means, True, {"updated": [0.014, 0.020]})
    out_json = tmp_path / "out.json"
    rc = load_benchmark("compare_tools").main(
        ["--free", str(tmp_path / "free"), "--tools", str(tmp_path / "tools"),
         "--json", str(out_json)]
    )  # fmt: skip
    assert rc == 0
    text = capsys.readouterr().out
    assert "| PASS; more holes at steps [2]" in text
    assert "updated | 0.0100, 0.0140 | 0.0100, 0.0200" in text
    row = json.loads(out_json.read_text())["rows"]["updated"]
    assert row["pass"] and row["more_holes_steps"] == [2]
    assert row["tools_missing"] == [0.014, 0.020]
