"""Frames in: a video file or an image folder, and which of its frames to import.

:class:`FrameConfig` says how raw frames become the sequence's images (frame range,
undistortion, field stop, depth scale, masks); :class:`VideoSource` and
:class:`ImageFolderSource` yield the source frames, decoding only the selected ones.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from chisel.core.errors import InvalidInputError
from chisel.io.import_common import IMAGE_SUFFIXES, list_files, read_rgb
from chisel.io.undistort import Circle


@dataclass(frozen=True)
class FrameConfig:
    """How to turn raw frames into the sequence's images."""

    undistort: bool = True
    """Remap frames to a pinhole camera with zero distortion (written ``undistorted``)."""
    alpha: float = 0.0
    """OpenCV free scaling of the new camera in [0, 1] (0 = no black corners)."""
    field_stop: Literal["fit", "none"] = "fit"
    """``fit``: fit the circular field stop to the bright region of the frames; ``none``:
    no field-stop mask. Overridden by ``field_stop_circle`` or a camera-mask file."""
    field_stop_circle: Circle | None = None
    """The field stop on the raw image, pixels, when known."""
    mask_margin_px: float = 2.0
    """Shrink the field-stop circle by this much (its rim is vignetted), pixels."""
    start: int = 0
    """First source frame to import."""
    stop: int | None = None
    """Source frame to stop before (None = to the end)."""
    step: int = 1
    """Import every ``step``-th source frame from ``start``."""
    depth_scale_mm: float = 1.0
    """Millimetres per stored depth unit (e.g. 1000 for .npy in metres, 0.1 for a PNG in
    1/10 mm). Depth is then checked to be plausible millimetres."""
    mask_invert: bool = False
    """Per-frame mask PNGs mark pixels to *exclude* (a tool segmentation) when True;
    otherwise 255 marks pixels to use."""
    rescale_intrinsics: bool = False
    """Scale the calibration to frames of the same aspect ratio at another resolution."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.alpha <= 1.0:
            raise InvalidInputError("alpha", f"must be in [0, 1], got {self.alpha}")
        if self.field_stop not in ("fit", "none"):
            raise InvalidInputError("field_stop", f"expected fit or none, got {self.field_stop!r}")
        if self.start < 0 or self.step < 1 or (self.stop is not None and self.stop <= self.start):
            raise InvalidInputError(
                "frame range",
                f"need 0 <= start < stop and step >= 1, got "
                f"start={self.start} stop={self.stop} step={self.step}",
            )
        if not self.depth_scale_mm > 0:
            raise InvalidInputError("depth_scale_mm", f"must be > 0, got {self.depth_scale_mm}")
        if self.mask_margin_px < 0:
            raise InvalidInputError("mask_margin_px", f"must be >= 0, got {self.mask_margin_px}")

    def selected(self, i: int) -> bool:
        """Is source frame ``i`` imported?"""
        return (
            i >= self.start
            and (self.stop is None or i < self.stop)
            and (i - self.start) % self.step == 0
        )


# ------------------------------------------------------------------------ frame sources


class ImageFolderSource:
    """Frames from an image folder, natural order; decoded lazily."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.files = list_files(self.folder, IMAGE_SUFFIXES, "image")
        self.name = str(self.folder)
        self.count: int | None = len(self.files)
        self.fps: float | None = None

    def first(self) -> np.ndarray:
        return read_rgb(self.files[0])

    def frames(self, wanted: FrameConfig) -> Iterator[tuple[int, np.ndarray | None]]:
        """(source index, RGB or None when not selected)."""
        for i, f in enumerate(self.files):
            yield i, (read_rgb(f) if wanted.selected(i) else None)


class VideoSource:
    """Frames from a video file through ``cv2.VideoCapture``; read sequentially."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.name = str(self.path)
        if not self.path.is_file():
            raise InvalidInputError(self.path, "video file not found")
        try:
            self.name.encode("utf-8")
        except UnicodeEncodeError:
            # OpenCV's video back ends open files by name and crash on such a name (exit
            # 139); they cannot read from memory, so the user renames the file.
            raise InvalidInputError(
                repr(self.name), "the video's file name is not valid UTF-8: rename it"
            ) from None
        cap = self._open()
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        cap.release()
        self.fps = fps if np.isfinite(fps) and fps > 0 else None
        self.count = None  # container frame counts are not trustworthy; we count reads

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise InvalidInputError(self.path, "cannot open video (corrupt, or no decoder for it)")
        return cap

    def first(self) -> np.ndarray:
        cap = self._open()
        try:
            ok, img = cap.read()
        finally:
            cap.release()
        if not ok or img is None:
            raise InvalidInputError(self.path, "video has no decodable frame")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def frames(self, wanted: FrameConfig) -> Iterator[tuple[int, np.ndarray | None]]:
        cap = self._open()
        try:
            i = 0
            while True:
                if wanted.selected(i):
                    ok, img = cap.read()
                    if not ok or img is None:
                        return
                    yield i, cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
                else:
                    if not cap.grab():  # skip without decoding
                        return
                    yield i, None
                i += 1
        finally:
            cap.release()


FrameSource = ImageFolderSource | VideoSource
