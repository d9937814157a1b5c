"""Real data in: endoscope video or image folder + tracked poses + calibration -> a sequence.

Everything a real recording needs to become a sequence folder (``chisel.io.sequence``):

- frames from a video file (``cv2.VideoCapture``) or an image folder;
- poses from a pose file, matched to the frames by index or by timestamp
  (:mod:`chisel.io.import_poses`);
- intrinsics and distortion from an OpenCV / ROS / JSON calibration
  (``chisel.io.calibration``); frames undistorted to a new pinhole camera and masked to
  the endoscope's circular field stop (``chisel.io.undistort``), as the reference
  implementation's data are;
- optional per-frame depth (``.npy`` float mm or 16-bit PNG times a scale) and
  per-frame validity masks (PNG; tools, blood), named in :class:`FrameFiles`.

:func:`import_frames` runs in steps: the pose of each frame (:func:`pose_lookup`), the
side files (:func:`list_side_files`), the output camera and its mask
(:func:`output_camera`), then the frames written one by one and the counts checked at
the end. Output goes through :class:`chisel.io.sequence.SequenceWriter`, so a failed
import leaves no partial folder and keeps an earlier one. ``.npy`` files are never
unpickled. The reference implementation's layout is :mod:`chisel.io.import_reference`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from chisel.core.errors import InvalidInputError, PoseError
from chisel.core.geometry import Camera
from chisel.io.calibration import Calibration, read_calibration
from chisel.io.import_common import (
    IMAGE_SUFFIXES,
    list_files,
    output_errors,
    read_depth,
    read_mask_png,
)
from chisel.io.import_poses import (
    PoseConfig,
    PoseTrack,
    match_poses_by_time,
    poses_world_from_cam,
    read_frame_times,
    read_pose_file,
)
from chisel.io.import_sources import FrameConfig, FrameSource, ImageFolderSource, VideoSource
from chisel.io.sequence import Frame, SequenceWriter
from chisel.io.undistort import (
    Circle,
    Undistortion,
    check_lens_model,
    circle_mask,
    fit_field_stop,
    make_undistortion,
)

log = logging.getLogger(__name__)

FIELD_STOP_FIT_FRAMES = 30
"""How many (evenly spread, selected) frames the field-stop fit looks at."""


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


@dataclass(frozen=True)
class FrameFiles:
    """The files beside the frames and the pose file; each optional, paths as given."""

    frame_times_path: str | Path | None = None
    """CSV/text of frame times in seconds (last column), for timestamp matching."""
    depth_dir: str | Path | None = None
    """Folder of per-frame depth (``.npy`` float or 16-bit ``.png``), one file per source
    frame in natural name order, on the raw image grid."""
    mask_dir: str | Path | None = None
    """Folder of per-frame mask PNGs (tools, blood), one per source frame, raw grid."""
    camera_mask_path: str | Path | None = None
    """PNG of the field stop on the raw grid (255 = inside); overrides the fit."""


# ----------------------------------------------------------------------------- import


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


@dataclass(frozen=True)
class PoseLookup:
    """The pose of each source frame: by index, or at the frame's time on the pose clock."""

    track: PoseTrack
    """The pose file as read (its timestamps, its raw rows for messages)."""
    poses: np.ndarray
    """(N, 4, 4) float64 ``T_world_from_cam`` in mm, NaN where tracking was lost."""
    cfg: PoseConfig
    """How the poses are matched to frames."""
    source_name: str
    """The video or image folder (for messages)."""
    frame_times: np.ndarray | None = None
    """(M,) float64 frame times in seconds from the frame-time file, if one was given."""
    frame_times_path: str | Path = ""
    """That file (for messages), given with ``frame_times``."""
    fps: float | None = None
    """Frame rate for frame times from the frame index, when there is no such file."""

    def check_has_pose(self, i: int) -> None:
        """Raise :class:`PoseError` when index matching has no pose for frame ``i``."""
        if self.cfg.match == "index" and i >= len(self.poses):
            raise PoseError(
                self.source_name,
                f"has more frames than {self.track.source} has poses ({len(self.poses)}); "
                f"index matching needs one pose per frame",
            )

    def pose_for(self, i: int) -> tuple[np.ndarray | None, str]:
        """(4, 4) ``T_world_from_cam`` in mm of source frame ``i``, or None and why not."""
        if self.cfg.match == "index":
            self.check_has_pose(i)
            T = self.poses[i]
            if np.isfinite(T).all():
                return T, ""
            # NaN is how trackers mark a lost pose; inf is a broken file, named as such
            # (read from the file's row: the world transform turned both into NaN).
            lost = np.isnan(self.track.poses[i]).any()
            return None, "pose is NaN (tracking lost)" if lost else "pose is inf"
        t = self.frame_time_s(i)
        assert self.track.timestamps_s is not None
        T = match_poses_by_time(
            self.track.timestamps_s,
            self.poses,
            np.array([t]),
            self.cfg.time_tolerance_s,
            self.cfg.interpolation,
            self.track.source,
        )[0]
        if np.isfinite(T).all():
            return T, ""
        return None, f"no valid pose within {self.cfg.time_tolerance_s} s of t = {t:.6f} s"

    def frame_time_s(self, i: int) -> float:
        """Time of source frame ``i`` on the pose clock, seconds."""
        if self.frame_times is not None:
            if i >= len(self.frame_times):
                raise InvalidInputError(
                    self.frame_times_path,
                    f"has {len(self.frame_times)} frame times but {self.source_name} has "
                    f"more frames",
                )
            return self.frame_times[i]
        assert self.fps is not None
        return self.cfg.frame_time_offset_s + i / self.fps

    def check_counts(self, n_source: int) -> None:
        """After the last frame: the pose file and frame-time file fit the frame count."""
        if self.cfg.match == "index" and n_source != len(self.poses):
            raise PoseError(
                self.source_name,
                f"has {n_source} frames but {self.track.source} has {len(self.poses)} poses "
                f"(a truncated video, or the wrong pose file?)",
            )
        if self.frame_times is not None and n_source != len(self.frame_times):
            raise InvalidInputError(
                self.frame_times_path,
                f"has {len(self.frame_times)} frame times but {self.source_name} has "
                f"{n_source} frames",
            )


