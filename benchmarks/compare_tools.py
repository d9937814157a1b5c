"""Issue 22: the update with tools in view against the tool-free run, per step and method.

Reads two finished default-target runs of the workflow (``snakemake --cores 2`` and
``snakemake --cores 2 --configfile config/tools.yaml``, same phantom seed) and prints:

* the tool statistics of the tools run's intraoperative sequences (``render/step_NN``):
  frames in a tool episode (``tools.json``), frames whose ``tool_mask/`` holds any pixel,
  and the mean fraction of the field stop (``camera_mask.png``) the tool covers in those;
* per step (1..bites) and per method row present in both runs: mean correspondence error
  (the paper's metric, ``metrics.json`` ``mean_mm``) of both runs and tools / tool-free;
  the goal is met for a row when every step's ratio is <= 1.1 (and it is reported whether
  it also stays >= 0.9, and at which steps the tools run shows more holes: its
  ``missing_fraction`` over the tool-free run's by more than half a percentage point);
* per step and method, ``missing_fraction`` of both runs: the error counts only pixels
  where the model shows a surface;
* frames used by each update and the mean changed-pixel fraction of its frames, tool and
  tool-free frames apart (``update.json``);
* per step, each run's hand-eye decision for the step (``sequence_registration`` of
  ``update.json``): the correction F's rotation and shift, applied or refused and by
  which gate, and how far F stands from the tracking-accuracy gate in F's own standard
  errors (from the reported ``z_rotation`` / ``z_translation``; the gate from the run's
  ``update_config.yaml``). A decision under one standard error from the gate is one the
  frames do not determine, and ``FLIP`` marks a step the two runs decided apart: the
  cause of most steps that fail the 10 % goal (docs/results.md, forty-seventh session).

Several runs of each (``--free A B --tools C D``: the same renders, the per-patient
fine-tunings seeded apart with ``depth.finetune_seed_offset``) compare the means over the
runs, and the tool-free runs' own spread per step (largest / smallest) is printed beside:
a network row moves by itself by more than 10 % at some steps when only its fine-tuning's
seed changes (docs/results.md, twenty-first session). Tool statistics and update counts
are read from the first run of each.

    .venv/bin/python benchmarks/compare_tools.py [--free results/default ...]
        [--tools results/tools ...] [--seed 0] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from chisel.core.config import load_config_file
from chisel.core.geometry import rotation_angle_deg
from chisel.io.images import decode_image
from chisel.registration import REJECTED_BY_DEPTH_RESIDUAL as DEPTH
from chisel.registration import REJECTED_BY_TRACKING_ACCURACY as TRACKING
from chisel.update_config import UpdateConfig

LOW, HIGH = 0.9, 1.1
MORE_HOLES = 0.005
"""A tools run whose ``missing_fraction`` exceeds the tool-free run's by more than this
(half a percentage point of the pixels) at a step is flagged beside its verdict: the
paper's error counts only pixels where the model shows a surface, so a run that shows
less can look more accurate."""


def _png(path: Path) -> np.ndarray:
    return decode_image(path, cv2.IMREAD_GRAYSCALE, "mask") > 127


def tool_stats(seq: Path) -> dict:
    """Tool episode frames, frames with tool pixels, mean tool fraction of the field stop."""
    if not (seq / "tools.json").exists():  # a tool-free sequence (e.g. a repeat run)
        n = len(list((seq / "rgb").glob("*.png")))
        return {
            "frames": n,
            "episode_frames": 0,
            "tool_frames": [],
            "tool_frame_fraction": 0.0,
            "mean_tool_px_fraction": 0.0,
            "max_tool_px_fraction": 0.0,
        }
    meta = json.loads((seq / "tools.json").read_text())
    episode = [f["index"] for f in meta["frames"] if f.get("tool") is not None]
    cam = seq / "camera_mask.png"
    files = sorted((seq / "tool_mask").glob("*.png"))
    stop = _png(cam) if cam.exists() else np.ones(_png(files[0]).shape, bool)
    fractions = {}
    for f in files:
        m = _png(f) & stop
        if m.any():
            fractions[int(f.stem)] = float(m.sum() / stop.sum())
    return {
        "frames": len(files),
        "episode_frames": len(episode),
        "tool_frames": sorted(fractions),
        "tool_frame_fraction": len(fractions) / len(files),
        "mean_tool_px_fraction": float(np.mean(list(fractions.values()))) if fractions else 0.0,
        "max_tool_px_fraction": float(max(fractions.values())) if fractions else 0.0,
    }


def _means(metrics: dict, key: str = "mean_mm") -> dict[tuple[int, str], float]:
    return {
        (s["step"], m): v[key]
        for s in metrics["steps"]
        if s["step"] > 0
        for m, v in s["methods"].items()
        if v.get(key) is not None
    }


def _run_means(run: Path, sub: str, key: str = "mean_mm") -> dict[tuple[int, str], float]:
    return _means(json.loads((run / sub / "base" / "metrics.json").read_text()), key)


def _mean_over_runs(runs: list[dict[tuple[int, str], float]]) -> dict[tuple[int, str], float]:
    """Each (step, method) error averaged over the runs that all hold it."""
    return {k: float(np.mean([r[k] for r in runs])) for k in runs[0] if all(k in r for r in runs)}


def update_stats(report: Path, tool_frames: set[int]) -> dict:
    rep = json.loads(report.read_text())
    frames = rep["frames"]

    def mean_changed(sel: list[dict]) -> float | None:
        vals = [
            f["changed_fraction"]
            for f in sel
            if f.get("used") and f.get("changed_fraction") is not None
        ]
        return float(np.mean(vals)) if vals else None

    return {
        "used": len(rep["frames_used"]),
        "of": rep["num_frames"],
        "used_tool_frames": sum(1 for f in frames if f.get("used") and f["index"] in tool_frames),
        "changed_tool": mean_changed([f for f in frames if f["index"] in tool_frames]),
        "changed_free": mean_changed([f for f in frames if f["index"] not in tool_frames]),
    }


def accuracy_gate(run: Path) -> tuple[float, float]:
    """The run's tracking-accuracy gate (mm, deg): its ``update_config.yaml``, as ``chisel
    update --config`` reads it, or the library's default without one."""
    path = run / "update_config.yaml"
    cfg = load_config_file(UpdateConfig, path) if path.exists() else UpdateConfig()
    return cfg.registration.tracking_accuracy_mm, cfg.registration.tracking_accuracy_deg


