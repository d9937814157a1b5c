"""Sizes a file declares, checked against limits before memory is allocated for them.

A ``.npy`` header, a compressed ``.npz`` member or a PNG header can declare an array of
terabytes in a few bytes; the readers look at the declaration first and refuse it with a
:class:`~chisel.core.errors.ResourceLimitError` naming the file, instead of dying of
``MemoryError`` (or the kernel's OOM killer) somewhere later.
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from pathlib import Path
from typing import IO

import numpy as np

from chisel.core.errors import InvalidInputError, ResourceLimitError, out_of_memory_names

MAX_ARRAY_BYTES = 8 * 2**30
"""Largest array read from one ``.npy`` / ``.npz`` member (a 512^3 float32 TSDF is 0.5 GiB)."""

MAX_IMAGE_PIXELS = 8192 * 8192
"""Largest image (width x height) decoded; endoscope frames are at most 4K."""

MAX_IMAGE_SIDE_PX = 16384
"""Largest image width or height decoded."""

MAX_TEXT_BYTES = 256 * 2**20
"""Largest text file (pose file, CSV) read whole."""

MIN_VOXEL_SIZE_MM = 1e-3
"""Smallest voxel edge of a grid (model or CT), mm (1 um; CT and endoscopic depth resolve
~0.1 mm)."""
MAX_VOXEL_SIZE_MM = 1e3
"""Largest voxel edge of a grid, mm."""
MAX_PLACEMENT_MM = 1e6
"""Farthest a grid corner may lie from the world origin, mm (1 km: any scanner frame)."""


def _declared_nbytes(fh: IO[bytes], source: str | Path) -> tuple[int, tuple[int, ...], np.dtype]:
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        else:
            shape, _fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError/SyntaxError/... on junk
        raise InvalidInputError(source, f"not a .npy array (bad header: {exc})") from None
    if dtype.hasobject:
        # np.load itself refuses these with allow_pickle=False; say why before it does.
        raise InvalidInputError(
            source,
            "this .npy holds Python objects and would need pickle to load, which is unsafe "
            "for files from elsewhere; convert it where it was made, e.g. "
            "np.save(path, np.asarray(arr, dtype=np.float64))",
        )
    count = 1
    for n in shape:
        count *= int(n)
    return count * dtype.itemsize, tuple(int(n) for n in shape), dtype


def check_npy_header(fh: IO[bytes], source: str | Path, file_bytes: int | None) -> None:
    """Read a ``.npy`` header from ``fh`` and refuse an array past the limits.

    ``file_bytes`` (the whole file's size, or None for a compressed member) bounds the data
    an uncompressed file can hold: a header declaring more is truncated or hostile.
    """
    nbytes, shape, dtype = _declared_nbytes(fh, source)
    if nbytes > MAX_ARRAY_BYTES:
        raise ResourceLimitError(
            source,
            f"array of shape {shape} {dtype} needs {nbytes} bytes, over the limit of "
            f"{MAX_ARRAY_BYTES} bytes",
        )
    if file_bytes is not None and nbytes > file_bytes - fh.tell():
        raise InvalidInputError(
            source,
            f"array of shape {shape} {dtype} needs {nbytes} bytes but the file holds "
            f"{file_bytes - fh.tell()} (truncated?)",
        )


def check_npz_members(path: str | Path) -> None:
    """Check every member of an ``.npz`` archive (or a bare ``.npy``): its declared array
    within the limits.

    Refuses (naming the file and member) a zip that does not open, a member whose
    header is past :data:`MAX_ARRAY_BYTES`, and an archive whose total uncompressed size is.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        if fh.read(6) == b"\x93NUMPY":  # a bare .npy: its one header
            fh.seek(0)
            check_npy_header(fh, path, path.stat().st_size)
            return
    if not zipfile.is_zipfile(path):
        return  # not an archive at all: np.load says so
    try:
        with zipfile.ZipFile(path) as zf:
            total = sum(info.file_size for info in zf.infolist())
            if total > 2 * MAX_ARRAY_BYTES:
                raise ResourceLimitError(
                    path,
                    f"archive unpacks to {total} bytes, over the limit of {2 * MAX_ARRAY_BYTES}",
                )
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with zf.open(info) as fh:
                    check_npy_header(fh, f"{path} member {info.filename}", None)
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        EOFError,
        OSError,
        NotImplementedError,
    ) as exc:
        raise InvalidInputError(path, f"not a readable .npz archive: {exc}") from None


def read_npz(path: str | Path, what: str) -> dict[str, np.ndarray]:
    """Every member of the untrusted ``.npz`` at ``path`` (a ``what``: "model", "panels").

    Declared sizes and object arrays are refused from the headers first
    (:func:`check_npz_members`), then it is read without pickle; a bare ``.npy``, an archive
    that does not open or a member that does not decompress is one
    :class:`InvalidInputError` naming the file, running out of memory a
    :class:`ResourceLimitError` naming it."""
    path = Path(path)
    check_npz_members(path)
    with out_of_memory_names(path, f"reading this {what} file"):
        try:
            loaded = np.load(path, allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):
                raise InvalidInputError(
                    path, f"not a {what} file: a single .npy array, not an .npz archive"
                )
            with loaded as z:
                return {k: np.asarray(z[k]) for k in z.files}
        except InvalidInputError:  # a ValueError, but it names the file already
            raise
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise InvalidInputError(
                path, f"cannot read {what} (.npz without pickle): {exc}"
            ) from None


def png_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, or None if ``path`` is not a PNG."""
    with open(path, "rb") as fh:
        head = fh.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


def jpeg_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) from a JPEG's first start-of-frame marker, or None if not found."""
    with open(path, "rb") as fh:
        data = fh.read(256 * 1024)
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            i += 1
            continue
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
            i += 1 if marker == 0xFF else 2
            continue
        length = struct.unpack(">H", data[i + 2 : i + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return width, height
        i += 2 + length
    return None


def check_image_size(path: str | Path) -> None:
    """Refuse a PNG or JPEG whose header declares more than :data:`MAX_IMAGE_PIXELS`
    (or a side over :data:`MAX_IMAGE_SIDE_PX`), before a decoder allocates it."""
    size = png_size(path) or jpeg_size(path)
    if size is None:
        return
    width, height = size
    if width > MAX_IMAGE_SIDE_PX or height > MAX_IMAGE_SIDE_PX or width * height > MAX_IMAGE_PIXELS:
        raise ResourceLimitError(
            path,
            f"image declares {width}x{height} pixels, over the limit of {MAX_IMAGE_SIDE_PX} px a "
            f"side and {MAX_IMAGE_PIXELS} pixels",
        )


def read_text_limited(
    path: str | Path, what: str, error: type[InvalidInputError] = InvalidInputError
) -> str:
    """The UTF-8 text of ``path`` (at most :data:`MAX_TEXT_BYTES`); one ``error`` otherwise."""
    path = Path(path)
    if not path.is_file():
        raise error(path, f"{what} not found")
    size = path.stat().st_size
    if size > MAX_TEXT_BYTES:
        raise ResourceLimitError(
            path, f"{what} is {size} bytes, over the limit of {MAX_TEXT_BYTES}"
        )
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(path, f"cannot parse {what}: not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise error(path, f"cannot read {what}: {exc.strerror or exc}") from None
