"""The ``chisel`` command: one entry point, one subcommand per task.

Each stage module registers its own subcommands through a ``register(subparsers)``
function listed in ``_COMMAND_MODULES``; this file only wires them.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from chisel.errors import ChiselError

_COMMAND_MODULES: list[str] = [
    # "module.path" providing register(subparsers: argparse._SubParsersAction) -> None
    "chisel.commands.importers",
    "chisel.commands.depth",
    "chisel.commands.evaluate",
    "chisel.commands.model",
]

_DESCRIPTION = """\
Endoscopic Chisel: build a TSDF model from a preoperative CT, detect tissue removed in
new endoscopic sequences, and carve it out of the model.

Units are millimetres; poses are T_world_from_cam (world = CT frame) with OpenCV camera
axes (+x right, +y down, +z forward); depth is z-depth in mm (0 = invalid on disk).
File formats: README.md "On-disk contracts" (sequence folders) and docs/updater.md
(model .npz files).
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="chisel",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.command is None else 2
    try:
        return int(args.func(args) or 0)
    except ChiselError as exc:
        sys.stderr.write(f"chisel {args.command}: error: {exc}\n")
        return 1
