"""Atomic folder writes refuse outputs that would destroy inputs or the working folder."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest

import chisel.core.atomic as atomic
from chisel.core.atomic import atomic_dir, atomic_paths, atomic_write_text, check_output_outside
from chisel.core.errors import InvalidInputError


def test_output_may_not_replace_hold_or_sit_inside_an_input(tmp_path: Path) -> None:
    inp = tmp_path / "phantom"
    (inp / "meshes").mkdir(parents=True)
    check_output_outside(tmp_path / "render", inp)  # a sibling is fine
    with pytest.raises(InvalidInputError, match="would replace the input"):
        check_output_outside(inp, inp)
    with pytest.raises(InvalidInputError, match="would replace the input"):
        check_output_outside(tmp_path, inp)  # holds the input
    with pytest.raises(InvalidInputError, match="inside the input"):
        check_output_outside(inp / "meshes", inp)
    with pytest.raises(InvalidInputError, match="would replace the input"):
        check_output_outside(
            tmp_path / "phantom" / ".." / "phantom", inp
        )  # same, spelled otherwise


def test_atomic_dir_refuses_a_file_and_the_working_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = tmp_path / "afile"
    f.write_text("keep me")
    with pytest.raises(InvalidInputError, match="not a folder"):
        with atomic_dir(f, "x"):
            pass
    assert f.read_text() == "keep me"
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.txt").write_text("mine")
    monkeypatch.chdir(work)
    for out in (".", str(tmp_path)):
        with pytest.raises(InvalidInputError, match="holds the current folder"):
            with atomic_dir(out, "x"):
                pass
    assert (work / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "work"]  # nothing left over


def test_atomic_dir_gives_the_usual_permissions(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        with atomic_dir(tmp_path / "out", "x") as tmp:
            (tmp / "x").write_text("1")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o755


def test_atomic_dir_replaces_only_its_own_kind_of_folder(tmp_path: Path) -> None:
    out = tmp_path / "seq"
    out.mkdir()
    (out / "thesis.tex").write_text("months of work")
    with pytest.raises(InvalidInputError, match="no sequence.json"):
        with atomic_dir(out, "sequence.json"):
            pass
    assert (out / "thesis.tex").read_text() == "months of work"
    (out / "thesis.tex").unlink()
    with atomic_dir(out, "sequence.json") as tmp:  # empty: fine
        (tmp / "sequence.json").write_text("1")
    with atomic_dir(out, "sequence.json") as tmp:  # an earlier output: replaced
        (tmp / "sequence.json").write_text("2")
    assert (out / "sequence.json").read_text() == "2"


def test_a_file_write_to_a_folder_or_an_empty_name_is_refused(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match="is a folder"):
        atomic_write_text(tmp_path, "x")
    with pytest.raises(InvalidInputError, match="not a file name"):
        atomic_write_text("", "x")
    assert list(tmp_path.iterdir()) == []


def test_atomic_paths_move_together_and_hold_ctrl_c_until_done(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    a, b = tmp_path / "report.json", tmp_path / "model.npz"
    a.write_text("old report")
    b.write_text("old model")
    # An error while staging: both stay as they were, no temporary file is left.
    with pytest.raises(RuntimeError):
        with atomic_paths(a, b) as (ta, tb):
            ta.write_text("new report")
            raise RuntimeError("fusion failed")
    assert (a.read_text(), b.read_text()) == ("old report", "old model")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.npz", "report.json"]
    # Ctrl-C between the two moves is delivered after both, never between them.
    real_replace, moved = os.replace, []

    def replace_then_interrupt(src: object, dst: object) -> None:
        real_replace(src, dst)  # type: ignore[arg-type]
        moved.append(Path(str(dst)).name)
        if len(moved) == 1:
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(os, "replace", replace_then_interrupt)
    # Python's own Ctrl-C handler, whatever the test runner's worker installed.
    runner_handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with atomic_paths(a, b) as (ta, tb):
                ta.write_text("new report")
                tb.write_text("new model")
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, runner_handler)
    assert moved == ["report.json", "model.npz"]
    assert (a.read_text(), b.read_text()) == ("new report", "new model")


def _dead_pid() -> int:
    proc = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        check=True,
        capture_output=True,
        text=True,
    )
    return int(proc.stdout)


def test_atomic_dir_swaps_in_one_step_where_the_platform_can(tmp_path: Path, monkeypatch) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    if not atomic.exchange_paths(a, b):
        pytest.skip("renameat2(RENAME_EXCHANGE) is not available here")
    out = tmp_path / "out"
    with atomic_dir(out, "m") as tmp:
        (tmp / "m").write_text("old")

    def no_replace(*args: object) -> None:
        raise AssertionError("a two-rename swap")

    monkeypatch.setattr(atomic.os, "replace", no_replace)
    with atomic_dir(out, "m") as tmp:
        (tmp / "m").write_text("new")
    assert (out / "m").read_text() == "new"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")] == []


def test_a_kill_between_the_two_renames_is_repaired_by_the_next_run(tmp_path: Path) -> None:
    """Without RENAME_EXCHANGE the swap is two renames; SIGKILL between them left the
    earlier output only under a hidden name. The next run of the same writer restores it
    (even when that run fails) and removes the dead run's temporary folder."""
    out = tmp_path / "out"
    with atomic_dir(out, "m") as tmp:
        (tmp / "m").write_text("earlier")
    code = (
        "import os, signal, sys\n"
        "import chisel.core.atomic as atomic\n"
        "atomic.exchange_paths = lambda a, b: False\n"
        "real = os.replace\n"
        "def replace(src, dst):\n"
        "    real(src, dst)\n"
        "    if '.old-' in str(dst): os.kill(os.getpid(), signal.SIGKILL)\n"
        "atomic.os.replace = replace\n"
        "with atomic.atomic_dir(sys.argv[1], 'm') as tmp:\n"
        "    (tmp / 'm').write_text('new')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(out)], timeout=120)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()  # the kill fell between the renames
    hidden = sorted(p.name.split("-")[0] for p in tmp_path.iterdir() if p.name != "out")
    assert hidden == [".out.old", ".out.tmp"]
    stale_unknown = tmp_path / ".out.tmp-abcdef"  # an older version's name: no pid
    stale_unknown.mkdir()
    live = tmp_path / f".out.tmp-{os.getppid()}-xyz"  # a concurrent, live writer
    live.mkdir()
    with pytest.raises(RuntimeError, match="fails"), atomic_dir(out, "m"):
        raise RuntimeError("this run fails")
    assert (out / "m").read_text() == "earlier"
    left = sorted(p.name for p in tmp_path.iterdir() if p.name != "out")
    assert left == sorted([stale_unknown.name, live.name])


def test_stale_leftovers_of_dead_writers_are_removed(tmp_path: Path, caplog) -> None:
    out = tmp_path / "out"
    with atomic_dir(out, "m") as tmp:
        (tmp / "m").write_text("current")
    dead = _dead_pid()
    (tmp_path / f".out.old-{dead}").mkdir()
    (tmp_path / f".out.tmp-{dead}-q1").mkdir()
    (tmp_path / ".out.tmp-legacy").mkdir()
    with caplog.at_level("WARNING"), atomic_dir(out, "m") as tmp:
        (tmp / "m").write_text("next")
    assert (out / "m").read_text() == "next"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.tmp-legacy", "out"]
    assert ".out.tmp-legacy is left from an interrupted run; safe to delete" in caplog.text
