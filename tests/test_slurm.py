"""The smoke experiment through SLURM: a single-node cluster on this machine
(``scripts/slurm-local.sh``), Snakemake's SLURM executor plugin with
``workflow/profiles/slurm``, every job submitted with sbatch; its ``metrics.json`` equals
the local run's. Skipped, with the reason, where SLURM is not installed or this is not root
(the daemons need root)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "slurm-local.sh"
SNAKEMAKE = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile")]
SMOKE = ["--configfile", str(ROOT / "config" / "smoke.yaml")]
PATH = os.environ.get("PATH", "") + ":/usr/sbin:/sbin"


def _missing() -> str | None:
    for tool in ("slurmctld", "slurmd", "munged", "sbatch", "squeue"):
        if shutil.which(tool, path=PATH) is None:
            return f"SLURM is not installed ({tool} not found; scripts/setup.sh installs slurm-wlm munge)"
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        return "snakemake-executor-plugin-slurm is not installed (pip install -e '.[dev]')"
    if os.geteuid() != 0:
        return "starting the SLURM daemons needs root"
    return None


pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(_missing() is not None, reason=str(_missing())),
]


@pytest.fixture(scope="module")
def cluster():
    """A running cluster; stopped afterwards when this fixture started it."""
    env = {**os.environ, "PATH": PATH}
    running = subprocess.run(["bash", str(SCRIPT), "status"], capture_output=True, env=env)
    started = running.returncode != 0
    if started:
        r = subprocess.run(
            ["bash", str(SCRIPT), "start"], capture_output=True, text=True, env=env, timeout=180
        )
        assert r.returncode == 0, r.stdout + r.stderr
    yield
    if started:
        subprocess.run(["bash", str(SCRIPT), "stop"], capture_output=True, env=env, timeout=120)


def _run(args: list[str], cwd: Path, timeout_s: float = 2400) -> tuple[float, str]:
    env = {**os.environ, "PATH": PATH, "PYTHONUNBUFFERED": "1"}
    t0 = time.monotonic()
    r = subprocess.run(
        [*SNAKEMAKE, "-d", str(cwd), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
    )
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-6000:]
    return time.monotonic() - t0, out


def test_smoke_on_slurm_equals_the_local_run(cluster, tmp_path: Path) -> None:
    local, slurm = tmp_path / "local", tmp_path / "slurm"
    local.mkdir()
    slurm.mkdir()
    t_local, _ = _run(["--cores", "2", *SMOKE], local)
    profile = ["--workflow-profile", str(ROOT / "workflow" / "profiles" / "slurm")]
    t_slurm, log = _run([*profile, *SMOKE], slurm)
    (tmp_path / "wall_s.json").write_text(json.dumps({"local": t_local, "slurm": t_slurm}))
    print(f"\nsmoke wall time: local {t_local:.0f} s, SLURM {t_slurm:.0f} s ({tmp_path})")
    a = json.loads((local / "results/smoke/metrics.json").read_text())
    b = json.loads((slurm / "results/smoke/metrics.json").read_text())
    assert a == b
    # every job went through sbatch (all but the target rule `all`), none ran locally, and
    # each left its SLURM log (the profile keeps the logs of successful jobs)
    done = re.findall(r"(\d+) of (\d+) steps \(100%\) done", log)
    assert done, log[-3000:]
    total = int(done[-1][1])
    submitted = log.count("has been submitted with SLURM jobid")
    jobs = sum(1 for _ in (slurm / ".snakemake" / "slurm_logs").rglob("*.log"))
    assert submitted > 10 and submitted == total - 1 == jobs, (submitted, total, jobs)
    assert "localrule" not in log.replace("localrule all", "")
