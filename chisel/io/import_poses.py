"""Tracker poses in: pose files, units, hand-eye and registration, matching to frames.

Poses come from a text file (N x 16 row-major 4x4, N blocks of 4 lines, or TUM
``timestamp tx ty tz qx qy qz qw``) or a ``.npy`` (N, 4, 4), are matched to frames by
index or by timestamp (nearest within a tolerance, or SLERP between the two samples
around the frame time), translations in m or mm, composed with a fixed hand-eye
transform and a tracker-to-world registration::

    T_world_from_cam[i] = T_world_from_tracker @ P[i] @ T_marker_from_cam

where ``P[i]`` is the i-th pose of the file (the tracked marker in tracker coordinates;
with no hand-eye transform the file's poses are the camera's own).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from chisel.core.errors import InvalidInputError, PoseError
from chisel.core.geometry import check_rigid
from chisel.io.import_common import load_npy
from chisel.io.limits import read_text_limited
from chisel.io.sequence import check_pose_units

QUATERNION_NORM_TOL = 1e-2
"""Quaternions whose norm differs from 1 by more than this are refused, not normalised."""


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


def _load_numbers_npy(path: Path, what: str) -> np.ndarray:
    """A ``.npy`` of real numbers as float64 (strings or complex numbers are refused:
    ``astype`` would raise, or drop the imaginary part)."""
    arr = load_npy(path)
    if arr.dtype.kind not in "fiu":
        raise PoseError(path, f"{what} must be real numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64)


def read_transform(path: str | Path, source: str) -> np.ndarray:
    """A single (4, 4) transform from a ``.npy`` or a text file of 16 numbers."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        arr = _load_numbers_npy(path, source)
    else:
        if not path.is_file():
            raise InvalidInputError(path, f"{source} file not found")
        text = read_text_limited(path, f"{source} file", PoseError).strip()
        try:
            arr = np.array(re.split(r"[,\s]+", text), dtype=np.float64)
        except ValueError as exc:
            raise PoseError(path, f"cannot parse {source}: {exc}") from None
    if arr.size != 16:
        raise PoseError(path, f"{source} must be a 4x4 matrix (16 numbers), got {arr.size}")
    return check_rigid(arr.reshape(4, 4), f"{path} ({source})")


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


def _read_numeric_rows(
    path: Path, what: str, error: type[InvalidInputError]
) -> tuple[np.ndarray, list[int]]:
    """Rows of numbers (comma or space separated, '#' comments, one header line allowed)
    from the text file ``path`` (UTF-8, size-limited: ``what`` and ``error`` name it)."""
    rows: list[list[float]] = []
    linenos: list[int] = []
    text = read_text_limited(path, what, error)
    for lineno, raw in enumerate(text.splitlines(), 1):
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
        arr = _load_numbers_npy(path, "poses")
        if arr.ndim == 2 and arr.shape[1] == 16:
            arr = arr.reshape(-1, 4, 4)
        if arr.ndim != 3 or arr.shape[1:] != (4, 4) or len(arr) == 0:
            raise PoseError(path, f"expected (N, 4, 4) or (N, 16) poses, got shape {arr.shape}")
        return PoseTrack(arr, None, str(path))
    rows, linenos = _read_numeric_rows(path, "pose file", PoseError)
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
        fix = (
            "pass --pose-units m, or check_units=False if this is right"
            if cfg.units == "mm"
            else "pass --pose-units mm"
        )
        check_pose_units(track.poses, cfg.units, track.source, "tracker", fix)
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
    rows, _ = _read_numeric_rows(path, "frame-time file", InvalidInputError)
    times = rows[:, -1].copy()
    if not np.all(np.isfinite(times)):
        raise InvalidInputError(path, "frame times contain NaN/inf")
    if len(times) > 1 and np.any(np.diff(times) <= 0):
        raise InvalidInputError(path, "frame times must increase")
    return times
