"""Exceptions raised at the public entry points of the updater.

Every error names the file (or argument) and the problem, with expected vs actual, so a
user with real data can fix the input. All derive from :class:`ChiselError`; the input
errors also derive from ``ValueError`` so generic callers can catch them.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path


class ChiselError(Exception):
    """Base class of every error this package raises on purpose."""


class InvalidInputError(ChiselError, ValueError):
    """An input file or argument is malformed. ``source`` names the file or argument."""

    def __init__(self, source: str | Path, problem: str) -> None:
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


class ConfigError(InvalidInputError):
    """A configuration value (YAML key, CLI option, dataclass field) is invalid."""


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


class OutsideManifestError(InvalidInputError):
    """A manifest names a file outside its own folder (after resolving links), and the
    user did not allow that explicitly."""


class ResourceLimitError(InvalidInputError):
    """A size declared by a file (array shape, image dimensions, count) is past a limit
    that protects memory; refused before anything is allocated."""


class TrainingDivergedError(ChiselError, RuntimeError):
    """Training produced a non-finite loss or weights; the last finite checkpoint is kept."""


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


OUT_OF_MEMORY_HINT = "image size, frame count or voxel size too large?"


@contextlib.contextmanager
def out_of_memory_names(source: str | Path, doing: str) -> Iterator[None]:
    """Turn a ``MemoryError`` inside the block into a :class:`ResourceLimitError` naming
    ``source``: past this point nothing could tell the user which input was too large.

    ``doing`` completes "out of memory ...", e.g. "reading this model file".
    """
    try:
        yield
    except MemoryError:
        raise ResourceLimitError(source, f"out of memory {doing} ({OUT_OF_MEMORY_HINT})") from None


def run_command(
    prog: str, command: Callable[[], int | None], inputs: Iterable[str | Path] = ()
) -> int:
    """Run a CLI command; what the user can act on becomes one line on stderr, no traceback.

    The project's own errors and OS errors (missing file, disk full) exit 1, an exhausted
    memory exits 1 naming ``inputs`` (the command's input files: the ``MemoryError`` came
    from outside every reader's :func:`out_of_memory_names`), Ctrl-C exits 130. SIGTERM is
    turned into ``SystemExit`` (exit 143) so that ``finally`` blocks run and atomic
    writers remove their temporary folders instead of leaving them beside the output.
    """

    def _terminate(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    try:
        return int(command() or 0)
    except ChiselError as exc:
        sys.stderr.write(f"{prog}: error: {exc}\n")
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        sys.stderr.write(f"{prog}: error: {where}{exc.strerror or exc}\n")
    except MemoryError:
        named = ", ".join(str(p) for p in inputs)
        where = f" processing {named}" if named else ""
        sys.stderr.write(f"{prog}: error: out of memory{where} ({OUT_OF_MEMORY_HINT})\n")
    except KeyboardInterrupt:
        sys.stderr.write(f"{prog}: interrupted; earlier outputs are unchanged\n")
        return 130
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    return 1
