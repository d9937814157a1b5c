"""Real data in: endoscope video or frames + tracked poses + calibration -> a sequence.

Everything a real dataset needs to become a sequence folder (``chisel.io.sequence``):

- frames from a video file (``cv2.VideoCapture``) or an image folder;
- poses from a text file (N x 16 row-major 4x4, N blocks of 4 lines, or TUM
  ``timestamp tx ty tz qx qy qz qw``) or a ``.npy`` (N, 4, 4), matched to frames by index
  or by timestamp (nearest within a tolerance, or SLERP between the two samples around
  the frame time), translations in m or mm, composed with a fixed hand-eye transform
  and a tracker-to-world registration::

      T_world_from_cam[i] = T_world_from_tracker @ P[i] @ T_marker_from_cam

  where ``P[i]`` is the i-th pose of the file (the tracked marker in tracker
  coordinates; with no hand-eye transform the file's poses are the camera's own);
- intrinsics and distortion from an OpenCV / ROS / JSON calibration
  (``chisel.io.calibration``); frames undistorted to a new pinhole camera and masked to
  the endoscope's circular field stop (``chisel.io.undistort``), as the reference
  implementation's data are;
- optional per-frame depth (``.npy`` float mm or 16-bit PNG times a scale) and
  per-frame validity masks (PNG; tools, blood);
- the reference implementation's dataset layout (``input.json`` with ``preop_data`` and
  numbered steps), see :func:`import_reference`.

Output goes through :class:`chisel.io.sequence.SequenceWriter`, so a failed import leaves
no partial folder and keeps an earlier one. ``.npy`` files are never unpickled.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from chisel.core.atomic import atomic_dir
from chisel.core.errors import (
    CameraError,
    ChiselError,
    InvalidInputError,
    OutputError,
    PoseError,
    ResourceLimitError,
)
from chisel.core.geometry import Camera, check_rigid
from chisel.io.calibration import Calibration, read_calibration
from chisel.io.images import decode_image
from chisel.io.limits import check_npy_header, read_text_limited
from chisel.io.manifest import check_inside, named_path, read_json_manifest
from chisel.io.meshfile import read_mesh_file
from chisel.io.sequence import Frame, SequenceWriter, check_depth_mm
from chisel.io.undistort import (
    Circle,
    Undistortion,
    check_lens_model,
    circle_mask,
    fit_field_stop,
    make_undistortion,
)

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

METRE_LIKE_MAX_TRANSLATION_MM = 1.0
"""With units "mm", a trajectory whose every position lies within this distance of the
tracker origin is taken to be in metres (trackers sit ~0.1-2 m from the patient)."""

MM_LIKE_MIN_TRANSLATION_M = 10.0
"""With units "m", a position farther than this from the tracker origin means mm."""

QUATERNION_NORM_TOL = 1e-2
"""Quaternions whose norm differs from 1 by more than this are refused, not normalised."""

FIELD_STOP_FIT_FRAMES = 30
"""How many (evenly spread, selected) frames the field-stop fit looks at."""


# ----------------------------------------------------------------------------- configs


@dataclass(frozen=True)
class PoseConfig:
    """How to read a pose file and match it to the frames."""

    format: Literal["auto", "matrix", "tum"] = "auto"
    """``matrix``: N x 16 row-major or N blocks of 4 rows; ``tum``: ``t tx ty tz qx qy qz
    qw``; ``auto``: by the number of columns (16 or 4 -> matrix, 8 -> tum). ``.npy``
    files are always (N, 4, 4) or (N, 16) matrices."""
    units: Literal["mm", "m"] = "mm"
    """Units of the translations in the pose file and the fixed transforms; converted to mm."""
    match: Literal["index", "timestamp"] = "index"
    """``index``: frame i takes pose i and the counts must be equal; ``timestamp``: each
    frame's time is looked up in the pose file's timestamps (TUM format only)."""
    interpolation: Literal["nearest", "slerp"] = "nearest"
    """Timestamp matching: the nearest pose sample within ``time_tolerance_s``, or SLERP
    (rotation) + linear (translation) between the samples just before and just after the
    frame time, each within ``time_tolerance_s`` of it."""
    time_tolerance_s: float = 0.02
    """Largest time between a frame and the pose sample(s) used for it, seconds."""
    fps: float | None = None
    """Frame rate for frame times (t_i = frame_time_offset_s + i / fps) when no frame-time
    CSV is given; None = the video's own rate."""
    frame_time_offset_s: float = 0.0
    """Time of frame 0 on the pose file's clock, seconds (with ``fps``)."""
    T_marker_from_cam: np.ndarray | None = None
    """(4, 4) hand-eye transform: the camera in the tracked marker's frame (pose-file units)."""
    T_world_from_tracker: np.ndarray | None = None
    """(4, 4) registration: the tracker frame in the world (CT) frame (pose-file units)."""
    drop_unposed: bool = False
    """Drop frames without a valid pose (NaN = tracking lost, or no sample in time)
    instead of refusing the input; the dropped source indices go into the meta."""
    check_units: bool = True
    """Refuse translations that look like the other unit (see the module constants)."""

    def __post_init__(self) -> None:
        if self.format not in ("auto", "matrix", "tum"):
            raise InvalidInputError(
                "pose format", f"expected auto, matrix or tum, got {self.format!r}"
            )
        if self.units not in ("mm", "m"):
            raise InvalidInputError("pose units", f"expected 'mm' or 'm', got {self.units!r}")
        if self.match not in ("index", "timestamp"):
            raise InvalidInputError("match", f"expected index or timestamp, got {self.match!r}")
        if self.interpolation not in ("nearest", "slerp"):
            raise InvalidInputError(
                "interpolation", f"expected nearest or slerp, got {self.interpolation!r}"
            )
        if not self.time_tolerance_s > 0:
            raise InvalidInputError("time_tolerance_s", f"must be > 0, got {self.time_tolerance_s}")
        if self.fps is not None and not self.fps > 0:
            raise InvalidInputError("fps", f"must be > 0, got {self.fps}")
        for name in ("T_marker_from_cam", "T_world_from_tracker"):
            T = getattr(self, name)
            if T is not None:
                object.__setattr__(self, name, check_rigid(T, name).copy())


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


