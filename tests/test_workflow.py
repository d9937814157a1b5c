"""The Snakemake workflow: lint, dry runs of every target, and the smoke experiment end to end."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile")]
SMOKE = ["--configfile", str(ROOT / "config" / "smoke.yaml")]
SMOKE_METHODS = yaml.safe_load((ROOT / "config" / "smoke.yaml").read_text())["methods"]


def run(args: list[str], cwd: Path, timeout_s: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [*SNAKEMAKE, "-d", str(cwd), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
    )


def test_lint_is_clean(tmp_path: Path) -> None:
    r = run(["--lint", *SMOKE], tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Lints for" not in r.stdout + r.stderr, r.stdout + r.stderr


@pytest.mark.parametrize("target", ["all", "table", "seqlen", "posenoise", "depthnoise", "report"])
@pytest.mark.parametrize("configfile", ["config.yaml", "smoke.yaml"])
def test_dry_run_of_every_target(tmp_path: Path, target: str, configfile: str) -> None:
    # The target goes first: --configfile takes several values.
    r = run(
        [target, "-n", "--cores", "2", "--configfile", str(ROOT / "config" / configfile)], tmp_path
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]


def test_bad_config_is_refused(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text((ROOT / "config" / "smoke.yaml").read_text().replace("bites: 2", "bites: -1"))
    r = run(["-n", "--configfile", str(bad)], tmp_path)
    assert r.returncode != 0
    assert "bites" in r.stdout + r.stderr


@pytest.mark.parametrize(
    ("prior", "expect"),
    [("ct_surface", "--mesh results/default/seed_0/preop/ct_surface.ply"),
     ("model", "--model results/default/seed_0/preop/model.npz")],
)  # fmt: skip
def test_change_aware_finetune_prior_reaches_the_command(
    tmp_path: Path, prior: str, expect: str
) -> None:
    cfg = tmp_path / "prior.yaml"
    cfg.write_text(yaml.safe_dump({"depth": {"change_aware_finetune_prior": prior}}))
    configs = ["--configfile", str(ROOT / "config" / "config.yaml"), str(cfg)]
    r = run(["-n", "-p", "--cores", "2", *configs], tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    finetune = [ln for ln in r.stdout.splitlines() if "depth finetune --kind change-aware" in ln]
    assert finetune and all(expect in ln for ln in finetune), finetune


def test_finetune_seed_offset_reaches_both_finetunings(tmp_path: Path) -> None:
    cfg = tmp_path / "seed.yaml"
    cfg.write_text(yaml.safe_dump({"depth": {"finetune_seed_offset": 100}}))
    configs = ["--configfile", str(ROOT / "config" / "config.yaml"), str(cfg)]
    r = run(["-n", "-p", "--cores", "2", *configs], tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    finetunes = [ln for ln in r.stdout.splitlines() if "chisel depth finetune" in ln]
    assert len(finetunes) == 2 and all("--seed 100 " in ln for ln in finetunes), finetunes
    cfg.write_text(yaml.safe_dump({"depth": {"finetune_seed_offset": -1}}))
    assert run(["-n", *configs], tmp_path).returncode != 0


def test_shading_correction_reaches_the_estimate_rows_only(tmp_path: Path) -> None:
    # The experiments turn the shading's pose correction on; exact depth opts out.
    for name in ("config.yaml", "smoke.yaml", "fine.yaml", "tools.yaml"):
        update = yaml.safe_load((ROOT / "config" / name).read_text())["update"]
        assert update["shading"]["align_by_shading"] is True, name
    r = run(["table", "-n", "-p", "--cores", "2", *SMOKE], tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    updates = [ln for ln in r.stdout.splitlines() if "python -m chisel update " in ln]
    exact = [ln for ln in updates if "--depth-source gt" in ln]
    estimates = [ln for ln in updates if "--depth-source gt" not in ln]
    assert exact and estimates, updates
    assert all("--no-align-by-shading" in ln for ln in exact), exact
    assert not any("align-by-shading" in ln for ln in estimates), estimates


def test_experiments_grow_the_change_threshold_with_depth() -> None:
    # Measured on the network rows (docs/results.md, forty-fifth session); every experiment
    # runs it, so that their tables compare.
    for name in ("config.yaml", "smoke.yaml", "fine.yaml", "tools.yaml"):
        update = yaml.safe_load((ROOT / "config" / name).read_text())["update"]
        assert update["change"]["noise_with_depth"] is True, name


def test_render_sim_section_reaches_sim_render_which_checks_it(tmp_path: Path) -> None:
    cfg = tmp_path / "sim.yaml"
    cfg.write_text(yaml.safe_dump({"render": {"sim": {"tools": {"fraction": 1.5}}}}))
    configs = ["--configfile", str(ROOT / "config" / "smoke.yaml"), str(cfg)]
    r = run(["--cores", "1", "results/smoke/sim_config.yaml", *configs], tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    written = yaml.safe_load((tmp_path / "results/smoke/sim_config.yaml").read_text())
    assert written == {"tools": {"fraction": 1.5}}
    r = run(["--cores", "2", "results/smoke/seed_0/render/render.json", *configs], tmp_path)
    assert r.returncode != 0
    log = (tmp_path / "results/smoke/logs/seed_0/render.log").read_text()
    assert "tools.fraction" in log and "sim_config.yaml" in log, log[-2000:]
    assert not (tmp_path / "results/smoke/seed_0/render").exists()


NOISY_GT = """\
import pathlib, sys
import numpy as np
src, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
for i, path in enumerate(sorted((src / "depth").glob("*.npy"))):
    d = np.load(path).astype(np.float32)
    noise = np.random.default_rng(i).normal(0.0, 0.1, d.shape).astype(np.float32)
    np.save(out / path.name, np.where(d > 0, d + noise, np.nan).astype(np.float32))
