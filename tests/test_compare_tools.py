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


def _compare(root: Path, out_json: Path, capsys) -> str:  # noqa: ANN001 - pytest fixture
    """compare_tools on ``root``/free against ``root``/tools; what it printed."""
    rc = load_benchmark("compare_tools").main(
        ["--free", str(root / "free"), "--tools", str(root / "tools"), "--json", str(out_json)]
    )
    assert rc == 0
    return capsys.readouterr().out


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
    text = _compare(tmp_path, out_json, capsys)
    assert "| PASS; more holes at steps [2]" in text
    assert "updated | 0.0100, 0.0140 | 0.0100, 0.0200" in text
    row = json.loads(out_json.read_text())["rows"]["updated"]
    assert row["pass"] and row["more_holes_steps"] == [2]
    assert row["tools_missing"] == [0.014, 0.020]


def _hand_eye_report(
    path: Path,
    deg: float,
    mm: float,
    se_deg: float | None,
    rejected: str,
    rejected_by: str | None = None,
) -> None:
    """An update.json whose step correction F turns ``deg`` about z and shifts ``mm`` along
    x, with F's standard error ``se_deg`` in rotation (None: the frames agree exactly) and
    0.25 mm in shift; refused (``rejected``, prose) by ``rejected_by`` (None: a report
    written before that field)."""
    a = np.radians(deg)
    F = np.eye(4)
    F[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    F[0, 3] = mm
    hand_eye = {
        "T_cam_from_corrected_cam": F.tolist(),
        "z_rotation": None if se_deg is None else deg / se_deg,
        "z_translation": mm / 0.25,
    }
    reg: dict = {"ok": True, "hand_eye": hand_eye}
    if rejected:
        reg["rejected"] = rejected
    if rejected_by is not None:
        reg["rejected_by"] = rejected_by
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps({"frames": [], "frames_used": [], "num_frames": 4, "sequence_registration": reg})
    )


def test_hand_eye_decisions_their_distance_from_the_gate_and_flips(tmp_path: Path, capsys) -> None:
    means = {"no_update": [1.0, 2.0], "updated": [0.5, 1.0]}
    _run(tmp_path / "free", means, False)
    _run(tmp_path / "tools", means, True)
    for run in ("free", "tools"):
        (tmp_path / run / "update_config.yaml").write_text(
            "registration:\n  tracking_accuracy_mm: 1.5\n  tracking_accuracy_deg: 1.5\n"
        )
    step = "seed_0/base/updated/step_{:02d}/update.json"
    refused = "hand-eye correction 0.50 mm / 1.80 deg exceeds the tracking accuracy"
    # Step 1: 1.2 deg +- 0.5 applied (0.3 deg inside the gate: 0.6 SE; the shift, 0.5 mm
    # +- 0.25, is 4 SE inside), 1.8 deg +- 0.6 refused (0.3 deg beyond: 0.5 SE): a flip.
    # Which gate refused is read from `rejected_by`, not from the prose.
    _hand_eye_report(tmp_path / "free" / step.format(1), 1.2, 0.5, 0.5, "")
    _hand_eye_report(
        tmp_path / "tools" / step.format(1), 1.8, 0.5, 0.6, "refused", "tracking_accuracy"
    )
    # Step 2: both refused, one by each gate: no flip. The frames that agree exactly give
    # F no error at all, so nothing moves that decision. The tools run's report predates
    # `rejected_by`: its prose names the gate.
    _hand_eye_report(tmp_path / "free" / step.format(2), 1.0, 0.5, 0.25, "widens", "depth_residual")
    _hand_eye_report(tmp_path / "tools" / step.format(2), 2.0, 0.5, None, refused)
    out_json = tmp_path / "out.json"
    text = _compare(tmp_path, out_json, capsys)
    assert (
        "updated step 1: 1.20 deg / 0.50 mm, applied, 0.6 SE | "
        "1.80 deg / 0.50 mm, refused: accuracy, 0.5 SE | FLIP"
    ) in text
    assert (
        "updated step 2: 1.00 deg / 0.50 mm, refused: depth, 2.0 SE | "
        "2.00 deg / 0.50 mm, refused: accuracy, inf SE\n"
    ) in text
    # 0.6 and 0.5 SE at step 1; 2.0 and no error at all at step 2.
    assert "decisions: 4, within one standard error of the gate: 2, flips: 1" in text
    got = json.loads(out_json.read_text())["hand_eye"]
    assert got["updated/1"]["flip"] and not got["updated/2"]["flip"]
    assert abs(got["updated/1"]["free"]["margin_se"] - 0.6) < 1e-9
    assert abs(got["updated/1"]["tools"]["margin_se"] - 0.5) < 1e-9
