"""Hostile values reaching the workflow's shell commands and the external depth estimators:
config paths with ``$(...)``, quotes and spaces; ``experiment: ".."``; a depth command
that pastes a folder into ``bash -c``; TorchScript models that return no depth tensor;
the ``chisel external-depth`` error prefix."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera
from chisel.depth.external import command_line, external_depth
from chisel.depth.infer import load_depth_source, predict_sequence
from chisel.io.sequence import Frame, Sequence, write_sequence

ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile")]
SMOKE = str(ROOT / "config" / "smoke.yaml")
H, W = 24, 32
# A file name that is shell code when pasted into a command line unquoted.
HOSTILE = "ck $(touch INJ) 'q'.pt"
HOSTILE_DIR = "my data $(touch INJ)"


def _snakemake(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*SNAKEMAKE, "-d", str(cwd), *args], capture_output=True, text=True, timeout=300
    )


def _run_printed_commands(lines: list[str], cwd: Path) -> list[list[str]]:
    """Run shell commands as ``snakemake -p`` printed them, with a stand-in ``python`` on
    PATH that records its arguments; returns each call's argv."""
    bin_dir, calls = cwd / "stub_bin", cwd / "calls"
    bin_dir.mkdir()
    calls.mkdir()
    stub = bin_dir / "python"
    stub.write_text(f'#!/bin/sh\nprintf "%s\\0" "$@" > "$(mktemp {calls}/call.XXXXXX)"\n')
    stub.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    for line in lines:
        log = re.search(r"> (\S+) 2>&1$", line)
        assert log, line
        (cwd / log.group(1)).parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(["bash", "-c", line], cwd=cwd, env=env, check=True, timeout=60)
    return [p.read_text().split("\0")[:-1] for p in sorted(calls.iterdir())]


