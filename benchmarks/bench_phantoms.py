"""Benchmark: the default phantom (seed 0, 5 bites, 0.5 mm CT volumes) end to end.

Goal: under 30 s on the project machine. Prints ``name: value`` lines; the headline
``phantom_s`` (generation + writing the folder) comes last.

    .venv/bin/python benchmarks/bench_phantoms.py [--seed S] [--tet]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from phantoms.generate import build_phantom, write_phantom
from phantoms.params import PhantomConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tet", action="store_true", help="include the tetrahedral export")
    args = parser.parse_args()
    cfg = PhantomConfig(seed=args.seed, tet=args.tet)

    marks: list[tuple[str, float]] = []
    t0 = time.perf_counter()

    def note(msg: str) -> None:
        marks.append((msg, time.perf_counter()))

    ph = build_phantom(cfg, progress=note)
    t_build = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        write_phantom(ph, Path(tmp) / "phantom")
        t_write = time.perf_counter()
        size_mb = (
            sum(p.stat().st_size for p in (Path(tmp) / "phantom").rglob("*") if p.is_file()) / 1e6
        )

    stamp = dict(marks)
    print(f"anatomy_s: {stamp['anatomy'] - t0:.2f}")
    print(f"bites_s: {stamp['bites'] - stamp['anatomy']:.2f}")
    print(f"ct_step0_and_path_s: {stamp['airway path'] - stamp['bites']:.2f}")
    print(f"ct_bites_s: {t_build - stamp['airway path']:.2f}")
    print(f"write_s: {t_write - t_build:.2f}")
    print(f"triangles_step0: {len(ph.steps[0].faces)}")
    print(f"voxels_per_volume: {ph.grid.shape[0] * ph.grid.shape[1] * ph.grid.shape[2]}")
    print(f"removed_mm3: {sum(s.removed_volume_mm3 for s in ph.steps):.2f}")
    print(f"output_mb: {size_mb:.1f}")
    print(f"phantom_s: {t_write - t0:.2f}")


if __name__ == "__main__":
    main()
