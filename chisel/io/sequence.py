"""The *sequence* on-disk contract (version 1): the updater's input.

A sequence folder holds one endoscopic pass: intrinsics, per-frame RGB, optional depth,
per-frame tracked poses (and, for synthetic data, the true poses), optional masks::

    <seq>/
      sequence.json        format, version, camera, frame count, what is present, meta
      poses.txt            N lines, 16 numbers each: tracked T_world_from_cam, row-major, mm
      poses_true.txt       optional: true T_world_from_cam (synthetic data)
      rgb/000000.png       optional: uint8 RGB
      depth/000000.npy     optional: float32 z-depth in mm, 0 = invalid (NaN in memory)
      mask/000000.png      optional: uint8, 255 = use this pixel (tools, blood, field stop)
      camera_mask.png      optional: uint8, 255 inside the endoscope's circular field stop

Readable by a person (JSON, text, PNG) and loadable without pickle (``.npy`` is read with
``allow_pickle=False``). Every file is read from inside the folder: a link (a subfolder, a
frame, ``poses.txt``) that leads out of it is refused
(:class:`~chisel.core.errors.OutsideManifestError`) unless the caller allows it. The one
place that converts depth between disk (0 = invalid) and memory (NaN = invalid) is
:func:`depth_to_disk` / :func:`depth_from_disk`.
"""

from __future__ import annotations

import errno
import json
import os
import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from chisel.core.atomic import atomic_dir
from chisel.core.errors import (
    CameraError,
    DepthUnitsError,
    FormatVersionError,
    InvalidInputError,
    PoseError,
    ResourceLimitError,
    out_of_memory_names,
)
from chisel.core.geometry import Camera, check_rigid
from chisel.io.images import PNG_MAGIC, decode_image
from chisel.io.limits import MAX_IMAGE_SIDE_PX, check_npy_header, read_text_limited
from chisel.io.manifest import check_inside, json_type, read_json_manifest
from chisel.io.undistort import check_lens_model

SEQUENCE_FORMAT = "endoscopic-chisel/sequence"
ALLOW_OUTSIDE_SEQUENCE = (
    "--allow-outside-sequence to chisel build, update or render-depth, or allow_outside=True "
    "to chisel.io.sequence.Sequence,"
)
SEQUENCE_VERSION = 1

MIN_PLAUSIBLE_MEDIAN_DEPTH_MM = 0.5
"""A valid depth map whose median is below this is taken to be in metres, not mm.

Endoscopic working distances are 5-30 mm; in metres they read 0.005-0.03."""

METRE_LIKE_MAX_TRANSLATION_MM = 1.0
"""Poses in mm whose every position lies within this distance of the origin are taken to
be in metres (a tracker sits ~0.1-2 m from the patient, a CT's origin ~0.1-0.3 m)."""

MM_LIKE_MIN_TRANSLATION_M = 10.0
"""Poses in metres with a position farther than this from the origin are taken to be mm."""


@dataclass(frozen=True)
class Frame:
    """One frame in memory."""

    index: int
    T_world_from_cam: np.ndarray
    """(4, 4) float64, tracked pose (what the navigation system reports), mm."""
    rgb: np.ndarray | None = None
    """(H, W, 3) uint8 RGB."""
    depth_mm: np.ndarray | None = None
    """(H, W) float32 z-depth in mm, NaN = invalid."""
    mask: np.ndarray | None = None
    """(H, W) bool, True = use this pixel."""
    T_world_from_cam_true: np.ndarray | None = None
    """(4, 4) float64 true pose (synthetic data only)."""


def depth_to_disk(depth_mm: np.ndarray) -> np.ndarray:
    """Memory -> disk: (H, W) float NaN-invalid -> float32 with 0 = invalid."""
    d = np.asarray(depth_mm, dtype=np.float32).copy()
    d[~np.isfinite(d) | (d <= 0)] = 0.0
    return d


def depth_from_disk(depth_disk: np.ndarray) -> np.ndarray:
    """Disk -> memory: float32 with 0 = invalid -> float32 with NaN = invalid."""
    d = np.asarray(depth_disk, dtype=np.float32).copy()
    d[~np.isfinite(d) | (d <= 0)] = np.nan
    return d