@dataclass(frozen=True)
class ImportReport:
    """What an import wrote."""

    path: Path
    """The sequence folder."""
    num_frames: int
    """Frames written."""
    num_source_frames: int
    """Frames in the video / folder."""
    dropped: list[tuple[int, str]]
    """(source frame index, reason) of selected frames left out for want of a pose."""
    camera: Camera
    """The sequence's camera (pinhole when undistorted)."""
    raw_camera: Camera
    """The calibrated camera of the raw frames."""
    field_stop: Circle | None
    """The field stop on the raw image, if any."""
    undistorted: bool
    """Whether the written frames are undistorted (zero distortion)."""


# ------------------------------------------------------------------------- small readers


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


def read_transform(path: str | Path, source: str) -> np.ndarray:
    """A single (4, 4) transform from a ``.npy`` or a text file of 16 numbers."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        arr = load_npy(path).astype(np.float64)
    else:
        if not path.is_file():
            raise InvalidInputError(path, f"{source} file not found")
        try:
            arr = np.array(re.split(r"[,\s]+", path.read_text().strip()), dtype=np.float64)
        except ValueError as exc:
            raise PoseError(path, f"cannot parse {source}: {exc}") from None
    if arr.size != 16:
        raise PoseError(path, f"{source} must be a 4x4 matrix (16 numbers), got {arr.size}")
    return check_rigid(arr.reshape(4, 4), f"{path} ({source})")


# -------------------------------------------------------------------------------- poses


@dataclass(frozen=True)
class PoseTrack:
    """Poses as read from a file: units of the file, NaN rows where tracking was lost."""

    poses: np.ndarray
    """(N, 4, 4) float64; a pose with any NaN/inf is 'no pose' for that sample."""
    timestamps_s: np.ndarray | None
    """(N,) float64 seconds (TUM files), else None."""
    source: str
    """The file (for messages)."""

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: finite samples."""
        return np.isfinite(self.poses.reshape(len(self.poses), -1)).all(axis=1)


def _read_numeric_rows(path: Path) -> tuple[np.ndarray, list[int]]:
    """Rows of numbers (comma or space separated, '#' comments, one header line allowed)."""
    rows: list[list[float]] = []
    linenos: list[int] = []
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [p for p in re.split(r"[,\s]+", line) if p]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            if not rows and not linenos:  # a header line such as "timestamp tx ty ..."
                linenos.append(-lineno)
                continue
            raise PoseError(f"{path}:{lineno}", f"not a row of numbers: {raw.strip()!r}") from None
        if rows and len(vals) != len(rows[0]):
            raise PoseError(
                f"{path}:{lineno}",
                f"expected {len(rows[0])} numbers like the first row, got {len(vals)}",
            )
        rows.append(vals)
        linenos.append(lineno)
    if not rows:
        raise PoseError(path, "pose file has no rows of numbers")
    return np.asarray(rows, dtype=np.float64), [n for n in linenos if n > 0]


