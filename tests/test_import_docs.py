"""docs/real-data.md's worked example runs as written and gives what the page claims."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "real-data.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", DOC.read_text(), flags=re.S)


def test_worked_example_runs(tmp_path) -> None:
    py = {b.splitlines()[0]: b for b in _blocks("python") if b.startswith("# ")}
    (tmp_path / "make_example.py").write_text(py["# make_example.py"])
    (tmp_path / "check_example.py").write_text(py["# check_example.py"])
    run = {"cwd": tmp_path, "capture_output": True, "text": True, "timeout": 300}
    made = subprocess.run([sys.executable, "make_example.py"], **run)
    assert made.returncode == 0, made.stderr
    (bash,) = [b for b in _blocks("bash") if b.startswith("chisel import video")]
    argv = shlex.split(bash.replace("\\\n", " "))
    assert argv[0] == "chisel"
    imported = subprocess.run([sys.executable, "-m", "chisel", *argv[1:]], **run)
    assert imported.returncode == 0, imported.stderr
    assert "field stop fitted" in imported.stderr
    checked = subprocess.run([sys.executable, "check_example.py"], **run)
    assert checked.returncode == 0, checked.stderr
    assert "max position error" in checked.stdout