def hand_eye_decision(report: Path, gate_mm: float, gate_deg: float) -> dict | None:
    """A step's hand-eye decision (None: the step estimated no correction F).

    ``margin_se``: how many of F's standard errors F would have to move for the accuracy
    gate to decide the other way (inside the gate: to the nearer bound; outside it: until
    every exceeded bound is met); None where the frames give no standard error.
    """
    reg = json.loads(report.read_text()).get("sequence_registration") or {}
    he = reg.get("hand_eye") or {}
    if "T_cam_from_corrected_cam" not in he:
        return None
    F = np.asarray(he["T_cam_from_corrected_cam"], dtype=float)
    deg, mm = rotation_angle_deg(F[:3, :3]), float(np.linalg.norm(F[:3, 3]))
    # z = size / standard error; z None = the frames agree exactly (no error at all).
    z_deg, z_mm = he.get("z_rotation"), he.get("z_translation")
    se = [
        0.0 if z is None else (size / z if z > 0 else None)
        for size, z in ((mm, z_mm), (deg, z_deg))
    ]
    rejected = str(reg.get("rejected", ""))
    decision = "applied"
    if rejected:
        gate = reg.get("rejected_by")
        if gate is None:  # a report written before `rejected_by`: only the prose says which
            gate = TRACKING if "tracking accuracy" in rejected else DEPTH
        decision = "refused: accuracy" if gate == TRACKING else "refused: depth"
    margin = None
    known = [e for e in se if e is not None]
    if len(known) == 2:
        d = [(size - gate) for size, gate in ((mm, gate_mm), (deg, gate_deg))]
        z = [np.inf if e == 0 else abs(x) / e for x, e in zip(d, known, strict=True)]
        outside = [zi for x, zi in zip(d, z, strict=True) if x > 0]
        margin = float(max(outside) if outside else min(z))
    return {
        "deg": deg, "mm": mm, "applied": not rejected, "decision": decision, "margin_se": margin
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--free", type=Path, nargs="+", default=[Path("results/default")])
    p.add_argument("--tools", type=Path, nargs="+", default=[Path("results/tools")])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="also write everything printed as JSON")
    a = p.parse_args(argv)
    sub = f"seed_{a.seed}"
    free_runs = [_run_means(r, sub) for r in a.free]
    mf, mt = _mean_over_runs(free_runs), _mean_over_runs([_run_means(r, sub) for r in a.tools])
    holes_f = _mean_over_runs([_run_means(r, sub, "missing_fraction") for r in a.free])
    holes_t = _mean_over_runs([_run_means(r, sub, "missing_fraction") for r in a.tools])
    free_dir, tools_dir = a.free[0], a.tools[0]
    steps = sorted({s for s, _ in mt})
    methods = [
        m
        for m in dict.fromkeys(m for _, m in mf)
        if all((s, m) in mt and (s, m) in mf for s in steps)
    ]

    out: dict = {"tools": {}, "rows": {}, "updates": {}, "hand_eye": {}}
    print("# tool statistics (tools run, intraoperative sequences)")
    print(
        "step | frames | in a tool episode | tool pixels in view | mean / max tool px fraction of the field stop"
    )
    all_tool_frames: dict[int, set[int]] = {}
    for s in steps:
        st = tool_stats(tools_dir / sub / "render" / f"step_{s:02d}")
        all_tool_frames[s] = set(st["tool_frames"])
        out["tools"][s] = st
        print(
            f"{s} | {st['frames']} | {st['episode_frames']} | {len(st['tool_frames'])} "
            f"({st['tool_frame_fraction']:.1%}) | {st['mean_tool_px_fraction']:.3f} / "
            f"{st['max_tool_px_fraction']:.3f}"
        )
    n = sum(v["frames"] for v in out["tools"].values())
    k = sum(len(v["tool_frames"]) for v in out["tools"].values())
    weighted = [
        out["tools"][s]["mean_tool_px_fraction"] * len(out["tools"][s]["tool_frames"])
        for s in steps
    ]
    px = sum(weighted) / k if k else 0.0
    out["tools"]["all"] = {
        "frames": n,
        "tool_frames": k,
        "tool_frame_fraction": k / n,
        "mean_tool_px_fraction": float(px),
    }
    print(f"all | {n} | - | {k} ({k / n:.1%}) | {px:.3f} (frame-weighted)")

    print("\n# mean correspondence error, mm: tool-free, tools, tools / tool-free")
    print("method | " + " | ".join(f"step {s}" for s in steps) + " | verdict")
    for m in methods:
        cells, ratios = [], []
        for s in steps:
            r = mt[(s, m)] / mf[(s, m)]
            ratios.append(r)
            cells.append(f"{mf[(s, m)]:.3f}, {mt[(s, m)]:.3f}, {r:.2f}x")
        worse = [s for s, r in zip(steps, ratios, strict=True) if r > HIGH]
        better = [s for s, r in zip(steps, ratios, strict=True) if r < LOW]
        verdict = "PASS" if not worse else f"FAIL (steps {worse})"
        if better:
            verdict += f"; better than 0.9x at steps {better}"
        holes = [
            s
            for s in steps
            if (s, m) in holes_f
            and (s, m) in holes_t
            and holes_t[(s, m)] - holes_f[(s, m)] > MORE_HOLES
        ]
        if holes:
            verdict += f"; more holes at steps {holes}"
        out["rows"][m] = {
            "free_mm": [mf[(s, m)] for s in steps],
            "tools_mm": [mt[(s, m)] for s in steps],
            "ratio": ratios,
            "pass": not worse,
            "more_holes_steps": holes,
        }
        print(f"{m} | " + " | ".join(cells) + f" | {verdict}")
    print("\n# missing fraction (pixels without a surface): tool-free, tools")
    for m in methods:
        if not all((s, m) in holes_f and (s, m) in holes_t for s in steps):
            continue
        out["rows"][m]["free_missing"] = [holes_f[(s, m)] for s in steps]
        out["rows"][m]["tools_missing"] = [holes_t[(s, m)] for s in steps]
        print(
            f"{m} | " + " | ".join(f"{holes_f[(s, m)]:.4f}, {holes_t[(s, m)]:.4f}" for s in steps)
        )
    if len(free_runs) > 1:
        print(f"\n# the {len(free_runs)} tool-free runs' own spread: largest / smallest error")
        for m in methods:
            spread = [
                max(r[(s, m)] for r in free_runs) / min(r[(s, m)] for r in free_runs) for s in steps
            ]
            out["rows"][m]["free_spread"] = spread
            print(f"{m} | " + " | ".join(f"{x:.2f}x" for x in spread))

    print(
        "\n# updates: frames used (tools run: of them with a tool), mean changed-pixel fraction tool / tool-free frames"
    )
    gates = {"free": accuracy_gate(free_dir), "tools": accuracy_gate(tools_dir)}
    hand_eye_lines = []
    for m in methods:
        if m == "no_update":
            continue
        for s in steps:
            rf = free_dir / sub / "base" / m / f"step_{s:02d}" / "update.json"
            rt = tools_dir / sub / "base" / m / f"step_{s:02d}" / "update.json"
            if not (rf.exists() and rt.exists()):
                continue
            uf = update_stats(rf, all_tool_frames[s])
            ut = update_stats(rt, all_tool_frames[s])
            out["updates"][f"{m}/{s}"] = {"free": uf, "tools": ut}

            def fmt(x: float | None) -> str:
                return "-" if x is None else f"{x:.3f}"

            print(
                f"{m} step {s}: used free {uf['used']}/{uf['of']}, tools {ut['used']}/{ut['of']} "
                f"({ut['used_tool_frames']} with tool); changed px tool-frames free/tools "
                f"{fmt(uf['changed_tool'])}/{fmt(ut['changed_tool'])}, other frames "
                f"{fmt(uf['changed_free'])}/{fmt(ut['changed_free'])}"
            )
            df, dt = hand_eye_decision(rf, *gates["free"]), hand_eye_decision(rt, *gates["tools"])
            if df is None or dt is None:
                continue
            flip = df["applied"] != dt["applied"]
            out["hand_eye"][f"{m}/{s}"] = {"free": df, "tools": dt, "flip": flip}

            def fmt_d(d: dict) -> str:
                margin = "-" if d["margin_se"] is None else f"{d['margin_se']:.1f} SE"
                return f"{d['deg']:.2f} deg / {d['mm']:.2f} mm, {d['decision']}, {margin}"

            hand_eye_lines.append(
                f"{m} step {s}: {fmt_d(df)} | {fmt_d(dt)}" + (" | FLIP" if flip else "")
            )
    print(
        "\n# hand-eye decision per step: F's rotation / shift, the decision, F's distance from "
        "the accuracy gate in its standard errors; tool-free | tools"
    )
    for line in hand_eye_lines:
        print(line)
    if out["hand_eye"]:
        decided = [d for v in out["hand_eye"].values() for d in (v["free"], v["tools"])]
        near = sum(d["margin_se"] is not None and d["margin_se"] < 1.0 for d in decided)
        flips = sum(v["flip"] for v in out["hand_eye"].values())
        out["hand_eye_summary"] = {"decisions": len(decided), "within_1_se": near, "flips": flips}
        print(
            f"decisions: {len(decided)}, within one standard error of the gate: {near}, flips: {flips}"
        )
    if a.json:
        a.json.write_text(json.dumps(out, indent=1, default=list) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