"""


def _extra_estimators(tmp_path: Path) -> Path:
    """A config adding two researchers' estimators: a tiny exported TorchScript model
    (relative depth) and a command that writes noisy ground truth (metric)."""
    import torch

    class Brightness(torch.nn.Module):
        def forward(self, rgb: torch.Tensor) -> torch.Tensor:
            return 50.0 - 0.1 * rgb.float().mean(dim=3)

    torch.jit.script(Brightness()).save(str(tmp_path / "tiny.pt"))
    (tmp_path / "noisy_gt.py").write_text(NOISY_GT)
    extra = {
        "tiny_net": {"torchscript": str(tmp_path / "tiny.pt")},
        "noisy_gt": {
            "command": f"{sys.executable} {tmp_path / 'noisy_gt.py'} {{input}} {{output}}",
            "metric": True,
        },
    }
    path = tmp_path / "extra.yaml"
    path.write_text(yaml.safe_dump({"depth": {"extra": extra}}))
    return path


def test_extra_estimators_are_checked(tmp_path: Path) -> None:
    # A built-in method's name, and an entry that is neither a model nor a command.
    for extra, word in (
        ({"updated": {"command": "x {input} {output}"}}, "built-in method"),
        ({"mine": {"metric": True}}, "mine"),
    ):
        path = tmp_path / "extra.yaml"
        path.write_text(yaml.safe_dump({"depth": {"extra": extra}}))
        r = run(["-n", "--configfile", str(ROOT / "config" / "smoke.yaml"), str(path)], tmp_path)
        assert r.returncode != 0 and word in r.stdout + r.stderr, r.stdout + r.stderr


def test_smoke_experiment_end_to_end(tmp_path: Path) -> None:
    extra = ["--configfile", str(ROOT / "config" / "smoke.yaml"), str(_extra_estimators(tmp_path))]
    r = run(["--cores", "2", *extra], tmp_path, timeout_s=1200)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-5000:]
    metrics = json.loads((tmp_path / "results/smoke/metrics.json").read_text())
    steps = {s["step"]: s for s in metrics["steps"]}
    assert sorted(steps) == [0, 1, 2]
    assert set(steps[0]["methods"]) == {"updated"}
    for step in (1, 2):
        # Every configured method has its row (the paper's four and the sweep-only build),
        # and so has each researcher's estimator from depth.extra.
        assert set(steps[step]["methods"]) == set(SMOKE_METHODS) | {"tiny_net", "noisy_gt"}
        for cell in steps[step]["methods"].values():
            assert cell["n_points"] > 0 and cell["mean_mm"] >= 0
    for name in ("metrics.csv", "metrics.md"):
        assert (tmp_path / "results/smoke/seed_0/base" / name).is_file()
    html = (tmp_path / "results/smoke/report.html").read_text()
    assert "no_update" in html and "depth_ablation" in html
    assert "tiny_net" in html and "noisy_gt" in html
    # Each estimator's depth went into its own update: the command's is metric, the
    # model's relative (its scale solved per frame).
    for name, metric in (("noisy_gt", True), ("tiny_net", False)):
        report = tmp_path / f"results/smoke/seed_0/base/{name}/step_01/update.json"
        frames = json.loads(report.read_text())["frames"]
        scales = [f["scale"] for f in frames if f["used"]]
        assert scales and (all(s == 1.0 for s in scales) == metric), (name, scales[:3])
    # An interrupted or repeated run finds nothing left to do.
    again = run(["-n", "--cores", "2", *extra], tmp_path)
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr
    # The same config in another folder gives the same bytes: every image, depth map,
    # model, mesh, CT and score (the scene builds once gave frames one level apart at a
    # pixel, and the fine-tuning other weights; docs/results.md, twenty-seventh session).
    # Files that record paths or timings (sequence.json, render.json, checkpoints) are
    # left out; the checkpoints' effect is in the predicted depth.
    other = tmp_path / "again"
    other.mkdir()
    r = run(["--cores", "2", *extra], other, timeout_s=1200)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-5000:]
    first = tmp_path / "results/smoke"
    kinds = ("*.png", "*.npy", "*.npz", "*.ply", "*.nii.gz", "metrics.json", "metrics.csv")
    files = sorted({p.relative_to(first) for k in kinds for p in first.rglob(k)})
    assert len(files) > 200
    differ = [
        f for f in files if (first / f).read_bytes() != (other / "results/smoke" / f).read_bytes()
    ]
    assert not differ, differ[:10]


def test_dataset_target_renders_one_job_per_seed_and_indexes_them(tmp_path: Path) -> None:
    # A tiny training set over two phantom seeds: one job per seed (a cluster runs them in
    # parallel through the same executor as the benchmark), then the index and the card.
    cfg = tmp_path / "dataset.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {"dataset": {"seeds": "1000-1001", "bites": 1, "frames": 4, "preop_frames": 4,
                         "width": 48, "height": 40, "spp": 1}}
        )
    )  # fmt: skip
    conf = ["--configfile", str(ROOT / "config" / "smoke.yaml"), str(cfg)]
    dry = run(["dataset", "-n", "--cores", "2", *conf], tmp_path)
    assert dry.returncode == 0, dry.stdout + dry.stderr
    assert "dataset_seed        2" in dry.stdout
    r = run(["dataset", "--cores", "2", *conf], tmp_path, timeout_s=900)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-5000:]
    out = tmp_path / "results/smoke/dataset"
    index = json.loads((out / "dataset.json").read_text())
    assert index["seeds"] == [1000, 1001] and index["num_sequences"] == 4
    for entry in index["sequences"]:
        assert (out / entry["path"] / "sequence.json").is_file()
    card = json.loads((out / "dataset_card.json").read_text())
    assert set(card["drawn"]) == {"1000", "1001"} and card["counts"]["frames"] == 16
    # Without seeds the target says what it needs.
    (tmp_path / "none.yaml").write_text(yaml.safe_dump({"dataset": {"frames": 4}}))
    bad = run(["dataset", "-n", "--configfile", str(ROOT / "config" / "smoke.yaml"),
               str(tmp_path / "none.yaml")], tmp_path)  # fmt: skip
    assert bad.returncode != 0 and "dataset.seeds" in bad.stdout + bad.stderr