def _tum_to_matrices(rows: np.ndarray, path: Path, linenos: list[int]) -> np.ndarray:
    t, q = rows[:, 1:4], rows[:, 4:8]  # qx qy qz qw (scalar last, as TUM and scipy)
    poses = np.full((len(rows), 4, 4), np.nan)
    finite = np.isfinite(rows[:, 1:]).all(axis=1)
    norms = np.linalg.norm(q, axis=1)
    bad = finite & (np.abs(norms - 1.0) > QUATERNION_NORM_TOL)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise PoseError(
            f"{path}:{linenos[i]}",
            f"quaternion norm is {norms[i]:.4f}, expected 1 (is the column order "
            f"'timestamp tx ty tz qx qy qz qw'?)",
        )
    if finite.any():
        R = Rotation.from_quat(q[finite] / norms[finite, None]).as_matrix()
        poses[finite, :3, :3] = R
        poses[finite, :3, 3] = t[finite]
        poses[finite, 3] = [0.0, 0.0, 0.0, 1.0]
    return poses


def read_pose_file(path: str | Path, fmt: Literal["auto", "matrix", "tum"] = "auto") -> PoseTrack:
    """Read a pose file (see :class:`PoseConfig`.format). Units are the file's own."""
    path = Path(path)
    if not path.is_file():
        raise PoseError(path, "pose file not found")
    if path.suffix.lower() == ".npy":
        arr = load_npy(path).astype(np.float64)
        if arr.ndim == 2 and arr.shape[1] == 16:
            arr = arr.reshape(-1, 4, 4)
        if arr.ndim != 3 or arr.shape[1:] != (4, 4) or len(arr) == 0:
            raise PoseError(path, f"expected (N, 4, 4) or (N, 16) poses, got shape {arr.shape}")
        return PoseTrack(arr, None, str(path))
    rows, linenos = _read_numeric_rows(path)
    ncol = rows.shape[1]
    kind = fmt
    if fmt == "auto":
        kind = {16: "matrix", 4: "matrix", 8: "tum"}.get(ncol, "unknown")  # type: ignore[assignment]
    if kind == "tum":
        if ncol != 8:
            raise PoseError(
                path, f"TUM format needs 8 columns (t tx ty tz qx qy qz qw), got {ncol}"
            )
        return PoseTrack(_tum_to_matrices(rows, path, linenos), rows[:, 0].copy(), str(path))
    if kind == "matrix" and ncol == 16:
        return PoseTrack(rows.reshape(-1, 4, 4), None, str(path))
    if kind == "matrix" and ncol == 4:
        if len(rows) % 4:
            raise PoseError(
                path, f"4-column matrix file needs a multiple of 4 rows, got {len(rows)}"
            )
        return PoseTrack(rows.reshape(-1, 4, 4), None, str(path))
    raise PoseError(
        path,
        f"cannot tell the pose format from {ncol} columns: expected 16 (row-major 4x4), "
        f"4 (blocks of 4 rows) or 8 (TUM: t tx ty tz qx qy qz qw)",
    )


def poses_world_from_cam(track: PoseTrack, cfg: PoseConfig) -> np.ndarray:
    """(N, 4, 4) float64 ``T_world_from_cam`` in mm; NaN rows where tracking was lost.

    Converts units, checks each finite pose is rigid, checks the units look right, and
    applies ``T_world_from_tracker @ P @ T_marker_from_cam``.
    """
    scale = 1000.0 if cfg.units == "m" else 1.0
    valid = track.valid
    if not valid.any():
        raise PoseError(track.source, f"all {len(track.poses)} poses are NaN/inf")
    P = track.poses.copy()
    P[:, :3, 3] *= scale
    check_rigid(P[valid], track.source)
    if cfg.check_units:
        t_max = float(np.linalg.norm(track.poses[valid, :3, 3], axis=1).max())
        if cfg.units == "mm" and t_max < METRE_LIKE_MAX_TRANSLATION_MM and valid.sum() > 1:
            raise PoseError(
                track.source,
                f"every camera position is within {t_max:.4g} of the tracker origin: "
                f"translations look like metres, but units are mm (pass --pose-units m, "
                f"or check_units=False if this is right)",
            )
        if cfg.units == "m" and t_max > MM_LIKE_MIN_TRANSLATION_M:
            raise PoseError(
                track.source,
                f"a camera position is {t_max:.4g} m from the tracker origin: translations "
                f"look like millimetres, but units are m (pass --pose-units mm)",
            )
    H = np.eye(4) if cfg.T_marker_from_cam is None else cfg.T_marker_from_cam.copy()
    W = np.eye(4) if cfg.T_world_from_tracker is None else cfg.T_world_from_tracker.copy()
    H[:3, 3] *= scale
    W[:3, 3] *= scale
    out = np.full_like(P, np.nan)
    out[valid] = W @ P[valid] @ H
    return out


