"""Atomic output: a file or folder appears complete or not at all.

A failed step must leave earlier results intact, so every writer in the package goes
through these helpers: write to a temporary sibling, fsync, then ``os.replace``.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import logging
import os
import re
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from chisel.core.errors import InvalidInputError

log = logging.getLogger(__name__)


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
    # The writer's pid in the name lets the next write of ``path`` remove it if this
    # process is killed before it can (recover_leftovers), as for folders.
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.tmp-{os.getpid()}-", suffix=suffix or path.suffix, dir=path.parent
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
        for signum in dict.fromkeys(caught):
            signal.raise_signal(signum)


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
    for final in finals:
        for stale in recover_leftovers(final):
            log.warning("%s: %s is left from an interrupted run; safe to delete", final, stale)
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


def atomic_savez(path: str | Path, arrays: Mapping[str, Any]) -> Path:
    """Write ``arrays`` as a compressed ``.npz`` at ``path``, atomically; returns ``path``.

    ``np.savez`` gets a file handle: given a bare temporary name it would append ".npz".
    """
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_texts(texts: Mapping[Path, str]) -> None:
    """Write each text to its path, all moved into place together (:func:`atomic_paths`):
    files that belong together (a table's JSON, CSV and Markdown) are all new or, after a
    failure, all as they were."""
    with atomic_paths(*texts) as temps:
        for tmp, text in zip(temps, texts.values(), strict=True):
            tmp.write_text(text, encoding="utf-8")


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def resolved(path: str | Path) -> Path:
    """``path`` with links and ``..`` resolved; a link loop is an :class:`InvalidInputError`
    naming it (``Path.resolve`` raises ``RuntimeError``, a traceback on the command line)."""
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError) as exc:
        raise InvalidInputError(path, f"cannot resolve the path: {exc}") from None


def overlap(out: str | Path, inp: str | Path) -> Literal["replaces", "inside"] | None:
    """How an output path meets an input path: ``"replaces"`` when it is the input or holds
    it (writing it would destroy the input), ``"inside"`` when it lies inside the input,
    else None. Paths are compared resolved (``..`` and links followed)."""
    o, i = resolved(out), resolved(inp)
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


_RENAME_EXCHANGE = 2  # linux/fs.h
_AT_FDCWD = -100


def _renameat2() -> Callable[..., int] | None:
    """libc's ``renameat2`` (Linux, glibc >= 2.28), or None where there is none."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


def exchange_paths(a: Path, b: Path) -> bool:
    """Swap ``a`` and ``b`` in one step (``renameat2(RENAME_EXCHANGE)``); True if done.

    False where the platform or the file system cannot (then nothing has changed): the
    caller falls back to two renames.
    """
    fn = _renameat2()
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def _owner_pid(leftover: Path, kind: str) -> int | None:
    """The writer's pid in ``.NAME.tmp-PID-xxxx`` / ``.NAME.old-PID``, or None."""
    tail = leftover.name.rsplit(f".{kind}-", 1)[-1]
    head = tail.split("-", 1)[0]
    return int(head) if head.isdigit() else None


def _legacy_temp_file(name: str, entry: str) -> bool:
    """Whether ``entry`` is a temporary file an older version wrote for ``name``: the
    ``mkstemp`` name ``.NAME.<8 random characters><suffix>``, without a pid."""
    return re.fullmatch(rf"\.{re.escape(name)}\.[a-z0-9_]{{8}}(\.[A-Za-z0-9]+)?", entry) is not None


def recover_leftovers(path: Path) -> list[Path]:
    """Tidy what killed writers of ``path`` left beside it; returns what remains, named.

    A hidden ``.NAME.old-PID`` folder whose writer is dead holds the earlier output when
    the kill fell between the two renames of the fallback swap: it is moved back to
    ``path`` if ``path`` is missing, else deleted. A ``.NAME.tmp-PID-*`` (the temporary
    folder of :func:`atomic_dir` or file of :func:`atomic_paths`) of a dead writer is
    deleted. Leftovers of live writers (a concurrent run) are left alone: a pid is
    checked on this machine only, so a folder shared between machines must have one
    writer of a path at a time (the workflow's jobs write distinct paths). Ones without a
    pid (an older version's) are returned so the caller can name them.
    """
    unknown: list[Path] = []
    parent = path.parent
    if not parent.is_dir():
        return unknown
    olds: list[Path] = []
    for entry in parent.iterdir():
        if _legacy_temp_file(path.name, entry.name) and entry.is_file():
            unknown.append(entry)
        for kind in ("old", "tmp"):
            if not entry.name.startswith(f".{path.name}.{kind}-"):
                continue
            is_file = entry.is_file() and not entry.is_symlink()
            if not (entry.is_dir() or (kind == "tmp" and is_file)):
                continue
            pid = _owner_pid(entry, kind)
            if pid is None:
                unknown.append(entry)
            elif pid != os.getpid() and not _pid_alive(pid):
                if kind == "old":
                    olds.append(entry)
                elif is_file:
                    entry.unlink(missing_ok=True)
                else:
                    shutil.rmtree(entry, ignore_errors=True)
    for old in sorted(olds, key=lambda p: p.stat().st_mtime, reverse=True):
        if not path.exists():
            os.replace(old, path)
            log.warning("%s: restored the earlier output from %s (a killed run)", path, old.name)
        else:
            shutil.rmtree(old, ignore_errors=True)
    return unknown


@contextlib.contextmanager
def atomic_dir(path: str | Path, marker: str) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path``.

    An existing ``path`` is kept until the new folder is complete, then swapped with it in
    one step (``renameat2(RENAME_EXCHANGE)`` on Linux; elsewhere two renames, and a kill
    between them is repaired by the next run, :func:`recover_leftovers`) and deleted. On
    an exception the temporary folder is removed and ``path`` is untouched.
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
    for stale in recover_leftovers(path):
        log.warning("%s: %s is left from an interrupted run; safe to delete", path, stale)
    if path.is_dir() and not (path / marker).exists() and any(path.iterdir()):
        raise InvalidInputError(
            path,
            f"is a folder with other content (no {marker}, so not an earlier output); "
            "refusing to replace it: choose a new or empty folder",
        )
    check_writable_parent(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-{os.getpid()}-", dir=path.parent))
    # mkdtemp creates 0700; give the final folder the permissions a plain mkdir() would.
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
        with deferred_signals():
            if path.exists() and exchange_paths(tmp, path):
                pass  # tmp now holds the earlier output; the finally block deletes it
            else:
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
