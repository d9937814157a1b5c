"""Atomic output: a file or folder appears complete or not at all.

A failed step must leave earlier results intact, so every writer in the package goes
through these helpers: write to a temporary sibling, fsync, then ``os.replace``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Literal

from chisel.core.errors import InvalidInputError


def check_writable_parent(path: Path) -> None:
    """Raise :class:`InvalidInputError` if ``path``'s folder cannot be created or written."""
    parent = Path(path).absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InvalidInputError(
            path, f"cannot create output folder {parent}: {exc.strerror}"
        ) from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InvalidInputError(path, f"output folder {parent} is not writable")


def _temp_beside(path: Path, suffix: str) -> Path:
    """A new empty temporary file beside ``path`` (same folder, so a rename is atomic)."""
    if path.name in ("", ".", ".."):
        raise InvalidInputError(path, "not a file name")
    if path.is_dir():
        raise InvalidInputError(path, "is a folder; expected the path of a file to write")
    check_writable_parent(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent
    )
    os.close(fd)
    # mkstemp creates 0600; give the final file the permissions a plain open() would.
    os.chmod(tmp, 0o666 & ~_umask())
    return Path(tmp)


def _fsync(path: Path) -> None:
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary file path beside ``path``; on success move it over ``path``.

    On an exception the temporary file is removed and ``path`` is left as it was.
    """
    with atomic_paths(path, suffixes=(suffix,)) as (tmp,):
        yield tmp


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM until the block is done, then deliver them.

    Python runs signal handlers in the main thread between bytecodes, so a handler swap
    is what holds them (blocking the signal in one thread would not: another thread may
    take it). Elsewhere than in the main thread this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    # A handler installed outside Python reads as None and could not be put back: leave it.
    held = [sig for sig in (signal.SIGINT, signal.SIGTERM) if signal.getsignal(sig) is not None]
    previous = {
        sig: signal.signal(sig, lambda signum, _frame: caught.append(signum)) for sig in held
    }
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(caught):
            signal.raise_signal(sig)


@contextlib.contextmanager
def atomic_paths(*paths: str | Path, suffixes: Sequence[str] = ()) -> Iterator[list[Path]]:
    """Yield a temporary path beside each of ``paths``; on success move them all into place.

    The moves happen together at the end, with Ctrl-C and SIGTERM held
    (:func:`deferred_signals`): the outputs are then all new or, after an exception or
    an interrupt before the moves, all as they were. Only a SIGKILL or a power cut
    between two renames can leave a mix. ``suffixes`` (default: each path's own) give
    the temporary names' endings, for writers that look at them (``np.savez``).
    """
    finals = [Path(p) for p in paths]
    ends = (list(suffixes) + [""] * len(finals))[: len(finals)]
    temps: list[Path] = []
    try:
        for final, end in zip(finals, ends, strict=True):
            temps.append(_temp_beside(final, end))
        yield temps
        for tmp in temps:
            _fsync(tmp)
        with deferred_signals():
            for tmp, final in zip(temps, finals, strict=True):
                os.replace(tmp, final)
    finally:
        for tmp in temps:
            if tmp.exists():
                tmp.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def overlap(out: str | Path, inp: str | Path) -> Literal["replaces", "inside"] | None:
    """How an output path meets an input path: ``"replaces"`` when it is the input or holds
    it (writing it would destroy the input), ``"inside"`` when it lies inside the input,
    else None. Paths are compared resolved (``..`` and links followed)."""
    o, i = Path(out).resolve(), Path(inp).resolve()
    if o == i or o in i.parents:
        return "replaces"
    if i in o.parents:
        return "inside"
    return None


def check_output_outside(out: str | Path, *inputs: str | Path) -> None:
    """Raise :class:`InvalidInputError` if the output folder ``out`` overlaps an input.

    An atomic folder write replaces ``out`` whole: an ``out`` equal to an input folder or
    holding one would delete that input, and an ``out`` inside one would change it.
    """
    for inp in inputs:
        how = overlap(out, inp)
        if how == "replaces":
            raise InvalidInputError(
                out, f"the output folder would replace the input {inp}; choose another output"
            )
        if how == "inside":
            raise InvalidInputError(
                out, f"the output folder lies inside the input {inp}; choose one outside it"
            )


@contextlib.contextmanager
def atomic_dir(path: str | Path, marker: str) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path``.

    An existing ``path`` is kept until the new folder is complete, then swapped out and
    deleted. On an exception the temporary folder is removed and ``path`` is untouched.
    ``marker`` is the file every folder of this kind holds (``sequence.json``, ...): an
    existing non-empty ``path`` without it is not an earlier output of ours, and is
    refused rather than deleted. Refused as well (:class:`InvalidInputError`): a ``path``
    that is an existing file, and one that holds the current working folder.
    """
    path = Path(os.path.abspath(path))
    if path.exists() and not path.is_dir():
        raise InvalidInputError(path, "exists and is not a folder; refusing to replace it")
    if overlap(path, Path.cwd()) == "replaces":
        raise InvalidInputError(
            path, "the output folder holds the current folder; replacing it would delete that"
        )
    if path.is_dir() and not (path / marker).exists() and any(path.iterdir()):
        raise InvalidInputError(
            path,
            f"is a folder with other content (no {marker}, so not an earlier output); "
            "refusing to replace it: choose a new or empty folder",
        )
    check_writable_parent(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    # mkdtemp creates 0700; give the final folder the permissions a plain mkdir() would.
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
        old = None
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            if old.exists():
                shutil.rmtree(old)
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
