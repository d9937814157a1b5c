"""The ``chisel`` command: one entry point, one subcommand per task.

Each stage module registers its own subcommands through a ``register(subparsers)``
function; ``_COMMANDS`` says which module registers which command, and this file only
wires them. Only the module of the command being run is imported (all of them for
``--help`` or an unknown command): the modules pull in torch, Open3D or Mitsuba, whose
imports cost seconds, and the workflow starts a ``chisel`` process per job.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from chisel.cli.args import check_outputs, input_paths
from chisel.core.errors import run_command

_COMMANDS: dict[str, str] = {
    # command -> "module.path" providing register(subparsers: argparse._SubParsersAction)
    "import": "chisel.cli.cmd_import",
    "depth": "chisel.cli.cmd_depth",
    "evaluate": "chisel.cli.cmd_evaluate",
    "report": "chisel.cli.cmd_evaluate",
    "ct-surface": "chisel.cli.cmd_model",
    "build": "chisel.cli.cmd_model",
    "update": "chisel.cli.cmd_model",
    "mesh": "chisel.cli.cmd_model",
    "render-depth": "chisel.cli.cmd_model",
    "export-ct": "chisel.cli.cmd_ct",
    "external-depth": "chisel.cli.cmd_extern",
}

_DESCRIPTION = """\
Endoscopic Chisel: build a TSDF model from a preoperative CT, detect tissue removed in
new endoscopic sequences, and carve it out of the model.

Units are millimetres; poses are T_world_from_cam (world = CT frame) with OpenCV camera
axes (+x right, +y down, +z forward); depth is z-depth in mm (0 = invalid on disk).
File formats: README.md "On-disk contracts" (sequence folders) and docs/updater.md
(model .npz files).
"""


def _modules_for(argv: list[str] | None) -> list[str]:
    """The command modules to import: the one of the first command named in ``argv``, or
    all (for None, help, a missing or an unknown command)."""
    for token in argv or []:
        if token in _COMMANDS:
            return [_COMMANDS[token]]
        if not token.startswith("-"):
            break
    return list(dict.fromkeys(_COMMANDS.values()))


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser for ``argv`` (default ``sys.argv[1:]``); every command when None."""
    parser = argparse.ArgumentParser(
        prog="chisel",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _modules_for(argv):
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.command is None else 2

    def command() -> int:
        check_outputs(args)  # before anything is read or written
        return args.func(args)

    inputs = [f"{option} {path}" for option, path in input_paths(args)]
    return run_command(f"chisel {args.command}", command, inputs)
