"""Decoding image files from elsewhere: path-safe, complete, within size limits.

``cv2.imread`` takes a ``str`` and hands it to C++: a file name with a byte that is not
UTF-8 (a surrogate-escaped ``str`` from ``os.listdir``) crashed the process (exit 139).
Here Python opens the file and OpenCV only decodes bytes (``cv2.imdecode``). OpenCV also
decodes a truncated JPEG with a grey fill and no error, so the end markers are checked
first, and the header's declared size is checked against limits before decoding.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from chisel.core.errors import InvalidInputError, ResourceLimitError
from chisel.io.limits import check_image_size

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def check_complete(path: Path, data: bytes) -> None:
    """Refuse a JPEG/PNG whose end marker is missing (by content, whatever the suffix):
    OpenCV decodes a truncated JPEG silently (grey fill), so the decoder alone does not
    catch it."""
    tail = data[-64:].rstrip(b"\x00")
    if data[:2] == b"\xff\xd8" and not tail.endswith(b"\xff\xd9"):
        raise InvalidInputError(path, "truncated JPEG (no end-of-image marker)")
    if data[:8] == PNG_MAGIC and b"IEND" not in tail[-12:]:
        raise InvalidInputError(path, "truncated PNG (no IEND chunk)")


def read_image_bytes(path: str | Path, what: str = "image") -> bytes:
    """The bytes of an image file, after the size and completeness checks."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, f"{what} file not found")
    check_image_size(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InvalidInputError(path, f"cannot read {what}: {exc.strerror or exc}") from None
    except MemoryError:
        raise ResourceLimitError(path, f"out of memory reading this {what}") from None
    check_complete(path, data)
    return data


def decode_image(path: str | Path, flags: int, what: str = "image") -> np.ndarray:
    """Decode ``path`` with ``cv2.imdecode(flags)`` (BGR order as OpenCV gives it).

    Raises :class:`InvalidInputError` naming the file if it is missing, truncated, over
    the size limits (:class:`~chisel.core.errors.ResourceLimitError`) or not decodable.
    """
    data = read_image_bytes(path, what)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if img is None:
        raise InvalidInputError(path, f"cannot decode {what} (corrupt, truncated or not an image)")
    return img
