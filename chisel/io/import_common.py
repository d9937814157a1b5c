"""Readers every importer shares: ``.npy`` without pickle, image/mask/depth files, folders
in natural order, and the mapping of a failed write to :class:`OutputError`.

Sources: :mod:`chisel.io.import_frames` (video, image folders),
:mod:`chisel.io.import_reference` (the reference implementation's layout); poses in
:mod:`chisel.io.import_poses`.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from chisel.core.errors import ChiselError, InvalidInputError, OutputError, ResourceLimitError
from chisel.io.images import decode_image
from chisel.io.limits import check_npy_header
from chisel.io.sequence import check_depth_mm

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def load_npy(path: str | Path) -> np.ndarray:
    """``np.load`` without pickle; a clear error for object arrays or unreadable files.

    The header's shape and dtype are checked first (:func:`chisel.io.limits.check_npy_header`):
    an array larger than the file's data or than :data:`chisel.io.limits.MAX_ARRAY_BYTES`
    is refused before memory is allocated for it.
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "file not found")
    try:
        with open(path, "rb") as fh:
            check_npy_header(fh, path, path.stat().st_size)
        return np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "allow_pickle" in str(exc) or "Object arrays" in str(exc):
            raise InvalidInputError(
                path,
                "this .npy holds Python objects and would need pickle to load, which is "
                "unsafe for files from elsewhere; convert it where it was made, e.g. "
                "np.save(path, np.asarray(arr, dtype=np.float64))",
            ) from None
        raise InvalidInputError(path, f"cannot read .npy: {exc}") from None
    except (OSError, EOFError) as exc:
        raise InvalidInputError(path, f"cannot read .npy (truncated?): {exc}") from None
    except MemoryError:
        raise ResourceLimitError(path, "out of memory reading this .npy") from None


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def list_files(folder: str | Path, suffixes: tuple[str, ...], what: str) -> list[Path]:
    """Files of ``folder`` with one of ``suffixes``, in natural order (2 before 10)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InvalidInputError(folder, f"{what} folder not found")
    files = sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes),
        key=_natural_key,
    )
    if not files:
        raise InvalidInputError(folder, f"no {what} files ({', '.join(suffixes)}) in the folder")
    return files


def read_rgb(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB image; raises :class:`InvalidInputError` if corrupt/truncated."""
    img = decode_image(path, cv2.IMREAD_COLOR, "image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_mask_png(path: str | Path, invert: bool = False, threshold: int = 127) -> np.ndarray:
    """(H, W) bool from a mask image: True where the pixel is > ``threshold`` (or <= it if
    ``invert``)."""
    m = decode_image(path, cv2.IMREAD_GRAYSCALE, "mask image") > threshold
    return ~m if invert else m


def read_depth(path: str | Path, scale_mm: float = 1.0) -> np.ndarray:
    """(H, W) float32 z-depth in mm (NaN invalid) from ``.npy`` or a 16-bit PNG.

    The stored values times ``scale_mm`` must be mm; 0, negative and NaN are invalid.
    Raises :class:`~chisel.core.errors.DepthUnitsError` for depth that reads as metres.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        arr = load_npy(path)
        if arr.dtype.kind not in "fiu":
            raise InvalidInputError(path, f"depth must be numeric, got dtype {arr.dtype}")
    elif suffix == ".png":
        arr = decode_image(path, cv2.IMREAD_UNCHANGED, "depth PNG")
        if arr.dtype != np.uint16 or arr.ndim != 2:
            raise InvalidInputError(
                path, f"depth PNG must be single-channel 16-bit, got {arr.dtype} shape {arr.shape}"
            )
    else:
        raise InvalidInputError(path, f"depth must be .npy or 16-bit .png, got {suffix!r}")
    return check_depth_mm(arr.astype(np.float64) * scale_mm, str(path))


@contextlib.contextmanager
def output_errors(path: Path) -> Iterator[None]:
    """Report a failed write (disk full, unwritable) as :class:`OutputError` on ``path``.

    The writers are atomic, so the earlier output is still in place when this raises."""
    try:
        yield
    except ChiselError:
        raise
    except OSError as exc:
        raise OutputError(path, exc) from exc
