"""Atomic folder writes refuse outputs that would destroy inputs or the working folder."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from chisel.atomic import atomic_dir, atomic_write_text, check_output_outside
from chisel.errors import InvalidInputError


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