def check_depth_mm(depth_mm: np.ndarray, source: str) -> np.ndarray:
    """Validate a z-depth map in mm; raise on all-invalid or metre-scaled input.

    depth_mm : (H, W) float, NaN or 0 = invalid. Returns float32 with NaN = invalid.
    """
    d = np.asarray(depth_mm, dtype=np.float32)
    if d.ndim != 2:
        raise InvalidInputError(source, f"depth must be a 2-D (H, W) map, got shape {d.shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, np.float32(np.nan)).astype(np.float32)
    valid = np.isfinite(d)
    if not valid.any():
        raise InvalidInputError(source, "depth map has no valid pixel (all 0/NaN/negative)")
    median = float(np.median(d[valid]))
    if median < MIN_PLAUSIBLE_MEDIAN_DEPTH_MM:
        raise DepthUnitsError(
            source,
            f"median depth is {median:.4g}, implausibly small for millimetres; the depth "
            f"looks like metres: multiply by 1000",
        )
    return d


def check_pose_units(
    poses: np.ndarray, units: Literal["mm", "m"], source: str, origin: str, fix: str
) -> None:
    """Refuse poses whose translations contradict their declared ``units``.

    poses : (N, 4, 4) float, units as declared; NaN/inf rows (lost tracking) are skipped.
    ``origin`` names the frame of the positions ("tracker", "world"), ``fix`` the way out.
    The one units check of poses: the importers and the sequence reader both call it.
    """
    valid = np.isfinite(poses).all(axis=(1, 2))
    if not valid.any():
        return
    t_max = float(np.linalg.norm(poses[valid, :3, 3], axis=1).max())
    # One pose near the origin is a plausible mm pose; a whole trajectory within 1 is not.
    if units == "mm" and t_max < METRE_LIKE_MAX_TRANSLATION_MM and valid.sum() > 1:
        raise PoseError(
            source,
            f"every camera position is within {t_max:.4g} of the {origin} origin: "
            f"translations look like metres, but units are mm ({fix})",
        )
    if units == "m" and t_max > MM_LIKE_MIN_TRANSLATION_M:
        raise PoseError(
            source,
            f"a camera position is {t_max:.4g} m from the {origin} origin: translations "
            f"look like millimetres, but units are m ({fix})",
        )


def imwrite(path: str, img: np.ndarray) -> None:
    """``cv2.imwrite`` that fails loudly: OpenCV returns False (disk full, unwritable
    folder) instead of raising, which would leave a frame silently missing."""
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        # A name with a byte that is not UTF-8 crashes OpenCV's own file handling
        # (exit 139); Python writes those bytes, OpenCV only encodes.
        ok, buf = cv2.imencode(Path(path).suffix, img)
        if not ok:
            raise OSError(errno.EIO, f"cannot encode image {path!r}") from None
        Path(path).write_bytes(buf.tobytes())
        return
    if not cv2.imwrite(path, img):
        raise OSError(errno.EIO, f"cannot write image {path} (disk full or unwritable?)")


def _poses_to_text(poses: np.ndarray) -> str:
    lines = [" ".join(f"{v:.17g}" for v in T.ravel()) for T in poses]
    return "\n".join(lines) + "\n"


def read_poses_txt(path: Path) -> np.ndarray:
    """Read N x 16 row-major ``T_world_from_cam`` lines; returns (N, 4, 4) float64."""
    if not path.is_file():
        raise PoseError(path, "file is missing")
    text = read_text_limited(path, "pose file", PoseError)
    with out_of_memory_names(path, "reading this pose file"):
        try:
            with warnings.catch_warnings():  # an empty file is refused below, by name
                warnings.simplefilter("ignore", UserWarning)
                arr = np.loadtxt(text.splitlines(), dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise PoseError(path, f"cannot parse pose file: {exc}") from None
    if arr.size == 0:
        raise PoseError(path, "pose file is empty")
    if arr.shape[1] != 16:
        raise PoseError(path, f"expected 16 numbers per line (a row-major 4x4), got {arr.shape[1]}")
    poses = arr.reshape(-1, 4, 4)
    check_rigid(poses, str(path))
    return poses


def check_pinhole_without_skew(camera: Camera, source: str) -> None:
    """Refuse a camera matrix with skew (``K[0, 1] != 0``): the projections of the updater
    and the renderers use fx, fy, cx, cy only, so a skew would be silently dropped."""
    skew = float(camera.K[0, 1])
    if abs(skew) > 1e-9 * camera.K[0, 0]:
        raise CameraError(
            source,
            f"camera matrix has skew K[0][1] = {skew:g}, which the projection does not model; "
            "import the frames undistorted (chisel import without --no-undistort remaps "
            "them to a pinhole camera without skew)",
        )


class SequenceWriter:
    """Write a sequence folder atomically, one frame at a time.

    Use as a context manager; the folder appears only when the block exits cleanly::

        with SequenceWriter(out_dir, camera, meta={"source": "sim"}) as w:
            for frame in frames:
                w.add(frame)
    """

    def __init__(
        self,
        path: str | Path,
        camera: Camera,
        meta: dict[str, Any] | None = None,
        camera_mask: np.ndarray | None = None,
        undistorted: bool = False,
    ) -> None:
        self.path = Path(path)
        check_pinhole_without_skew(camera, f"{self.path}: camera")
        self.camera = camera
        self.meta = dict(meta or {})
        self.camera_mask = camera_mask
        self.undistorted = undistorted
        self._poses: list[np.ndarray] = []
        self._true: list[np.ndarray | None] = []
        self._has: dict[str, bool | None] = {"rgb": None, "depth": None, "mask": None}
        self._ctx: AbstractContextManager[Path] | None = None
        self._tmp: Path | None = None

    def __enter__(self) -> SequenceWriter:
        self._ctx = atomic_dir(self.path, "sequence.json")
        self._tmp = self._ctx.__enter__()
        for sub in ("rgb", "depth", "mask"):
            (self._tmp / sub).mkdir()
        return self

    def _present(self, key: str, value: object) -> bool:
        has = value is not None
        if self._has[key] is None:
            self._has[key] = has
        elif self._has[key] != has:
            raise InvalidInputError(
                f"frame {len(self._poses)}", f"{key} present in some frames only"
            )
        return has

    def add(self, frame: Frame) -> None:
        assert self._tmp is not None, "use SequenceWriter as a context manager"
        i = len(self._poses)
        name = f"{i:06d}"
        self._poses.append(check_rigid(frame.T_world_from_cam, f"frame {i} pose"))
        self._true.append(
            None
            if frame.T_world_from_cam_true is None
            else check_rigid(frame.T_world_from_cam_true, f"frame {i} true pose")
        )
        if self._present("rgb", frame.rgb):
            assert frame.rgb is not None  # _present: not None
            self.camera.check_image(frame.rgb, f"frame {i} rgb")
            rgb = np.asarray(frame.rgb)
            if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
                raise InvalidInputError(
                    f"frame {i} rgb", f"expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}"
                )
            imwrite(str(self._tmp / "rgb" / f"{name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if self._present("depth", frame.depth_mm):
            assert frame.depth_mm is not None  # _present: not None
            self.camera.check_image(frame.depth_mm, f"frame {i} depth")
            np.save(self._tmp / "depth" / f"{name}.npy", depth_to_disk(frame.depth_mm))
        if self._present("mask", frame.mask):
            assert frame.mask is not None  # _present: not None
            self.camera.check_image(frame.mask, f"frame {i} mask")
            imwrite(
                str(self._tmp / "mask" / f"{name}.png"),
                np.where(frame.mask, 255, 0).astype(np.uint8),
            )

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self._ctx is not None and self._tmp is not None
        try:
            if exc_type is None:
                self._finish(self._tmp)
        except BaseException:
            self._ctx.__exit__(*__import__("sys").exc_info())
            raise
        self._ctx.__exit__(exc_type, exc, tb)

    def _finish(self, tmp: Path) -> None:
        n = len(self._poses)
        if n == 0:
            raise InvalidInputError(self.path, "a sequence needs at least one frame")
        has_true = [t is not None for t in self._true]
        if any(has_true) and not all(has_true):
            raise InvalidInputError(self.path, "true poses present for some frames only")
        for sub in ("rgb", "depth", "mask"):
            if not self._has[sub]:
                (tmp / sub).rmdir()
        (tmp / "poses.txt").write_text(_poses_to_text(np.stack(self._poses)))
        if all(has_true):
            (tmp / "poses_true.txt").write_text(_poses_to_text(np.stack(self._true)))  # type: ignore[arg-type]
        if self.camera_mask is not None:
            self.camera.check_image(self.camera_mask, "camera_mask")
            imwrite(
                str(tmp / "camera_mask.png"), np.where(self.camera_mask, 255, 0).astype(np.uint8)
            )
        header = {
            "format": SEQUENCE_FORMAT,
            "version": SEQUENCE_VERSION,
            "num_frames": n,
            "camera": self.camera.to_dict(),
            "undistorted": bool(self.undistorted),
            "units": "mm",
            "depth_kind": "z",
            "pose_convention": "T_world_from_cam, OpenCV camera axes (+x right, +y down, +z forward)",
            "has_rgb": bool(self._has["rgb"]),
            "has_depth": bool(self._has["depth"]),
            "has_mask": bool(self._has["mask"]),
            "has_true_poses": bool(all(has_true)),
            "has_camera_mask": self.camera_mask is not None,
            "meta": self.meta,
        }
        (tmp / "sequence.json").write_text(json.dumps(header, indent=2) + "\n")


def write_sequence(
    path: str | Path,
    camera: Camera,
    frames: list[Frame] | Iterator[Frame],
    meta: dict[str, Any] | None = None,
    camera_mask: np.ndarray | None = None,
    undistorted: bool = False,
) -> Path:
    """Write ``frames`` as a sequence folder at ``path`` (atomically); returns ``path``."""
    with SequenceWriter(path, camera, meta, camera_mask, undistorted) as w:
        for f in frames:
            w.add(f)
    return Path(path)


def _is_int(value: object) -> bool:
    # bool is an int subclass: ``true`` is not a frame count or a pixel size.
    return isinstance(value, int) and not isinstance(value, bool)


def _header_flag(header: dict[str, Any], key: str, source: Path) -> bool:
    """A ``has_*`` / ``undistorted`` flag; absent means False (as written by older tools)."""
    value = header.get(key, False)
    # bool("false") is True: a quoted flag would silently switch a part on.
    if not isinstance(value, bool):
        raise InvalidInputError(source, f"{key} must be true or false, got {value!r}")
    return value


def _header_camera(value: object, source: Path) -> Camera:
    """The header's ``camera`` object as a :class:`Camera` that fits its own image size."""
    if not isinstance(value, dict):
        raise CameraError(
            source, f"camera must be an object {{width, height, K, dist}}, got {json_type(value)}"
        )
    for key in ("width", "height"):
        if key in value and not _is_int(value[key]):
            raise CameraError(source, f"camera {key} must be an integer, got {value[key]!r}")
        if key in value and value[key] > MAX_IMAGE_SIDE_PX:
            raise ResourceLimitError(
                source, f"camera {key} is {value[key]} px, over the limit of {MAX_IMAGE_SIDE_PX}"
            )
    try:
        camera = Camera.from_dict(value, str(source))
    except CameraError:
        raise
    except (TypeError, ValueError) as exc:  # K or dist that are not arrays of numbers
        raise CameraError(source, f"camera K (3x3) and dist (5) must be numbers: {exc}") from None
    if not camera.principal_point_in_image:
        raise CameraError(
            source,
            f"principal point ({camera.cx:g}, {camera.cy:g}) lies outside the "
            f"{camera.width}x{camera.height} image: the intrinsics do not match the image size",
        )
    check_pinhole_without_skew(camera, str(source))
    return camera


class Sequence:
    """A sequence folder opened for reading; frames are loaded lazily.

    Raises :class:`InvalidInputError` subclasses naming the file on any malformed part, and
    :class:`~chisel.core.errors.OutsideManifestError` for a file or subfolder that is a link
    leading out of the folder (another patient's frames, ``/etc/...``), unless
    ``allow_outside``. Hard links and links that stay inside are read.
    """

    SUBFOLDERS = ("rgb", "depth", "mask")

    def __init__(self, path: str | Path, allow_outside: bool = False) -> None:
        self.path = Path(path)
        self.allow_outside = allow_outside
        header_path = self.path / "sequence.json"
        self._header_path = header_path
        if not header_path.is_file():
            raise InvalidInputError(self.path, "not a sequence folder: sequence.json is missing")
        # Checked once here: a file below a subfolder then needs only its own lstat.
        for name in ("sequence.json", *self.SUBFOLDERS):
            self._inside(name, "the header" if name == "sequence.json" else f"folder {name}/")
        header = read_json_manifest(header_path)
        if header.get("format") != SEQUENCE_FORMAT:
            raise FormatVersionError(
                header_path, f"format is {header.get('format')!r}, expected {SEQUENCE_FORMAT!r}"
            )
        if header.get("version") != SEQUENCE_VERSION:
            raise FormatVersionError(
                header_path,
                f"sequence version {header.get('version')!r}; this reader reads version {SEQUENCE_VERSION}",
            )
        for key in ("camera", "num_frames"):
            if key not in header:
                raise InvalidInputError(header_path, f"required field {key!r} is missing")
        # Absent in files from older tools, which wrote mm as well.
        units = header.get("units", "mm")
        if units != "mm":
            raise InvalidInputError(
                header_path, f"units is {units!r}; poses and depth must be in mm ('mm')"
            )
        # Absent in files from older tools, which wrote z-depth as well.
        depth_kind = header.get("depth_kind", "z")
        if depth_kind != "z":
            raise InvalidInputError(
                header_path,
                f"depth_kind is {depth_kind!r}; this reader reads z-depth along the optical "
                "axis ('z'): convert ray lengths with depth_z = depth_ray / |K^-1 (u, v, 1)|",
            )
        meta = header.get("meta", {})
        if not isinstance(meta, dict):
            raise InvalidInputError(header_path, f"meta must be an object, got {json_type(meta)}")
        num_frames = header["num_frames"]
        if not _is_int(num_frames) or num_frames < 1:
            raise InvalidInputError(
                header_path, f"num_frames must be a positive integer, got {num_frames!r}"
            )
        self.header: dict[str, Any] = header
        self.meta: dict[str, Any] = meta
        self.camera = _header_camera(header["camera"], header_path)
        self.num_frames: int = num_frames
        self.undistorted = _header_flag(header, "undistorted", header_path)
        self.has_rgb = _header_flag(header, "has_rgb", header_path)
        self.has_depth = _header_flag(header, "has_depth", header_path)
        self.has_mask = _header_flag(header, "has_mask", header_path)
        self.poses = read_poses_txt(self._inside("poses.txt", "poses"))
        if len(self.poses) != self.num_frames:
            raise PoseError(
                self.path / "poses.txt",
                f"{len(self.poses)} poses but sequence.json declares {self.num_frames} frames",
            )
        # The importers' units check, here too (metres read as mm failed much later);
        # skipped for a sequence imported with the check switched off on purpose.
        if meta.get("pose_units_checked", True) is not False:
            fix = (
                "a sequence stores mm: multiply the translations by 1000; if they are mm in a "
                "world whose origin lies within 1 mm of every camera, set meta.pose_units_checked "
                "to false in sequence.json"
            )
            check_pose_units(self.poses, "mm", str(self.path / "poses.txt"), "world", fix)
        self.true_poses: np.ndarray | None = None
        if _header_flag(header, "has_true_poses", header_path):
            true_path = self._inside("poses_true.txt", "true poses")
            if not true_path.is_file():
                raise PoseError(true_path, "file is missing but sequence.json sets has_true_poses")
            self.true_poses = read_poses_txt(true_path)
            if len(self.true_poses) != self.num_frames:
                raise PoseError(
                    true_path, f"{len(self.true_poses)} poses for {self.num_frames} frames"
                )
        self.camera_mask: np.ndarray | None = None
        if _header_flag(header, "has_camera_mask", header_path):
            mask_path = self._inside("camera_mask.png", "camera mask")
            self.camera_mask = self._read_mask(mask_path)
            if not self.camera_mask.any():
                raise InvalidInputError(mask_path, "camera mask keeps no pixel (all black)")
        # The importers refuse a lens model that folds over inside the used image; a
        # sequence written by other tools gets the same check (it failed much later).
        check_lens_model(self.camera, self.camera_mask, str(header_path))

    def __len__(self) -> int:
        return self.num_frames

    def _inside(self, name: str, what: str) -> Path:
        """``self.path / name`` (``name`` relative, made by this reader: no ``..``), refused
        if it is a link that resolves outside the sequence folder. The subfolders are checked
        in ``__init__``, so one ``lstat`` per file read suffices (no resolve on the frame path
        unless the file is a link)."""
        path = self.path / name
        if not self.allow_outside and os.path.islink(path):
            check_inside(self._header_path, Path(name), what, option=ALLOW_OUTSIDE_SEQUENCE)
        return path

    def _read_png(self, path: Path, gray: bool) -> np.ndarray:
        if not path.is_file():
            raise InvalidInputError(path, "file is missing")
        with open(path, "rb") as fh:
            if fh.read(8) != PNG_MAGIC:
                # OpenCV decodes by content: JPEG bytes (even truncated ones, with a grey
                # fill) under a .png name would otherwise read as a whole frame.
                raise InvalidInputError(path, "not a PNG file (a sequence stores PNG frames)")
        img = decode_image(path, cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
        self.camera.check_image(img, str(path))
        return img if gray else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def _read_mask(self, path: Path) -> np.ndarray:
        """A 0/255 mask PNG as bool; other values are refused, not thresholded (a grey 128
        from a resized or JPEG-compressed mask would turn excluded pixels valid)."""
        img = self._read_png(path, gray=True)
        odd = (img != 0) & (img != 255)
        if odd.any():
            values = np.unique(img[odd])
            raise InvalidInputError(
                path,
                f"mask holds {int(odd.sum())} pixel(s) that are neither 0 nor 255 (e.g. "
                f"{values[:5].tolist()}); a mask is 255 = use, 0 = do not use",
            )
        return img == 255

    def rgb(self, i: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of frame ``i``."""
        if not self.has_rgb:
            raise InvalidInputError(self.path, "sequence has no RGB")
        return self._read_png(self._inside(f"rgb/{i:06d}.png", f"rgb frame {i}"), gray=False)

    def depth_mm(self, i: int) -> np.ndarray:
        """(H, W) float32 z-depth of frame ``i`` in mm, NaN = invalid."""
        if not self.has_depth:
            raise InvalidInputError(self.path, "sequence has no depth")
        path = self._inside(f"depth/{i:06d}.npy", f"depth frame {i}")
        if not path.is_file():
            raise InvalidInputError(path, "file is missing")
        with out_of_memory_names(path, "reading this depth map"):
            try:
                with open(path, "rb") as fh:
                    if fh.read(6) == b"\x93NUMPY":
                        fh.seek(0)
                        check_npy_header(fh, path, path.stat().st_size)
                arr = np.load(path, allow_pickle=False)
            except InvalidInputError:  # a ValueError, but it names the file already
                raise
            except (ValueError, EOFError, OSError) as exc:  # EOFError: an empty file
                raise InvalidInputError(
                    path, f"cannot read depth (.npy without pickle): {exc}"
                ) from None
        if not isinstance(arr, np.ndarray):  # np.load opens an .npz archive as well
            arr.close()
            raise InvalidInputError(path, "depth must be a single .npy array, not an .npz archive")
        if arr.dtype.kind != "f":
            raise InvalidInputError(path, f"depth must be float32 mm, got dtype {arr.dtype}")
        if arr.ndim != 2:
            raise InvalidInputError(path, f"depth must be a 2-D (H, W) map, got shape {arr.shape}")
        self.camera.check_image(arr, str(path))
        depth = depth_from_disk(arr)
        valid = np.isfinite(depth)
        # The importers' units check, here too: depth in metres failed much later.
        if valid.any() and float(np.median(depth[valid])) < MIN_PLAUSIBLE_MEDIAN_DEPTH_MM:
            raise DepthUnitsError(
                path,
                f"median depth is {float(np.median(depth[valid])):.4g}, implausibly small for "
                "millimetres; the depth looks like metres: multiply by 1000",
            )
        return depth

    def mask(self, i: int) -> np.ndarray | None:
        """(H, W) bool mask of frame ``i`` (per-frame mask AND camera mask), or None."""
        m = None
        if self.has_mask:
            m = self._read_mask(self._inside(f"mask/{i:06d}.png", f"mask frame {i}"))
        if self.camera_mask is not None:
            m = self.camera_mask if m is None else (m & self.camera_mask)
        return m

    def frame(self, i: int, rgb: bool = True, depth: bool = True) -> Frame:
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range 0..{self.num_frames - 1}")
        return Frame(
            index=i,
            T_world_from_cam=self.poses[i],
            rgb=self.rgb(i) if (rgb and self.has_rgb) else None,
            depth_mm=self.depth_mm(i) if (depth and self.has_depth) else None,
            mask=self.mask(i),
            T_world_from_cam_true=None if self.true_poses is None else self.true_poses[i],
        )

    def __iter__(self) -> Iterator[Frame]:
        for i in range(self.num_frames):
            yield self.frame(i)