@pytest.mark.parametrize(
    ("finetune", "targets", "commands"),
    [(True, ["depth/finetuned.pt", "depth/change_aware_finetuned.pt"],
      ["chisel depth finetune --checkpoint", "chisel depth finetune --kind change-aware"]),
     (False, ["depth/pred/step_01", "base/change_aware/step_01/model.npz"],
      ["chisel depth predict", "chisel update"])],
)  # fmt: skip
def test_checkpoint_paths_reach_the_shell_quoted(
    tmp_path: Path, finetune: bool, targets: list[str], commands: list[str]
) -> None:
    # config depth.checkpoint / change_aware_checkpoint are any string: a name holding
    # $(...) ran it in the finetune, change-aware finetune, predict and update jobs.
    work = tmp_path / "work"
    work.mkdir()
    for name in ("base", "change"):
        (work / f"{name} {HOSTILE}").write_bytes(b"")
    cfg = tmp_path / "hostile.yaml"
    depth = {"checkpoint": f"base {HOSTILE}", "change_aware_checkpoint": f"change {HOSTILE}"}
    cfg.write_text(yaml.safe_dump({"depth": {**depth, "finetune": finetune}}))
    r = _snakemake(
        [*(f"results/smoke/seed_0/{t}" for t in targets), "-n", "-p", "--cores", "1",
         "--configfile", SMOKE, str(cfg)],
        work,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    printed = [ln.split("Shell command: ", 1)[-1].strip() for ln in r.stdout.splitlines()]
    lines = [ln for ln in printed if any(ln.startswith(f"python -m {c}") for c in commands)]
    assert len(lines) == 2, printed
    argvs = _run_printed_commands(lines, work)
    assert not (work / "INJ").exists()
    # Each checkpoint reached its command as one whole argument.
    ckpt_args = [a for argv in argvs for a in argv if HOSTILE in a]
    assert sorted(ckpt_args) == sorted(
        {
            True: [f"base {HOSTILE}", f"change {HOSTILE}"],
            False: [f"base {HOSTILE}", f"change-aware:change {HOSTILE}"],
        }[finetune]
    ), argvs


@pytest.mark.parametrize("name", ["..", ".", ".hidden"])
def test_experiment_names_outside_results_are_refused(tmp_path: Path, name: str) -> None:
    # ".." passed the old pattern, and the run planned results/../metrics.json.
    r = _snakemake(["-n", "--configfile", SMOKE, "--config", f"experiment={name}"], tmp_path)
    out = r.stdout + r.stderr
    assert r.returncode != 0 and "experiment" in out and "does not match" in out, out[-2000:]
    assert "metrics.json" not in out


def _sequence(root: Path) -> Sequence:
    cam = Camera.from_fov(W, H, 70.0)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(2):
        T = np.eye(4)
        T[:3, 3] = [10.0 * i + 5.0, 0.0, 0.0]
        depth = (20.0 + 5.0 * rng.random((H, W))).astype(np.float32)
        rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        frames.append(Frame(i, T, rgb=rgb, depth_mm=depth))
    return Sequence(write_sequence(root / "seq", cam, frames))


COPY_GT = """\
import pathlib, sys
import numpy as np
src, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
for path in sorted((src / "depth").glob("*.npy")):
    np.save(out / path.name, np.load(path).astype(np.float32))
"""


def test_a_folder_pasted_into_bash_c_is_refused_and_the_cli_names_itself(
    tmp_path: Path,
) -> None:
    seq = _sequence(tmp_path / HOSTILE_DIR)
    (tmp_path / "est.py").write_text(COPY_GT)
    r = subprocess.run(
        [sys.executable, "-m", "chisel", "external-depth", "--sequence", str(seq.path),
         "--out", "out", "--metric", "--command", "bash -c 'python est.py {input} {output}'"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 1
    assert not (tmp_path / "INJ").exists() and not (tmp_path / "out").exists()
    # The subcommand's name, not the --command value (they shared argparse's dest).
    assert r.stderr.startswith("chisel external-depth: error: --command: "), r.stderr
    assert "whole argument" in r.stderr and '"$1" "$2"' in r.stderr, r.stderr
    for bad in ("python est.py --in={input} {output}", "sh -c 'cd {output}' {input}"):
        with pytest.raises(InvalidInputError, match=r"--command: .*whole argument"):
            command_line(bad, seq.path, tmp_path)


def test_the_documented_shell_form_takes_any_folder_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # where a `touch INJ` would land
    seq = _sequence(tmp_path / HOSTILE_DIR)
    script = tmp_path / "est.py"
    script.write_text(COPY_GT)
    cmd = f'bash -c \'{sys.executable} {script} "$1" "$2"\' _ {{input}} {{output}}'
    out = external_depth(seq, tmp_path / HOSTILE_DIR / "depth out", command=cmd, metric=True)
    assert not (tmp_path / "INJ").exists()
    for i in range(len(seq)):
        np.testing.assert_allclose(Sequence(out).depth_mm(i), seq.depth_mm(i), rtol=1e-6)


class _Tuple(torch.nn.Module):
    def forward(self, rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d = 50.0 - 0.1 * rgb.float().mean(dim=3)
        return d, d


class _Int(torch.nn.Module):
    def forward(self, rgb: torch.Tensor) -> int:
        return 3


class _List(torch.nn.Module):
    def forward(self, rgb: torch.Tensor) -> list[torch.Tensor]:
        return [50.0 - 0.1 * rgb.float().mean(dim=3)]


class _DoubleBatch(torch.nn.Module):
    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        d = 50.0 - 0.1 * rgb.float().mean(dim=3)
        return torch.cat([d, d])


@pytest.mark.parametrize(
    ("module", "what"),
    [(_Tuple, r"returned an object of type tuple, not a tensor"), (_Int, r"returned an object of type int, not a tensor"),
     (_List, r"returned an object of type list, not a tensor"),
     (_DoubleBatch, r"returned a torch.float32 tensor of shape \(2, 24, 32\); expected .* shape \(1, 24, 32\)")],
)  # fmt: skip
def test_torchscript_outputs_that_are_no_depth_tensor_are_named(
    tmp_path: Path, module: type[torch.nn.Module], what: str
) -> None:
    seq = _sequence(tmp_path)
    model = tmp_path / f"bad_{module.__name__}.pt"
    torch.jit.script(module()).save(str(model))
    named = rf"bad_{module.__name__}\.pt: the depth model {what}"
    # chisel external-depth --torchscript
    with pytest.raises(InvalidInputError, match=named):
        external_depth(seq, tmp_path / "extra", torchscript=model)
    # chisel depth predict --checkpoint (and the updater's network:FILE depth source)
    with pytest.raises(InvalidInputError, match=named):
        predict_sequence(load_depth_source(model), seq, tmp_path / "pred")
    assert not (tmp_path / "extra").exists() and not (tmp_path / "pred").exists()


def test_cli_names_the_torchscript_file_under_its_own_prefix(tmp_path: Path) -> None:
    seq = _sequence(tmp_path)
    model = tmp_path / "tuple.pt"
    torch.jit.script(_Tuple()).save(str(model))
    r = subprocess.run(
        [sys.executable, "-m", "chisel", "external-depth", "--sequence", str(seq.path),
         "--out", str(tmp_path / "out"), "--torchscript", str(model)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 1
    assert r.stderr.startswith(f"chisel external-depth: error: {model}: "), r.stderr
    assert "returned an object of type tuple" in r.stderr, r.stderr