def pose_lookup(
    track: PoseTrack,
    poses: np.ndarray,
    cfg: PoseConfig,
    source: FrameSource,
    frame_times_path: str | Path | None,
) -> PoseLookup:
    """How each frame finds its pose; refuses timestamp matching without the times."""
    if cfg.match != "timestamp":
        return PoseLookup(track, poses, cfg, source.name)
    if track.timestamps_s is None:
        raise PoseError(
            track.source,
            "timestamp matching needs a TUM pose file (with timestamps); use match=index",
        )
    if frame_times_path is not None:
        times = read_frame_times(frame_times_path)
        return PoseLookup(track, poses, cfg, source.name, times, frame_times_path)
    fps = cfg.fps or source.fps
    if fps is None:
        raise InvalidInputError(
            source.name,
            "timestamp matching needs frame times: give a frame-time CSV or fps",
        )
    return PoseLookup(track, poses, cfg, source.name, fps=fps)


@dataclass(frozen=True)
class SideFolder:
    """A folder of per-frame files, one per source frame, natural name order."""

    folder: str | Path
    """The folder, as given (it names the errors)."""
    files: list[Path]
    """Its files."""

    def nth(self, i: int) -> Path:
        """The file of source frame ``i``; refuses a folder that ran out of files."""
        if i >= len(self.files):
            raise InvalidInputError(
                self.folder, f"has {len(self.files)} files, fewer than the frames"
            )
        return self.files[i]


