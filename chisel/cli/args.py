"""Command-line outputs that may not overwrite the command's inputs or one another (and
:func:`trainer_options`, the training options both depth networks' configs take).

An argument declared with ``action=Output`` is something the command writes. Before the
command runs, :func:`check_outputs` refuses an output that is an input given on the same
command line, holds one (an atomic folder write would delete it) or lies inside an input
folder (it would change it), and two outputs that are the same path. Inputs are all other
path-like arguments that exist, including the path in ``kind:PATH`` specs such as
``--depth-source sequence:DIR``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from chisel.core.atomic import overlap, resolved
from chisel.core.config import finite_float as finite_float  # re-exported: one home
from chisel.core.errors import InvalidInputError

Sidecar = Callable[[argparse.Namespace], Path | None]


class Output(argparse.Action):
    """``add_argument(..., action=Output)``: store the value and record it as an output.

    ``sidecar`` names a second file the command writes beside this output (a checkpoint's
    ``.json``, an update's default report), as a function of the parsed arguments; it is
    checked like the output itself.
    """

    def __init__(self, *args: Any, sidecar: Sidecar | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.sidecar = sidecar

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        setattr(namespace, self.dest, values)
        namespace.__dict__.setdefault("_outputs", []).append(self.dest)
        if self.sidecar is not None:
            namespace.__dict__.setdefault("_sidecars", {})[self.dest] = self.sidecar


def _option(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def _paths(value: Any) -> Iterator[Path]:
    """The existing paths a parsed argument value names (none for numbers, flags...)."""
    if isinstance(value, list | tuple):
        for v in value:
            yield from _paths(v)
        return
    if not isinstance(value, str | Path) or str(value) == "":
        return
    candidates = [Path(value)]
    kind, sep, rest = str(value).partition(":")
    if sep and rest and kind.isalpha():  # "sequence:DIR", "network:CHECKPOINT", "1=run.json"
        candidates.append(Path(rest))
    if "=" in str(value):
        candidates.append(Path(str(value).split("=", 1)[1]))
    for p in candidates:
        try:
            if p.exists():
                yield p
        except OSError:  # a name too long to be a path, say
            continue


def input_paths(args: argparse.Namespace) -> list[tuple[str, Path]]:
    """(option, path) of every existing path the parsed arguments name that is not an
    output: the command's inputs, for the overlap checks and the out-of-memory message."""
    out_dests = set(getattr(args, "_outputs", []))
    return [
        (_option(dest), inp)
        for dest, value in vars(args).items()
        if dest not in out_dests and not dest.startswith("_") and not callable(value)
        for inp in _paths(value)
    ]


def check_outputs(args: argparse.Namespace) -> None:
    """Raise :class:`InvalidInputError` (naming the option) if an output would overwrite an
    input or another output of the same command line."""
    out_dests = list(dict.fromkeys(getattr(args, "_outputs", [])))
    outputs = [
        (_option(d), Path(getattr(args, d))) for d in out_dests if getattr(args, d) is not None
    ]
    for dest, sidecar in getattr(args, "_sidecars", {}).items():
        extra = sidecar(args)
        if extra is not None:
            outputs.append((f"{_option(dest)} sidecar", Path(extra)))
    for i, (la, a) in enumerate(outputs):
        for lb, b in outputs[i + 1 :]:
            if resolved(a) == resolved(b):
                raise InvalidInputError(
                    lb, f"{b} is also {la}: one output would overwrite the other"
                )
    for option, inp in input_paths(args):
        for label, o in outputs:
            how = overlap(o, inp)
            if how == "replaces":
                raise InvalidInputError(label, f"{o} would overwrite the input {option} {inp}")
            if how == "inside" and inp.is_dir():
                raise InvalidInputError(
                    label,
                    f"{o} lies inside the input folder {option} {inp}: "
                    "write outputs outside the inputs",
                )


def trainer_options(args: argparse.Namespace) -> dict[str, Any]:
    """The ``chisel depth train|finetune`` options that both trainers' configs take
    (``TrainConfig``, ``ChangeTrainConfig``), as their keyword arguments."""
    return {
        "batch_size": args.batch_size,
        "lr": args.lr,
        "seed": args.seed,
        "num_threads": args.threads,
        "device": args.device,
    }