def match_poses_by_time(
    pose_times_s: np.ndarray,
    poses: np.ndarray,
    frame_times_s: np.ndarray,
    tolerance_s: float,
    method: Literal["nearest", "slerp"] = "nearest",
    source: str = "poses",
) -> np.ndarray:
    """Poses at frame times.

    pose_times_s : (N,) float64 s, increasing. poses : (N, 4, 4) float64, NaN = no sample.
    frame_times_s : (M,) float64 s. Returns (M, 4, 4) float64, NaN where no pose qualifies:
    ``nearest`` takes the nearest valid sample within ``tolerance_s``; ``slerp``
    interpolates between the valid samples just before and just after (both within
    ``tolerance_s``; a sample at exactly the frame time is used as is).
    """
    pose_times_s = np.asarray(pose_times_s, np.float64)
    frame_times_s = np.atleast_1d(np.asarray(frame_times_s, np.float64))
    valid = np.isfinite(poses.reshape(len(poses), -1)).all(axis=1) & np.isfinite(pose_times_s)
    t, P = pose_times_s[valid], poses[valid]
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise PoseError(source, f"timestamps must increase: {t[i]!r} is followed by {t[i + 1]!r}")
    out = np.full((len(frame_times_s), 4, 4), np.nan)
    if len(t) == 0:
        return out
    k = np.searchsorted(t, frame_times_s)  # t[k-1] < f <= t[k]
    before = np.clip(k - 1, 0, len(t) - 1)
    after = np.clip(k, 0, len(t) - 1)
    d_before = np.where(k > 0, frame_times_s - t[before], np.inf)
    d_after = np.where(k < len(t), t[after] - frame_times_s, np.inf)
    if method == "nearest":
        nearest = np.where(d_before <= d_after, before, after)
        ok = np.minimum(d_before, d_after) <= tolerance_s
        out[ok] = P[nearest[ok]]
        return out
    exact = d_after == 0.0
    out[exact] = P[after[exact]]
    between = ~exact & (d_before <= tolerance_s) & (d_after <= tolerance_s)
    if between.any():
        i0, i1 = before[between], after[between]
        w = (frame_times_s[between] - t[i0]) / (t[i1] - t[i0])
        R = np.empty((int(between.sum()), 3, 3))
        for j, (a, b, wj) in enumerate(zip(i0, i1, w, strict=True)):
            slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([P[a, :3, :3], P[b, :3, :3]])))
            R[j] = slerp(wj).as_matrix()
        T = np.tile(np.eye(4), (len(w), 1, 1))
        T[:, :3, :3] = R
        T[:, :3, 3] = (1.0 - w)[:, None] * P[i0, :3, 3] + w[:, None] * P[i1, :3, 3]
        out[between] = T
    return out