@dataclass(frozen=True)
class SideFiles:
    """Per-frame depth and mask files, each None when there is no such folder."""

    depth: SideFolder | None
    """Depth files (``.npy`` float or 16-bit ``.png``)."""
    mask: SideFolder | None
    """Mask PNGs."""

    def read(
        self, i: int, cfg: FrameConfig, raw: Camera
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Source frame ``i``'s depth (H, W) float32 mm, NaN = invalid, and mask (H, W)
        bool, True = use, on the raw grid; None where there is no such folder."""
        depth = mask = None
        if self.depth is not None:
            path = self.depth.nth(i)
            depth = read_depth(path, cfg.depth_scale_mm)
            raw.check_image(depth, str(path))
        if self.mask is not None:
            path = self.mask.nth(i)
            mask = read_mask_png(path, cfg.mask_invert)
            raw.check_image(mask, str(path))
        return depth, mask

    def check_counts(self, n_source: int | None, source_name: str) -> None:
        """One file per source frame (when the frame count is known)."""
        if n_source is None:
            return
        for side in (self.depth, self.mask):
            if side is not None and len(side.files) != n_source:
                raise InvalidInputError(
                    side.folder,
                    f"has {len(side.files)} files but {source_name} has {n_source} frames",
                )


def list_side_files(files: FrameFiles, source: FrameSource) -> SideFiles:
    """List the depth and mask folders; their counts must match a known frame count."""
    depth = mask = None
    if files.depth_dir is not None:
        depth = SideFolder(files.depth_dir, list_files(files.depth_dir, (".npy", ".png"), "depth"))
    if files.mask_dir is not None:
        mask = SideFolder(files.mask_dir, list_files(files.mask_dir, IMAGE_SUFFIXES, "mask"))
    side = SideFiles(depth, mask)
    side.check_counts(source.count, source.name)
    return side


@dataclass(frozen=True)
class OutputCamera:
    """The camera the sequence is written with, and how raw frames map onto it."""

    camera: Camera
    """The sequence's camera (pinhole when undistorted)."""
    mask: np.ndarray | None
    """(H, W) bool camera mask on the output grid, None when it keeps every pixel."""
    undistortion: Undistortion | None
    """The remap of raw frames, None when they are written as they are."""
    field_stop: Circle | None
    """The field stop on the raw image, if any."""

    def undistorted(self, raw: Camera) -> bool:
        """Whether the written frames have zero distortion."""
        return self.undistortion is not None or not raw.has_distortion


def output_camera(
    source: FrameSource,
    raw: Camera,
    calibration_source: str,
    cfg: FrameConfig,
    camera_mask_path: str | Path | None,
) -> OutputCamera:
    """Field-stop mask, lens check and undistortion of the raw camera."""
    mask_raw, circle = _camera_mask_raw(
        source, raw, cfg, None if camera_mask_path is None else Path(camera_mask_path)
    )
    check_lens_model(raw, mask_raw, calibration_source)
    und: Undistortion | None = None
    camera = raw
    camera_mask = mask_raw
    if cfg.undistort and raw.has_distortion:
        und = make_undistortion(raw, cfg.alpha)
        camera = und.camera
        camera_mask = und.valid.copy() if mask_raw is None else und.mask(mask_raw)
    if camera_mask is not None:
        if not camera_mask.any():
            raise InvalidInputError(camera_mask_path or "field stop", "camera mask keeps no pixel")
        if camera_mask.all():
            camera_mask = None
    return OutputCamera(camera, camera_mask, und, circle)


def _header_meta(
    source: FrameSource,
    poses_path: str | Path,
    calib: Calibration,
    raw: Camera,
    pose_cfg: PoseConfig,
    circle: Circle | None,
    meta: dict[str, Any] | None,
) -> dict[str, Any]:
    """The sequence meta: where the frames, poses and calibration came from."""
    return {
        "source": source.name,
        "poses_file": str(poses_path),
        "calibration": calib.source,
        "raw_camera": raw.to_dict(),
        "pose_units_in_file": pose_cfg.units,
        # False tells the sequence reader not to refuse positions that look like metres.
        "pose_units_checked": pose_cfg.check_units,
        "pose_match": pose_cfg.match,
        "pose_interpolation": pose_cfg.interpolation if pose_cfg.match == "timestamp" else None,
        "field_stop_raw_px": None if circle is None else [circle.cx, circle.cy, circle.r],
        **(meta or {}),
    }


@dataclass(frozen=True)
class _Written:
    """What the frame loop wrote."""

    kept: list[int]
    """Source indices of the frames written, in order."""
    dropped: list[tuple[int, str]]
    """(source index, reason) of selected frames left out for want of a pose."""
    num_source_frames: int
    """Frames the source yielded."""


def _write_frames(
    w: SequenceWriter,
    frames: Iterable[tuple[int, np.ndarray | None]],
    raw: Camera,
    out: OutputCamera,
    lookup: PoseLookup,
    side: SideFiles,
    cfg: FrameConfig,
) -> _Written:
    """Write each selected frame with a pose (undistorted when ``out`` says so)."""
    dropped: list[tuple[int, str]] = []
    kept: list[int] = []
    n_source = 0
    und = out.undistortion
    for i, rgb in frames:
        n_source = i + 1
        lookup.check_has_pose(i)  # raises: more frames than poses
        if rgb is None:
            continue
        raw.check_image(rgb, f"{lookup.source_name} frame {i}")
        T, why = lookup.pose_for(i)
        if T is None:
            if not lookup.cfg.drop_unposed:
                raise PoseError(
                    lookup.track.source,
                    f"frame {i} of {lookup.source_name}: {why} (use drop_unposed / "
                    f"--drop-unposed to leave such frames out)",
                )
            dropped.append((i, why))
            continue
        depth, mask = side.read(i, cfg, raw)
        if und is not None:
            rgb = und.image(rgb)
            depth = None if depth is None else und.depth(depth)
            mask = None if mask is None else und.mask(mask)
        w.add(Frame(index=len(kept), T_world_from_cam=T, rgb=rgb, depth_mm=depth, mask=mask))
        kept.append(i)
    return _Written(kept, dropped, n_source)


def import_frames(
    source: FrameSource,
    poses_path: str | Path,
    calibration: str | Path | Calibration,
    out_path: str | Path,
    pose_cfg: PoseConfig | None = None,
    frame_cfg: FrameConfig | None = None,
    *,
    files: FrameFiles | None = None,
    meta: dict[str, Any] | None = None,
    progress: bool = False,
) -> ImportReport:
    """Import frames + poses + calibration into a sequence folder at ``out_path``.

    Per-frame depth files and mask PNGs (``files``) are taken in natural order, one per
    source frame, on the raw image grid. Raises a
    :class:`~chisel.core.errors.InvalidInputError` subclass naming the file on any bad input;
    ``out_path`` is then left as it was.
    """
    pose_cfg = pose_cfg or PoseConfig()
    frame_cfg = frame_cfg or FrameConfig()
    files = files or FrameFiles()
    out_path = Path(out_path)
    calib = calibration if isinstance(calibration, Calibration) else read_calibration(calibration)
    track = read_pose_file(poses_path, pose_cfg.format)
    poses = poses_world_from_cam(track, pose_cfg)

    first = source.first()
    raw = calib.camera_for(first.shape[1], first.shape[0], rescale=frame_cfg.rescale_intrinsics)
    lookup = pose_lookup(track, poses, pose_cfg, source, files.frame_times_path)
    side = list_side_files(files, source)
    out = output_camera(source, raw, calib.source, frame_cfg, files.camera_mask_path)
    header = _header_meta(source, poses_path, calib, raw, pose_cfg, out.field_stop, meta)

    frames: Iterable[tuple[int, np.ndarray | None]] = source.frames(frame_cfg)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=source.count, desc="import", unit="frame")
    with (
        output_errors(out_path),
        SequenceWriter(out_path, out.camera, header, out.mask, out.undistorted(raw)) as w,
    ):
        done = _write_frames(w, frames, raw, out, lookup, side, frame_cfg)
        lookup.check_counts(done.num_source_frames)
        side.check_counts(done.num_source_frames, source.name)
        if not done.kept:
            raise PoseError(track.source, f"no selected frame of {source.name} has a valid pose")
        w.meta["source_frame_index"] = done.kept
        w.meta["dropped_frames"] = [[i, why] for i, why in done.dropped]
    if done.dropped:
        log.warning(
            "%d frame(s) dropped for want of a pose: %s",
            len(done.dropped),
            [i for i, _ in done.dropped][:20],
        )
    return ImportReport(
        out_path,
        len(done.kept),
        done.num_source_frames,
        done.dropped,
        out.camera,
        raw,
        out.field_stop,
        out.undistorted(raw),
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
