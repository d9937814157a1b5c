"""CLI: ``chisel external-depth`` (a researcher's own depth estimator on one sequence).

Thin wrapper around :func:`chisel.depth.external.external_depth`: the result is a depth
sequence folder for ``chisel update --depth-source sequence:DIR``, written atomically.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from chisel.cli.args import Output
from chisel.core.config import finite_float
from chisel.core.errors import InvalidInputError

_DESCRIPTION = """\
Run your own depth estimator on a sequence and write its depth as a new sequence folder
(the input's RGB, masks and poses; the estimator's depth) for
`chisel update --depth-source sequence:OUT`. Exactly one of:

  --torchscript FILE  an exported TorchScript module: (B, H, W, 3) uint8 RGB in,
                      (B, H, W) float32 depth out (chisel depth export writes one)
  --command LINE      a command line with {input} and {output}: {input} is the sequence
                      folder (sequence.json, poses.txt, rgb/NNNNNN.png, mask/NNNNNN.png),
                      {output} an empty folder where it writes NNNNNN.npy per frame,
                      (H, W) float32 z-depth, NaN or <= 0 = invalid. Split like a shell
                      line and run without a shell; {input} and {output} must each be a
                      whole argument. For pipes, pass the folders as a shell's arguments:
                      bash -c 'python est.py "$1" "$2"' _ {input} {output}

--metric: the depth is millimetres; without it the depth is up to scale (the updater
solves the scale per frame) and is written rescaled to a median of 10.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "external-depth",
        help="your own depth estimator (TorchScript or a command) -> a depth sequence",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--sequence", required=True, type=Path, help="input sequence folder")
    p.add_argument(
        "--out", required=True, type=Path, action=Output, help="new depth sequence folder"
    )
    kind = p.add_mutually_exclusive_group(required=True)
    kind.add_argument("--torchscript", type=Path, help="exported TorchScript depth model")
    # dest: "command" is the subcommand's name (chisel external-depth: error: ...)
    kind.add_argument(
        "--command",
        dest="estimator_command",
        metavar="LINE",
        help="command line with {input} and {output}",
    )
    p.add_argument("--metric", action="store_true", help="the depth is in millimetres")
    p.add_argument(
        "--timeout-s", type=finite_float, default=3600.0, help="stop a command after this long (s)"
    )
    p.set_defaults(func=_cmd_external_depth)


def _cmd_external_depth(args: argparse.Namespace) -> int:
    from chisel.depth.external import external_depth
    from chisel.io.sequence import Sequence

    if not args.timeout_s > 0:
        raise InvalidInputError("--timeout-s", f"must be > 0, got {args.timeout_s}")
    seq = Sequence(args.sequence)
    external_depth(
        seq,
        args.out,
        torchscript=args.torchscript,
        command=args.estimator_command,
        metric=args.metric,
        timeout_s=args.timeout_s,
    )
    sys.stdout.write(json.dumps({"sequence": str(args.out), "frames": len(seq)}) + "\n")
    return 0
