"""Output helpers: atomic folders, deterministic mesh and JSON bytes.

Folders go through :func:`chisel.core.atomic.atomic_dir` (``phantoms`` may import
``chisel.core``): build in a temporary sibling, then swap; an existing folder is replaced
only on success, and a failure leaves it (and no half-written sibling) behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from chisel.core.atomic import atomic_dir as core_atomic_dir
from chisel.core.errors import InvalidInputError
from phantoms.errors import OutputError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_output_dir(path: str | Path) -> Path:
    """Raise :class:`OutputError` unless ``path``'s parent can hold a new folder."""
    path = Path(os.path.abspath(path))
    if path.exists() and not path.is_dir():
        raise OutputError(path, "exists and is not a folder")
    cwd = Path.cwd().resolve()
    try:
        resolved = path.resolve()
    except (OSError, RuntimeError) as exc:  # a link loop: RuntimeError, a traceback
        raise OutputError(path, f"cannot resolve the path: {exc}") from None
    if resolved == cwd or resolved in cwd.parents:
        # The atomic swap replaces the folder whole: `--out .` would delete its contents.
        raise OutputError(path, "holds the current folder; replacing it would delete that")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            path, f"cannot create the parent folder {parent}: {exc.strerror or exc}"
        ) from None
    if not parent.is_dir():
        raise OutputError(path, f"parent {parent} is not a folder")
    # root ignores permission bits, so probe by creating a temporary entry
    try:
        probe = tempfile.mkdtemp(prefix=f".{path.name}.probe-", dir=parent)
        os.rmdir(probe)
    except OSError as exc:
        raise OutputError(
            path, f"parent folder {parent} is not writable: {exc.strerror or exc}"
        ) from None
    return path


@contextlib.contextmanager
def atomic_dir(path: str | Path, marker: str = "phantom.json") -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path``.

    :func:`chisel.core.atomic.atomic_dir` (one-step swap, leftovers of killed runs
    repaired), with its refusals as :class:`OutputError`: an existing non-empty ``path``
    without ``marker`` is not an earlier output, and is refused rather than deleted.
    """
    path = check_output_dir(path)
    with contextlib.ExitStack() as stack:
        try:
            tmp = stack.enter_context(core_atomic_dir(path, marker))
        except InvalidInputError as exc:
            raise OutputError(exc.source, exc.problem) from None
        yield tmp


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary sibling and a rename."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    except OSError as exc:
        raise OutputError(path, f"cannot write: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual mode
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def ply_bytes(vertices_mm: np.ndarray, faces: np.ndarray) -> bytes:
    """Binary little-endian PLY of a triangle mesh.

    vertices_mm : (V, 3) float, written as float64 mm.  faces : (F, 3) int, written as int32.
    """
    v = np.ascontiguousarray(vertices_mm, dtype="<f8")
    f = np.ascontiguousarray(faces, dtype="<i4")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment units mm\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    face_rec = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face_rec["n"] = 3
    face_rec["idx"] = f
    return header + v.tobytes() + face_rec.tobytes()


def npy_bytes(array: np.ndarray) -> bytes:
    """``np.save`` bytes of an array (deterministic; read with ``np.load``, no pickle)."""
    import io

    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def json_bytes(obj: object) -> bytes:
    """Deterministic pretty JSON (keys in insertion order, newline at the end)."""
    return (json.dumps(obj, indent=1) + "\n").encode("utf-8")


def rounded(x, digits: int = 6):
    """Floats (and nested lists/arrays of them) rounded for a stable, readable manifest."""
    if isinstance(x, dict):
        return {k: rounded(v, digits) for k, v in x.items()}
    if isinstance(x, list | tuple | np.ndarray):
        return (
            [rounded(v, digits) for v in np.asarray(x).tolist()]
            if isinstance(x, np.ndarray)
            else [rounded(v, digits) for v in x]
        )
    if isinstance(x, bool | str) or x is None:
        return x
    if isinstance(x, int | np.integer):
        return int(x)
    return round(float(x), digits)
