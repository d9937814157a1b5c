"""Bad input at the command line: one line naming the problem, inputs and outputs kept.

Cases found by trying to break ``python -m sim``: an output folder that is (or lies in)
the input phantom, OS errors and interrupts as tracebacks, and ``sim dataset`` options
and ``--resume`` states that crashed or silently mixed renders.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import sys
from pathlib import Path

import numpy as np
import pytest

from chisel.core.atomic import atomic_dir
from chisel.core.errors import InvalidInputError, run_command
from chisel.io.manifest import MAX_MANIFEST_BYTES
from chisel.io.sequence import Sequence
from sim.cli import main
from sim.config import SimConfig, replace_in
from sim.dataset import _finished_render, build_dataset
from sim.errors import ConfigError
from sim.synthetic import write_toy_phantom

SMALL = ["--frames", "2", "--preop-frames", "2", "--width", "32", "--height", "24"]
SMALL += ["--spp", "1", "--quiet"]


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_render_refuses_an_output_that_is_or_lies_in_the_phantom(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    phantom = write_toy_phantom(tmp_path / "ph", n_bites=1)
    before = tree(phantom)
    for out, why in [
        (phantom, "would replace the input"),
        (phantom / "meshes", "inside the input"),
        (tmp_path, "would replace the input"),
    ]:
        rc = main(
            ["render", "--phantom", str(phantom), "--out", str(out), *SMALL, "--eval-poses", "1"]
        )
        err = capsys.readouterr().err.strip()
        assert rc == 1 and why in err and len(err.splitlines()) == 1, err
    assert tree(phantom) == before


def test_run_command_turns_os_errors_and_interrupts_into_one_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    def missing() -> int:
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", "seq/rgb/000001.png")

    def interrupted() -> int:
        raise KeyboardInterrupt

    def user_error() -> int:
        raise InvalidInputError("phantom.json", "bad")

    assert run_command("sim render", missing) == 1
    assert capsys.readouterr().err == (
        "sim render: error: seq/rgb/000001.png: No such file or directory\n"
    )
    assert run_command("sim render", interrupted) == 130
    assert "interrupted" in capsys.readouterr().err
    assert run_command("sim render", user_error) == 1
    assert capsys.readouterr().err == "sim render: error: phantom.json: bad\n"
    assert run_command("sim render", lambda: 0) == 0


def test_sigterm_removes_the_temporary_output_and_keeps_the_old_one(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("earlier result")
    handler = signal.getsignal(signal.SIGTERM)

    def killed_midway() -> int:
        with atomic_dir(out, "old.txt") as tmp:
            (tmp / "half.txt").write_text("half")
            os.kill(os.getpid(), signal.SIGTERM)
        return 0

    with pytest.raises(SystemExit) as exc:
        run_command("sim render", killed_midway)
    assert exc.value.code == 128 + signal.SIGTERM
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no .out.tmp-* left
    assert (out / "old.txt").read_text() == "earlier result"
    assert signal.getsignal(signal.SIGTERM) == handler  # restored


def test_dataset_options_that_crashed_now_give_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    afile = tmp_path / "afile"
    afile.write_text("keep")
    cases = [
        (["--phantom-args", '--seed "'], "--phantom-args: cannot split"),
        (["--phantom-cmd", "/nonexistent/gen"], "cannot run the phantom generator"),
        (["--out", str(afile)], "exists and is not a folder"),
    ]
    for extra, why in cases:
        argv = ["dataset", "--seeds", "1", "--bites", "1", "--out", str(tmp_path / "ds")]
        rc = main([*argv, *SMALL, *extra])
        err = capsys.readouterr().err.strip()
        assert rc == 1 and why in err and len(err.splitlines()) == 1, err
    assert afile.read_text() == "keep"


def test_dataset_resume_renders_broken_seeds_again_and_refuses_other_options(
    tmp_path: Path, tiny_sim_config: SimConfig
) -> None:
    cfg = tiny_sim_config
    gen = f"{sys.executable} -m sim.synthetic"  # the toy phantom, generator contract
    out = tmp_path / "ds"
    first = build_dataset(out, [1, 2], cfg, bites=1, phantom_cmd=gen, progress=False)
    rgb = Sequence(out / "seed_1/step_01").rgb(0)
    # A half-deleted seed and a corrupt render.json are rendered again, not crashed on.
    shutil.rmtree(out / "seed_1/preop")
    (out / "seed_2/render.json").write_text("{not json")
    again = build_dataset(out, [1, 2], cfg, bites=1, phantom_cmd=gen, resume=True, progress=False)
    assert again == first
    assert (out / "seed_1/preop/sequence.json").is_file()
    np.testing.assert_array_equal(Sequence(out / "seed_1/step_01").rgb(0), rgb)
    # Other options than the finished seeds were rendered with: refused, nothing changed.
    listing = (out / "dataset.json").read_text()
    wider = replace_in(cfg, **{"camera.width": 48})
    with pytest.raises(ConfigError, match=r"seed_1/render\.json.*camera\.width"):
        build_dataset(out, [1, 2, 3], wider, bites=1, phantom_cmd=gen, resume=True, progress=False)
    with pytest.raises(ConfigError, match="bites"):
        build_dataset(out, [1], cfg, bites=2, phantom_cmd=gen, resume=True, progress=False)
    assert (out / "dataset.json").read_text() == listing
    assert not (out / "seed_3").exists()
    assert json.loads(listing)["num_sequences"] == 4


def _write_bad_json(path: Path, kind: str) -> None:
    """A file the bounded JSON reader refuses: cut short, nested past its depth limit
    (json itself would recurse into a RecursionError), or over its size limit (sparse)."""
    if kind == "malformed":
        path.write_text('{"format": "endoscopic-chisel/sequence", "num_frames": 2')
    elif kind == "deep":
        path.write_text("[" * 100_000 + "]" * 100_000)
    else:
        with path.open("wb") as f:
            f.truncate(MAX_MANIFEST_BYTES + 1)


PROBLEMS = {"malformed": "invalid JSON", "deep": "nested deeper than", "huge": "at most"}


@pytest.mark.parametrize("kind", sorted(PROBLEMS))
def test_resume_renders_a_seed_again_whose_render_json_is_unreadable(
    tmp_path: Path, tiny_sim_config: SimConfig, caplog: pytest.LogCaptureFixture, kind: str
) -> None:
    header = tmp_path / "seed_1/render.json"
    header.parent.mkdir()
    _write_bad_json(header, kind)
    with caplog.at_level("WARNING", logger="sim.dataset"):
        assert _finished_render(header, tiny_sim_config, bites=1) is None
    (record,) = caplog.records
    assert f"{header}: " in record.getMessage() and PROBLEMS[kind] in record.getMessage()
    # A seed never rendered is not worth a warning.
    caplog.clear()
    assert _finished_render(tmp_path / "seed_2/render.json", tiny_sim_config, 1) is None
    assert not caplog.records


def test_resume_over_an_unreadable_sequence_json_is_one_line_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gen = f"{sys.executable} -m sim.synthetic"  # the toy phantom, generator contract
    out = tmp_path / "ds"
    argv = ["dataset", "--seeds", "1", "--bites", "1", "--out", str(out), "--phantom-cmd", gen]
    assert main([*argv, *SMALL]) == 0
    listing = (out / "dataset.json").read_text()
    capsys.readouterr()
    seq_json = out / "seed_1/step_01/sequence.json"
    for kind, problem in PROBLEMS.items():
        _write_bad_json(seq_json, kind)
        assert main([*argv, *SMALL, "--resume"]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert err.startswith(f"sim dataset: error: {seq_json}: ") and problem in err, err
    assert (out / "dataset.json").read_text() == listing


def test_a_dataset_that_fails_before_its_first_phantom_leaves_no_empty_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "new" / "ds"
    argv = ["dataset", "--seeds", "1", "--bites", "1", "--out", str(out)]
    assert main([*argv, *SMALL, "--phantom-cmd", "/nonexistent/gen"]) == 1
    assert "cannot run the phantom generator" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    # A folder that was there before stays, with what it held.
    out.mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    assert main([*argv, *SMALL, "--phantom-cmd", "/nonexistent/gen"]) == 1
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
