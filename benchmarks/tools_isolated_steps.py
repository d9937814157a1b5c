"""Issue 22: the effect of tools on one step, without the drift carried from earlier steps.

In the workflow each step updates the model the same method left at the step before, so a
tools run's step k starts from a model that earlier tool frames already changed. This
script replays step k of the tools run from the *tool-free* run's model of step k-1 (same
update config, same depth network for ``change_aware``) and scores it like the workflow
(mean correspondence error inside the change box, ``chisel.eval.step.evaluate_step``), so
tools / tool-free at step k is the effect of that step's tool frames alone. ``--control``
also replays the tool-free sequence itself (should reproduce the tool-free run's figure).

    PYTHONPATH=. .venv/bin/python benchmarks/tools_isolated_steps.py \
        --methods updated change_aware --steps 2 3 4 5 [--control] [--out /tmp/iso]

``--chain`` instead chains the tools replays from step 1 (the tools run again, with the
tool-free run's fine-tuned networks). Prints one ``method step free_mm isolated_tools_mm ratio [control_mm]`` line per pair.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chisel.eval.step import evaluate_step  # noqa: E402
from chisel.io.manifest import named_path, read_json_manifest  # noqa: E402


def depth_opts(method: str, run: Path, seed: int, step: int, free: Path) -> list[str]:
    if method == "depth_ablation":
        return ["--depth-source", "gt"]
    if method in ("updated", "registration_ablation"):
        opts = ["--depth-source", f"sequence:{run}/seed_{seed}/depth/pred/step_{step:02d}"]
        return opts + (["--no-register"] if method == "registration_ablation" else [])
    if method == "change_aware":
        # the tool-free run's fine-tuned change-aware network, on either sequence
        return [
            "--depth-source",
            f"change-aware:{free}/seed_{seed}/depth/change_aware_finetuned.pt",
        ]
    raise SystemExit(f"unsupported method {method}")


def replay(
    method: str, step: int, run: Path, free: Path, seed: int, out: Path, prev: Path | None = None
) -> float:
    """Update step ``step`` on ``run``'s sequence from ``prev`` (default: the tool-free
    run's model of the step before) into ``out``; the mean correspondence error, mm."""
    if prev is None:
        prev = (
            free / f"seed_{seed}/preop/model.npz"
            if step == 1
            else free / f"seed_{seed}/base/{method}/step_{step - 1:02d}/model.npz"
        )
    out.mkdir(parents=True, exist_ok=True)
    model, mesh = out / "model.npz", out / "mesh.ply"
    cmd = [
        sys.executable, "-m", "chisel", "update", "--model", str(prev),
        "--sequence", str(run / f"seed_{seed}/render/step_{step:02d}"),
        "--config", str(free / "update_config.yaml"), "--allow-unused-step",
        *depth_opts(method, run, seed, step, free),
        "--out", str(model), "--report", str(out / "update.json"), "--no-progress",
    ]  # fmt: skip
    with open(out / "update.log", "w") as log:
        subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT)
    subprocess.run(
        [sys.executable, "-m", "chisel", "mesh", "--model", str(model), "--out", str(mesh)],
        check=True, capture_output=True,
    )  # fmt: skip
    manifest_path = free / f"seed_{seed}/phantom/phantom.json"
    manifest = read_json_manifest(manifest_path)
    steps = {s["step"]: s for s in manifest["steps"]}
    res = evaluate_step(
        gt_mesh_path=named_path(manifest_path, steps[step]["mesh"], "mesh"),
        method_mesh_paths={method: mesh},
        eval_sequence_path=free / f"seed_{seed}/render/eval/step_{step:02d}",
        roi_box_mm=[v for corner in manifest["roi_box_mm"] for v in corner],
        step=step,
    )
    return float(res["methods"][method]["mean_mm"])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--free", type=Path, default=Path("results/default"))
    p.add_argument("--tools", type=Path, default=Path("results/tools"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--methods", nargs="+", default=["updated", "change_aware"])
    p.add_argument("--steps", nargs="+", type=int, default=[2, 3, 4, 5])
    p.add_argument("--control", action="store_true", help="also replay the tool-free sequence")
    p.add_argument("--out", type=Path, default=Path("results/tools_isolated"))
    p.add_argument(
        "--chain",
        action="store_true",
        help="chain the tools replays instead (step k from this script's step k-1 model; "
        "give --steps 1 2 ...): the whole tools run, but with the tool-free run's networks",
    )
    a = p.parse_args()
    free_metrics = json.loads((a.free / f"seed_{a.seed}/base/metrics.json").read_text())
    free_mm = {
        (s["step"], m): v["mean_mm"] for s in free_metrics["steps"] for m, v in s["methods"].items()
    }
    rows = []
    for m in a.methods:
        prev = None
        for s in a.steps:
            t_out = a.out / f"{m}/step_{s:02d}/{'chain' if a.chain else 'tools'}"
            t = replay(m, s, a.tools, a.free, a.seed, t_out, prev if a.chain else None)
            prev = t_out / "model.npz"
            c = (
                replay(m, s, a.free, a.free, a.seed, a.out / f"{m}/step_{s:02d}/free")
                if a.control
                else None
            )
            f = free_mm[(s, m)]
            rows.append(
                {
                    "method": m,
                    "step": s,
                    "free_mm": f,
                    "tools_isolated_mm": t,
                    "ratio": t / f,
                    "control_mm": c,
                }
            )
            print(
                f"{m} {s} {f:.3f} {t:.3f} {t / f:.3f}" + ("" if c is None else f" {c:.3f}"),
                flush=True,
            )
    (a.out / ("chain.json" if a.chain else "isolated.json")).write_text(
        json.dumps(rows, indent=1) + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
