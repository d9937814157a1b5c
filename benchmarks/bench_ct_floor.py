"""Benchmark: the CT's own floor under the paper's metric, beside the exact-depth row.

What is the least error any update could reach on the model's grid? For each seed and
step of a finished workflow run (`table` or `all`), build the model from that step's own
true CT (`chisel build --from-ct ct/step_KK_hu.nii.gz` with the preop sequence and the
workflow's model options: a perfect update, as far as a CT on the model's grid holds the
tissue) and score it against the step's exact mesh with the evaluation's protocol (its
poses, ROI box and field stop, `chisel.eval.step.evaluate_step`), together with the
`depth_ablation` row (exact depth) of the same run as the peer, in the same call.

The phantom's truth is the exact cut mesh; a 0.5 mm CT rounds the corners of a cut
lamella's end face, and a ray that meets the face there passes through the model to the
cell behind it, ~15 mm deeper. A few % of such pixels set the mean.

Prints ``name: value`` lines: per seed and step ``seed_S_step_K_ct_floor_mm``,
``seed_S_step_K_exact_mm`` and ``seed_S_step_K_exact_over_floor``; ``cpu_simd``,
``elapsed_s``, ``exact_over_floor_max`` and last ``ct_floor_max_mm`` (worst step of any
seed; issue 19's exact-depth goal is <= 0.3 mm).

    .venv/bin/python benchmarks/bench_ct_floor.py --run /tmp/fid/results/table13 --seeds 0-4
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chisel.eval.step import evaluate_step  # noqa: E402
from sim.dataset import parse_seeds  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from host import cpu_simd  # noqa: E402


def build_floor_mesh(ct: Path, preop: Path, out: Path, model: dict) -> Path:
    """The model built from one step's true CT with the preop sequence, as a mesh file."""
    out.mkdir(parents=True, exist_ok=True)
    npz, ply = out / "model.npz", out / "mesh.ply"
    opts = [
        "--voxel-size-mm", str(model["voxel_size_mm"]), "--trunc-mm", str(model["trunc_mm"]),
        "--max-miss-fraction", str(model.get("max_miss_fraction", 0.05)),
    ]  # fmt: skip
    run = [sys.executable, "-m", "chisel"]
    subprocess.run(
        [*run, "build", "--from-ct", str(ct), "--sequence", str(preop), *opts, "--no-progress",
         "--out", str(npz)],
        check=True, capture_output=True,
    )  # fmt: skip
    subprocess.run([*run, "mesh", "--model", str(npz), "--out", str(ply)], check=True,
                   capture_output=True)  # fmt: skip
    return ply


def floor_of_seed(seed_dir: Path, model: dict, work: Path) -> list[tuple[int, float, float]]:
    """(step, CT floor mm, exact-depth mm) for every step of one seed's results."""
    phantom = seed_dir / "phantom"
    manifest = json.loads((phantom / "phantom.json").read_text())
    out = []
    for entry in manifest["steps"][1:]:
        k = int(entry["step"])
        step_json = json.loads((seed_dir / "base" / "eval" / f"step_{k:02d}.json").read_text())
        box = step_json["protocol"]["roi_box_mm"]
        floor = build_floor_mesh(
            phantom / entry["ct_hu"], seed_dir / "render" / "preop", work / f"{k:02d}", model
        )
        cells = evaluate_step(
            phantom / entry["mesh"],
            {
                "ct_floor": floor,
                "exact": seed_dir / "base" / "depth_ablation" / f"step_{k:02d}" / "mesh.ply",
            },
            seed_dir / "render" / "eval" / f"step_{k:02d}",
            box,
            k,
        )["methods"]
        out.append((k, cells["ct_floor"]["mean_mm"], cells["exact"]["mean_mm"]))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True,
                        help="a workflow experiment's results folder (results/EXPERIMENT)")  # fmt: skip
    parser.add_argument("--seeds", default="0-4")
    parser.add_argument("--configfile", type=Path, default=ROOT / "config" / "config.yaml",
                        help="the run's config, for the model options")  # fmt: skip
    args = parser.parse_args()
    model = yaml.safe_load(args.configfile.read_text())["model"]
    t0 = time.perf_counter()
    floors, ratios = [], []
    with tempfile.TemporaryDirectory(prefix="chisel-floor-") as tmp:
        for seed in parse_seeds(args.seeds):
            seed_dir = args.run / f"seed_{seed}"
            if not (seed_dir / "base" / "eval").is_dir():
                print(f"seed_{seed}_missing: {seed_dir} holds no evaluated run")
                continue
            for k, floor_mm, exact_mm in floor_of_seed(seed_dir, model, Path(tmp) / str(seed)):
                print(f"seed_{seed}_step_{k}_ct_floor_mm: {floor_mm:.3f}")
                print(f"seed_{seed}_step_{k}_exact_mm: {exact_mm:.3f}")
                print(f"seed_{seed}_step_{k}_exact_over_floor: {exact_mm / floor_mm:.3f}")
                floors.append(floor_mm)
                ratios.append(exact_mm / floor_mm)
    if not floors:
        print("ct_floor_max_mm: nan")
        return 1
    print(f"cpu_simd: {cpu_simd()}")
    print(f"elapsed_s: {time.perf_counter() - t0:.1f}")
    print(f"exact_over_floor_max: {max(ratios):.3f}")
    print(f"ct_floor_max_mm: {max(floors):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
