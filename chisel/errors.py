"""Exceptions raised at the public entry points of the updater.

Every error names the file (or argument) and the problem, with expected vs actual, so a
user with real data can fix the input. All derive from :class:`ChiselError`; the input
errors also derive from ``ValueError`` so generic callers can catch them.
"""

from __future__ import annotations

from pathlib import Path


class ChiselError(Exception):
    """Base class of every error this package raises on purpose."""


class InvalidInputError(ChiselError, ValueError):
    """An input file or argument is malformed. ``source`` names the file or argument."""

    def __init__(self, source: str | Path, problem: str) -> None:
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


class PoseError(InvalidInputError):
    """A pose is not a finite rigid 4x4 transform, or pose and frame counts differ."""


class DepthUnitsError(InvalidInputError):
    """Depth looks like it is in metres (or another unit) where millimetres are expected."""


class CameraError(InvalidInputError):
    """Intrinsics do not match the images, or are not a valid pinhole model."""


class FormatVersionError(InvalidInputError):
    """A file was written by an incompatible version of an on-disk contract."""


class VariantError(InvalidInputError):
    """No usable Mitsuba variant, or an explicitly requested variant does not work."""


class EmptyResultError(ChiselError, RuntimeError):
    """There is nothing to return (empty surface, no valid pixel, no registered frame)."""


class OutputError(ChiselError, OSError):
    """An output could not be written (disk full, unwritable folder); earlier files are kept.

    Also an ``OSError`` with the original ``errno`` (e.g. ``ENOSPC``), so callers that
    handle OS errors keep working.
    """

    def __init__(self, path: str | Path, exc: OSError) -> None:
        self.source = str(path)
        self.problem = f"cannot write output: {exc.strerror or exc}"
        OSError.__init__(self, exc.errno, f"{self.source}: {self.problem}")

    def __str__(self) -> str:  # "file: problem" like every other ChiselError, no "[Errno n]"
        return f"{self.source}: {self.problem}"