def read_frame_times(path: str | Path) -> np.ndarray:
    """(N,) float64 frame times in seconds: the last column of each row of a CSV/text file
    (so ``t`` and ``index,t`` both work; one header line is skipped)."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "frame-time file not found")
    rows, _ = _read_numeric_rows(path)
    times = rows[:, -1].copy()
    if not np.all(np.isfinite(times)):
        raise InvalidInputError(path, "frame times contain NaN/inf")
    if len(times) > 1 and np.any(np.diff(times) <= 0):
        raise InvalidInputError(path, "frame times must increase")
    return times


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


# ----------------------------------------------------------------------------- import


@contextlib.contextmanager
def _output_errors(path: Path) -> Iterator[None]:
    """Report a failed write (disk full, unwritable) as :class:`OutputError` on ``path``.

    The writers are atomic, so the earlier output is still in place when this raises."""
    try:
        yield
    except ChiselError:
        raise
    except OSError as exc:
        raise OutputError(path, exc) from exc


def _camera_mask_raw(
    source: FrameSource, raw: Camera, cfg: FrameConfig, camera_mask_path: Path | None
) -> tuple[np.ndarray | None, Circle | None]:
    """The field-stop mask on the raw grid and the circle it came from (if any)."""
    if camera_mask_path is not None:
        m = read_mask_png(camera_mask_path)
        raw.check_image(m, str(camera_mask_path))
        return m, None
    circle = cfg.field_stop_circle
    if circle is None and cfg.field_stop == "fit":
        picked: list[np.ndarray] = []
        stride = (
            1
            if source.count is None
            else max(1, source.count // (FIELD_STOP_FIT_FRAMES * cfg.step))
        )
        for n, (_i, rgb) in enumerate(source.frames(cfg)):
            if rgb is not None and n % stride == 0:
                picked.append(rgb)
            if len(picked) >= FIELD_STOP_FIT_FRAMES:
                break
        circle = fit_field_stop(picked)
        if circle is None:
            log.info("no dark border around the frames: no field-stop mask")
            return None, None
        log.info(
            "field stop fitted: centre (%.1f, %.1f) px, radius %.1f px",
            circle.cx,
            circle.cy,
            circle.r,
        )
    if circle is None:
        return None, None
    if cfg.mask_margin_px >= circle.r:
        raise InvalidInputError(
            "mask_margin_px",
            f"{cfg.mask_margin_px:g} px is not less than the field stop's radius "
            f"{circle.r:.1f} px: the camera mask would keep no pixel",
        )
    return circle_mask(raw.shape, circle, cfg.mask_margin_px), circle


def import_frames(
    source: FrameSource,
    poses_path: str | Path,
    calibration: str | Path | Calibration,
    out_path: str | Path,
    pose_cfg: PoseConfig | None = None,
    frame_cfg: FrameConfig | None = None,
    *,
    frame_times_path: str | Path | None = None,
    depth_dir: str | Path | None = None,
    mask_dir: str | Path | None = None,
    camera_mask_path: str | Path | None = None,
    meta: dict[str, Any] | None = None,
    progress: bool = False,
) -> ImportReport:
    """Import frames + poses + calibration into a sequence folder at ``out_path``.

    Per-frame depth files (``depth_dir``) and mask PNGs (``mask_dir``) are taken in natural
    order, one per source frame, on the raw image grid. Raises a
    :class:`~chisel.core.errors.InvalidInputError` subclass naming the file on any bad input;
    ``out_path`` is then left as it was.
    """
    pose_cfg = pose_cfg or PoseConfig()
    frame_cfg = frame_cfg or FrameConfig()
    out_path = Path(out_path)
    calib = calibration if isinstance(calibration, Calibration) else read_calibration(calibration)
    track = read_pose_file(poses_path, pose_cfg.format)
    poses = poses_world_from_cam(track, pose_cfg)

    first = source.first()
    raw = calib.camera_for(first.shape[1], first.shape[0], rescale=frame_cfg.rescale_intrinsics)

    # Pose lookup per source frame index.
    frame_times: np.ndarray | None = None
    fps: float | None = None
    if pose_cfg.match == "timestamp":
        if track.timestamps_s is None:
            raise PoseError(
                track.source,
                "timestamp matching needs a TUM pose file (with timestamps); use match=index",
            )
        if frame_times_path is not None:
            frame_times = read_frame_times(frame_times_path)
        else:
            fps = pose_cfg.fps or source.fps
            if fps is None:
                raise InvalidInputError(
                    source.name,
                    "timestamp matching needs frame times: give a frame-time CSV or fps",
                )

    def pose_for(i: int) -> tuple[np.ndarray | None, str]:
        if pose_cfg.match == "index":
            if i >= len(poses):
                raise PoseError(
                    source.name,
                    f"has more frames than {track.source} has poses ({len(poses)}); "
                    f"index matching needs one pose per frame",
                )
            T = poses[i]
            if np.isfinite(T).all():
                return T, ""
            # NaN is how trackers mark a lost pose; inf is a broken file, named as such
            # (read from the file's row: the world transform turned both into NaN).
            lost = np.isnan(track.poses[i]).any()
            return None, "pose is NaN (tracking lost)" if lost else "pose is inf"
        if frame_times is not None:
            if i >= len(frame_times):
                raise InvalidInputError(
                    frame_times_path,
                    f"has {len(frame_times)} frame times but {source.name} has more frames",
                )
            t = frame_times[i]
        else:
            assert fps is not None
            t = pose_cfg.frame_time_offset_s + i / fps
        T = match_poses_by_time(
            track.timestamps_s,
            poses,
            np.array([t]),
            pose_cfg.time_tolerance_s,
            pose_cfg.interpolation,
            track.source,
        )[0]
        if np.isfinite(T).all():
            return T, ""
        return None, f"no valid pose within {pose_cfg.time_tolerance_s} s of t = {t:.6f} s"

    depth_files = None if depth_dir is None else list_files(depth_dir, (".npy", ".png"), "depth")
    mask_files = None if mask_dir is None else list_files(mask_dir, IMAGE_SUFFIXES, "mask")
    if source.count is not None:
        for files, what in ((depth_files, depth_dir), (mask_files, mask_dir)):
            if files is not None and len(files) != source.count:
                raise InvalidInputError(
                    what, f"has {len(files)} files but {source.name} has {source.count} frames"
                )

    mask_raw, circle = _camera_mask_raw(
        source, raw, frame_cfg, None if camera_mask_path is None else Path(camera_mask_path)
    )
    check_lens_model(raw, mask_raw, calib.source)
    und: Undistortion | None = None
    camera = raw
    camera_mask = mask_raw
    if frame_cfg.undistort and raw.has_distortion:
        und = make_undistortion(raw, frame_cfg.alpha)
        camera = und.camera
        camera_mask = und.valid.copy() if mask_raw is None else und.mask(mask_raw)
    if camera_mask is not None:
        if not camera_mask.any():
            raise InvalidInputError(camera_mask_path or "field stop", "camera mask keeps no pixel")
        if camera_mask.all():
            camera_mask = None

    header_meta: dict[str, Any] = {
        "source": source.name,
        "poses_file": str(poses_path),
        "calibration": calib.source,
        "raw_camera": raw.to_dict(),
        "pose_units_in_file": pose_cfg.units,
        "pose_match": pose_cfg.match,
        "pose_interpolation": pose_cfg.interpolation if pose_cfg.match == "timestamp" else None,
        "field_stop_raw_px": None if circle is None else [circle.cx, circle.cy, circle.r],
        **(meta or {}),
    }
    dropped: list[tuple[int, str]] = []
    kept: list[int] = []
    n_source = 0
    frames_iter = source.frames(frame_cfg)
    if progress:
        from tqdm import tqdm

        frames_iter = tqdm(frames_iter, total=source.count, desc="import", unit="frame")
    with (
        _output_errors(out_path),
        SequenceWriter(
            out_path, camera, header_meta, camera_mask, bool(und) or not raw.has_distortion
        ) as w,
    ):
        for i, rgb in frames_iter:
            n_source = i + 1
            if pose_cfg.match == "index" and i >= len(poses):
                pose_for(i)  # raises: more frames than poses
            if rgb is None:
                continue
            raw.check_image(rgb, f"{source.name} frame {i}")
            T, why = pose_for(i)
            if T is None:
                if not pose_cfg.drop_unposed:
                    raise PoseError(
                        track.source,
                        f"frame {i} of {source.name}: {why} (use drop_unposed / "
                        f"--drop-unposed to leave such frames out)",
                    )
                dropped.append((i, why))
                continue
            depth = mask = None
            if depth_files is not None:
                if i >= len(depth_files):
                    raise InvalidInputError(
                        depth_dir, f"has {len(depth_files)} files, fewer than the frames"
                    )
                depth = read_depth(depth_files[i], frame_cfg.depth_scale_mm)
                raw.check_image(depth, str(depth_files[i]))
            if mask_files is not None:
                if i >= len(mask_files):
                    raise InvalidInputError(
                        mask_dir, f"has {len(mask_files)} files, fewer than the frames"
                    )
                mask = read_mask_png(mask_files[i], frame_cfg.mask_invert)
                raw.check_image(mask, str(mask_files[i]))
            if und is not None:
                rgb = und.image(rgb)
                depth = None if depth is None else und.depth(depth)
                mask = None if mask is None else und.mask(mask)
            w.add(Frame(index=len(kept), T_world_from_cam=T, rgb=rgb, depth_mm=depth, mask=mask))
            kept.append(i)
        if pose_cfg.match == "index" and n_source != len(poses):
            raise PoseError(
                source.name,
                f"has {n_source} frames but {track.source} has {len(poses)} poses "
                f"(a truncated video, or the wrong pose file?)",
            )
        if frame_times is not None and n_source != len(frame_times):
            raise InvalidInputError(
                frame_times_path,
                f"has {len(frame_times)} frame times but {source.name} has {n_source} frames",
            )
        for files, what in ((depth_files, depth_dir), (mask_files, mask_dir)):
            if files is not None and len(files) != n_source:
                raise InvalidInputError(
                    what, f"has {len(files)} files but {source.name} has {n_source} frames"
                )
        if not kept:
            raise PoseError(track.source, f"no selected frame of {source.name} has a valid pose")
        w.meta["source_frame_index"] = kept
        w.meta["dropped_frames"] = [[i, why] for i, why in dropped]
    if dropped:
        log.warning(
            "%d frame(s) dropped for want of a pose: %s", len(dropped), [i for i, _ in dropped][:20]
        )
    return ImportReport(
        out_path,
        len(kept),
        n_source,
        dropped,
        camera,
        raw,
        circle,
        bool(und) or not raw.has_distortion,
    )


def import_video(
    video: str | Path,
    poses_path: str | Path,
    calibration: str | Path,
    out_path: str | Path,
    **kwargs: Any,
) -> ImportReport:
    """:func:`import_frames` from a video file."""
    return import_frames(VideoSource(video), poses_path, calibration, out_path, **kwargs)


def import_images(
    folder: str | Path,
    poses_path: str | Path,
    calibration: str | Path,
    out_path: str | Path,
    **kwargs: Any,
) -> ImportReport:
    """:func:`import_frames` from an image folder (natural file-name order)."""
    return import_frames(ImageFolderSource(folder), poses_path, calibration, out_path, **kwargs)


# -------------------------------------------------------------- reference implementation

REFERENCE_MANIFEST = "reference.json"
REFERENCE_FORMAT = "endoscopic-chisel/reference-import"


@dataclass(frozen=True)
class ReferencePart:
    """One imported part of a reference dataset (preop or a surgical step)."""

    name: str
    """``preop`` or ``step_<i>``."""
    sequence: Path
    """The sequence folder written for it."""
    num_frames: int
    """Frames in it."""
    surface: Path | None
    """The copied segmentation mesh (``seg``), if the part names one."""
    has_depth: bool
    """Whether the estimated depths were imported."""


@dataclass(frozen=True)
class ReferenceImport:
    """Result of :func:`import_reference`."""

    path: Path
    parts: list[ReferencePart] = field(default_factory=list)


def _reference_intrinsics(value: object, source: str) -> np.ndarray:
    try:
        vals = [float(v) for v in (value.split(",") if isinstance(value, str) else value)]  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise CameraError(source, f"intrinsics must be 'fx,fy,cx,cy', got {value!r}") from None
    if len(vals) != 4:
        raise CameraError(source, f"intrinsics must be 4 numbers 'fx,fy,cx,cy', got {len(vals)}")
    fx, fy, cx, cy = vals
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _reference_poses(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".npy":
        arr = load_npy(path)
        if arr.dtype.kind not in "fiu":
            raise PoseError(path, f"poses must be numbers, got dtype {arr.dtype}")
        arr = arr.astype(np.float64)
    else:  # the older layout's trajectories.csv: 16 numbers per pose, any line breaks
        text = read_text_limited(path, "pose file", PoseError).strip()
        try:
            arr = np.array([v for v in re.split(r"[,\s]+", text) if v], dtype=np.float64)
        except ValueError as exc:
            raise PoseError(path, f"cannot parse poses: {exc}") from None
    if arr.size == 0 or arr.size % 16:
        raise PoseError(
            path, f"expected N 4x4 poses (a multiple of 16 numbers), got shape {arr.shape}"
        )
    return arr.reshape(-1, 4, 4)


def _reference_int(part: dict, key: str, default: int | None, manifest: Path, name: str) -> int:
    value = part.get(key, default)
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise InvalidInputError(
            manifest, f"{name}.{key}: expected an integer >= 0, got {value!r}"[:300]
        )
    return value


def _import_reference_part(
    part: object,
    name: str,
    manifest: Path,
    K: np.ndarray,
    out: Path,
    with_depth: bool,
    depth_scale_mm: float,
    pose_units: str,
    allow_outside: bool,
) -> ReferencePart:
    source = str(manifest)
    if not isinstance(part, dict) or "base_dir" not in part:
        raise InvalidInputError(source, f"{name}: expected an object with 'base_dir'")

    def inside(
        value: object, key: str, kind: Literal["file", "folder"], base: Path | None = None
    ) -> Path:
        return named_path(
            manifest, value, f"{name}.{key}", allow_outside=allow_outside, kind=kind, base=base
        )

    base = inside(part["base_dir"], "base_dir", "folder")
    img_dir = inside(part.get("img_dir", "images"), "img_dir", "folder", base)
    # The reference pairs sorted(*.jpg) with the poses in order; keep its plain sort.
    images = sorted(img_dir.glob("*.jpg"))
    if not images:
        images = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise InvalidInputError(img_dir, f"{name}: no images (*.jpg) in the folder")
    # A link inside an accepted folder may still point anywhere.
    images = [
        check_inside(manifest, p, f"{name} image", allow_outside=allow_outside) for p in images
    ]
    poses_path = inside(part.get("poses", "trajectories.npy"), "poses", "file", base)
    if poses_path.suffix.lower() not in (".npy", ".csv", ".txt"):
        raise PoseError(
            poses_path, "poses must be a .npy (N, 4, 4) or a .csv/.txt of 16 numbers per pose"
        )
    P = _reference_poses(poses_path)
    if "start_idx" in part:  # older layout: poses for every tracker sample, subsampled here
        first_idx = _reference_int(part, "start_idx", 0, manifest, name)
        last_idx = _reference_int(part, "end_idx", None, manifest, name)
        interval = _reference_int(part, "interval", 1, manifest, name)
        if interval < 1:
            raise InvalidInputError(manifest, f"{name}.interval: must be >= 1, got {interval}")
        P = P[first_idx : last_idx + 1 : interval]
    track = PoseTrack(P, None, str(poses_path))
    poses = poses_world_from_cam(track, PoseConfig(units=pose_units))  # type: ignore[arg-type]
    if not np.isfinite(poses).all():
        bad = np.flatnonzero(~np.isfinite(poses.reshape(len(poses), -1)).all(axis=1))
        raise PoseError(poses_path, f"NaN/inf in pose(s) {bad[:10].tolist()}")
    if len(poses) != len(images):
        raise PoseError(poses_path, f"{len(poses)} poses but {len(images)} images in {img_dir}")
    mask_path = inside("undistorted_mask.bmp", "undistorted_mask.bmp", "file", base)
    camera_mask = read_mask_png(mask_path, threshold=0)  # the reference binarises with mask > 0
    first = read_rgb(images[0])
    camera = Calibration(K, np.zeros(5), None, source).camera_for(first.shape[1], first.shape[0])
    camera.check_image(camera_mask, str(mask_path))
    depth_files: list[Path] | None = None
    if with_depth and (base / "depths").is_dir():
        depth_dir = inside("depths", "depths", "folder", base)
        depth_files = [
            check_inside(manifest, p, f"{name} depth", allow_outside=allow_outside)
            for p in sorted(depth_dir.glob("*.npy"))
        ]
        if len(depth_files) != len(images):
            raise InvalidInputError(
                depth_dir, f"{len(depth_files)} depth maps for {len(images)} images"
            )
    surface = None
    if "seg" in part:
        seg = inside(part["seg"], "seg", "file", base)
        # Parsed as a mesh and written anew: a manifest cannot make us copy other bytes.
        mesh = read_mesh_file(seg, f"{name}.seg mesh")
        surface = out / f"{name}_surface{seg.suffix.lower()}"
        mesh.export(surface)
    meta = {
        "source": "reference layout (Mangulabnan et al., github.com/janemilym/ct-update)",
        "part": name,
        "base_dir": str(base),
        "poses_file": str(poses_path),
        "pose_units_in_file": pose_units,
        "surface": None if surface is None else surface.name,
        "depth_source": None
        if depth_files is None
        else f"monocular estimate (depths/*.npy) x {depth_scale_mm} mm per unit",
        "source_images": [p.name for p in images],
    }
    seq = out / name
    with SequenceWriter(seq, camera, meta, None if camera_mask.all() else camera_mask, True) as w:
        for i, img_path in enumerate(images):
            rgb = first if i == 0 else read_rgb(img_path)
            camera.check_image(rgb, str(img_path))
            depth = None
            if depth_files is not None:
                depth = read_depth(depth_files[i], depth_scale_mm)
                camera.check_image(depth, str(depth_files[i]))
            w.add(Frame(index=i, T_world_from_cam=poses[i], rgb=rgb, depth_mm=depth))
    return ReferencePart(
        name,
        Path(name),
        len(images),
        None if surface is None else Path(surface.name),
        depth_files is not None,
    )


def import_reference(
    input_json: str | Path,
    out_dir: str | Path,
    *,
    with_depth: bool = False,
    depth_scale_mm: float = 1.0,
    pose_units: Literal["mm", "m"] = "mm",
    allow_outside_manifest: bool = False,
) -> ReferenceImport:
    """Import a dataset laid out for the reference implementation (``input.json``).

    Writes ``out_dir/preop/``, ``out_dir/step_<i>/`` (sequence folders, already
    undistorted, camera mask from ``undistorted_mask.bmp``), ``<part>_surface.<ext>``
    copies of the ``seg`` meshes, and ``reference.json`` listing them. All or nothing:
    ``out_dir`` appears only when every part imported. See docs/real-data.md.

    Every path ``input.json`` names (``base_dir``, ``img_dir``, ``poses``, ``seg``, and
    each file found in those folders) must resolve inside ``input.json``'s folder unless
    ``allow_outside_manifest`` (:class:`~chisel.core.errors.OutsideManifestError`); each
    file is parsed as its kind (mesh, poses, image) before anything is written.
    """
    input_json = Path(input_json).absolute()
    source = str(input_json)
    if not input_json.is_file():
        raise InvalidInputError(input_json, "input.json not found")
    args = read_json_manifest(input_json)
    for key in ("intrinsics", "preop_data"):
        if key not in args:
            raise InvalidInputError(input_json, f"missing key {key!r}")
    K = _reference_intrinsics(args["intrinsics"], source)
    steps = args.get("steps", 0)
    if not isinstance(steps, int) or isinstance(steps, bool) or not 0 <= steps <= len(args):
        raise InvalidInputError(
            input_json,
            f"steps must be an integer from 0 to the number of entries, got {steps!r}"[:300],
        )
    parts = [("preop", args["preop_data"])]
    for i in range(1, steps + 1):
        if str(i) not in args:
            raise InvalidInputError(input_json, f"steps = {steps} but there is no {str(i)!r} entry")
        parts.append((f"step_{i}", args[str(i)]))
    done: list[ReferencePart] = []
    with _output_errors(Path(out_dir)), atomic_dir(out_dir, REFERENCE_MANIFEST) as tmp:
        for name, part in parts:
            done.append(
                _import_reference_part(
                    part,
                    name,
                    input_json,
                    K,
                    tmp,
                    with_depth,
                    depth_scale_mm,
                    pose_units,
                    allow_outside_manifest,
                )
            )
        manifest = {
            "format": REFERENCE_FORMAT,
            "version": 1,
            "source": str(input_json.absolute()),
            "intrinsics_fx_fy_cx_cy": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
            "parts": [
                {
                    "name": p.name,
                    "sequence": str(p.sequence),
                    "num_frames": p.num_frames,
                    "surface": None if p.surface is None else str(p.surface),
                    "has_depth": p.has_depth,
                }
                for p in done
            ],
        }
        (tmp / REFERENCE_MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    return ReferenceImport(Path(out_dir), done)
