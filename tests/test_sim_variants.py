"""The GPU variant renders what the CPU variant renders (skipped where no GPU works).

CI has no GPU, so this runs only on a machine where ``cuda_ad_rgb`` passes its probe: it
is the first check to run when one is lent. Both renders go through the CLI in their own
process, as users run them, from the same phantom, seed and options.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from chisel.core.mitsuba_variant import _gpu_present, probe_variant
from chisel.io.sequence import Sequence
from sim.synthetic import write_toy_phantom

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    not (_gpu_present() and probe_variant("cuda_ad_rgb")[0]),
    reason="no working cuda_ad_rgb (no GPU here)",
)


def _render(phantom: Path, out: Path, variant: str) -> Path:
    cmd = [sys.executable, "-m", "sim", "render", "--phantom", str(phantom), "--out", str(out)]
    cmd += ["--variant", variant, "--width", "96", "--height", "80", "--spp", "16"]
    cmd += ["--frames", "4", "--preop-frames", "3", "--eval-poses", "2", "--seed", "3"]
    done = subprocess.run(cmd + ["--quiet"], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return out


def test_cuda_and_llvm_render_the_same_depth_and_colour(tmp_path: Path) -> None:
    phantom = write_toy_phantom(tmp_path / "phantom", n_bites=1)
    cpu = _render(phantom, tmp_path / "llvm", "llvm_ad_rgb")
    gpu = _render(phantom, tmp_path / "cuda", "cuda_ad_rgb")
    for name in ("preop", "step_01"):
        a, b = Sequence(cpu / name), Sequence(gpu / name)
        np.testing.assert_array_equal(a.poses, b.poses)  # paths do not depend on the variant
        for i in range(len(a)):
            da, db = a.depth_mm(i), b.depth_mm(i)
            both = np.isfinite(da) & np.isfinite(db)
            assert (np.isfinite(da) != np.isfinite(db)).mean() < 0.002  # silhouettes only
            assert np.median(np.abs(da[both] - db[both])) <= 0.01
            # Same samples (counter-based), float precision apart: 8-bit values agree but
            # for rounding, a few pixels at silhouettes excepted.
            diff = np.abs(a.rgb(i).astype(int) - b.rgb(i).astype(int))
            assert np.median(diff) == 0 and (diff > 8).mean() < 0.01
