"""The ``chisel`` entry point: its command table, and that a command imports only its module."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys

import pytest

from chisel.cli import _COMMANDS, build_parser, main


def test_command_table_matches_what_the_modules_register() -> None:
    for module in set(_COMMANDS.values()):
        parser = argparse.ArgumentParser()
        sub = parser.add_subparsers(dest="command")
        importlib.import_module(module).register(sub)
        registered = set(sub.choices)
        assert registered == {c for c, m in _COMMANDS.items() if m == module}, module
    args = build_parser(["mesh"]).parse_args(["mesh", "--model", "m", "--out", "o"])
    assert args.command == "mesh" and callable(args.func)


def test_a_command_imports_only_its_own_module() -> None:
    """``chisel mesh`` must not pay for torch or Open3D (the workflow runs one per job)."""
    code = (
        "import sys\n"
        "from chisel.cli import build_parser\n"
        "build_parser(['-v', 'mesh', '--model', 'm.npz'])\n"
        "print(sorted(m for m in ('torch', 'open3d', 'mitsuba') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 0
    text = capsys.readouterr().out
    for command in _COMMANDS:
        assert command in text, command
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
