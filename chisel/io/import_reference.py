"""The reference implementation's dataset layout in: ``input.json`` -> sequence folders.

The layout of Mangulabnan et al. (github.com/janemilym/ct-update): ``input.json`` with
``intrinsics``, ``preop_data`` and numbered steps, each a folder of undistorted images,
poses, a camera mask and optionally monocular depths and a segmentation mesh; see
:func:`import_reference` and docs/real-data.md. Every path the manifest names must lie
inside its folder unless the caller allows otherwise (issue 17).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from chisel.core.atomic import atomic_dir
from chisel.core.errors import CameraError, InvalidInputError, PoseError
from chisel.io.calibration import Calibration
from chisel.io.import_common import (
    IMAGE_SUFFIXES,
    load_npy,
    output_errors,
    read_depth,
    read_mask_png,
    read_rgb,
)
from chisel.io.import_poses import PoseConfig, PoseTrack, poses_world_from_cam
from chisel.io.limits import read_text_limited
from chisel.io.manifest import check_inside, named_path, read_json_manifest
from chisel.io.meshfile import read_mesh_file
from chisel.io.sequence import Frame, SequenceWriter

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


@dataclass(frozen=True)
class _ReferenceOptions:
    """The choices of :func:`import_reference` that hold for every part."""

    with_depth: bool
    """Import ``depths/*.npy`` where a part has them."""
    depth_scale_mm: float
    """Millimetres per stored depth unit."""
    pose_units: Literal["mm", "m"]
    """Units of the pose translations."""
    allow_outside: bool
    """Accept paths that resolve outside the manifest's folder."""


def _reference_intrinsics(value: object, source: str) -> np.ndarray:
    items: Any = value.split(",") if isinstance(value, str) else value  # JSON: anything
    try:
        vals = [float(v) for v in items]
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


def _part_images(manifest: Path, name: str, img_dir: Path, allow_outside: bool) -> list[Path]:
    """The part's images in the reference's order, each checked to lie inside."""
    # The reference pairs sorted(*.jpg) with the poses in order; keep its plain sort.
    images = sorted(img_dir.glob("*.jpg"))
    if not images:
        images = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise InvalidInputError(img_dir, f"{name}: no images (*.jpg) in the folder")
    # A link inside an accepted folder may still point anywhere.
    return [check_inside(manifest, p, f"{name} image", allow_outside=allow_outside) for p in images]


def _part_poses(
    part: dict, name: str, manifest: Path, poses_path: Path, pose_units: str
) -> np.ndarray:
    """(N, 4, 4) float64 ``T_world_from_cam`` in mm, all finite, subsampled as the older
    layout asks (``start_idx``, ``end_idx``, ``interval``)."""
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
    return poses


def _import_reference_part(
    part: object, name: str, manifest: Path, K: np.ndarray, out: Path, opts: _ReferenceOptions
) -> ReferencePart:
    source = str(manifest)
    if not isinstance(part, dict) or "base_dir" not in part:
        raise InvalidInputError(source, f"{name}: expected an object with 'base_dir'")

    def inside(
        value: object, key: str, kind: Literal["file", "folder"], base: Path | None = None
    ) -> Path:
        return named_path(
            manifest, value, f"{name}.{key}", allow_outside=opts.allow_outside, kind=kind, base=base
        )

    base = inside(part["base_dir"], "base_dir", "folder")
    img_dir = inside(part.get("img_dir", "images"), "img_dir", "folder", base)
    images = _part_images(manifest, name, img_dir, opts.allow_outside)
    poses_path = inside(part.get("poses", "trajectories.npy"), "poses", "file", base)
    poses = _part_poses(part, name, manifest, poses_path, opts.pose_units)
    if len(poses) != len(images):
        raise PoseError(poses_path, f"{len(poses)} poses but {len(images)} images in {img_dir}")
    mask_path = inside("undistorted_mask.bmp", "undistorted_mask.bmp", "file", base)
    camera_mask = read_mask_png(mask_path, threshold=0)  # the reference binarises with mask > 0
    first = read_rgb(images[0])
    camera = Calibration(K, np.zeros(5), None, source).camera_for(first.shape[1], first.shape[0])
    camera.check_image(camera_mask, str(mask_path))
    depth_files: list[Path] | None = None
    if opts.with_depth and (base / "depths").is_dir():
        depth_dir = inside("depths", "depths", "folder", base)
        depth_files = [
            check_inside(manifest, p, f"{name} depth", allow_outside=opts.allow_outside)
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
        "pose_units_in_file": opts.pose_units,
        "surface": None if surface is None else surface.name,
        "depth_source": None
        if depth_files is None
        else f"monocular estimate (depths/*.npy) x {opts.depth_scale_mm} mm per unit",
        "source_images": [p.name for p in images],
    }
    seq = out / name
    with SequenceWriter(seq, camera, meta, None if camera_mask.all() else camera_mask, True) as w:
        for i, img_path in enumerate(images):
            rgb = first if i == 0 else read_rgb(img_path)
            camera.check_image(rgb, str(img_path))
            depth = None
            if depth_files is not None:
                depth = read_depth(depth_files[i], opts.depth_scale_mm)
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
    opts = _ReferenceOptions(with_depth, depth_scale_mm, pose_units, allow_outside_manifest)
    done: list[ReferencePart] = []
    with output_errors(Path(out_dir)), atomic_dir(out_dir, REFERENCE_MANIFEST) as tmp:
        for name, part in parts:
            done.append(_import_reference_part(part, name, input_json, K, tmp, opts))
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
