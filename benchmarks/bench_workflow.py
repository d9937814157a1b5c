"""Wall time of the default experiment end to end (goal: <= 15 min on 2 cores).

Runs `snakemake --cores 2` on a config (default: config/config.yaml) in a fresh folder,
then prints the experiment's headline errors from its metrics.json and, last, the wall
time. `--configfile config/smoke.yaml` times the smoke experiment (goal: <= 3 min).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]


def run_workflow(
    target: str,
    workdir: Path,
    configfile: Path,
    cores: int = 2,
    overrides: Mapping[str, Any] | None = None,
) -> tuple[str, float] | None:
    """Run a workflow target in ``workdir``: (experiment name, wall seconds), or None after
    printing ``workflow_failed`` and the log's tail.

    overrides : config keys laid over ``configfile``, written as a second YAML config file
    (``--config KEY=[0, 1]`` would hand Snakemake's schema a list of strings).
    """
    # The target goes before --configfile, which takes several values.
    cmd = [sys.executable, "-m", "snakemake", target, "-s", str(ROOT / "Snakefile")]
    cmd += ["-d", str(workdir), "--cores", str(cores), "--configfile", str(configfile.resolve())]
    if overrides:
        workdir.mkdir(parents=True, exist_ok=True)
        overlay = workdir / "bench_overrides.yaml"
        overlay.write_text(yaml.safe_dump(dict(overrides)))
        cmd.append(str(overlay.resolve()))
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall_s = time.perf_counter() - t0
    if r.returncode != 0:
        sys.stderr.write(r.stdout[-4000:] + r.stderr[-4000:])
        print(f"workflow_failed: rc={r.returncode}")
        return None
    return next(workdir.joinpath("results").iterdir()).name, wall_s


@contextlib.contextmanager
def work_folder(workdir: Path | None, prefix: str) -> Iterator[Path]:
    """``workdir``, or a temp folder removed at exit: a run leaves ~0.6 GB per seed, and a
    benchmark run again and again must not fill the disk."""
    if workdir is not None:
        yield workdir
        return
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        yield Path(tmp)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--configfile", type=Path, default=ROOT / "config" / "config.yaml")
    parser.add_argument(
        "--workdir", type=Path, help="keep results here (default: a temp dir, removed at exit)"
    )
    parser.add_argument("--target", default="all")
    args = parser.parse_args()
    with work_folder(args.workdir, "chisel-bench-") as workdir:
        return report(args, workdir)


def report(args: argparse.Namespace, workdir: Path) -> int:
    ran = run_workflow(args.target, workdir, args.configfile)
    if ran is None:
        return 1
    experiment, wall_s = ran
    metrics = json.loads((workdir / "results" / experiment / "metrics.json").read_text())
    print(f"experiment: {experiment}")
    print(f"workdir: {workdir if args.workdir else '(removed; --workdir keeps it)'}")
    for step in metrics["steps"]:
        label = step["label"].replace(" ", "_")
        for method, cell in step["methods"].items():
            print(f"{label}_{method}_mean_mm: {cell['mean_mm']:.3f}")
            print(f"{label}_{method}_std_mm: {cell['std_mm']:.3f}")
    print(f"workflow_s: {wall_s:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
