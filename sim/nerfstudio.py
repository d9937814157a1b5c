"""Export a sequence folder to nerfstudio's ``transforms.json`` layout.

Conventions converted here (nerfstudio docs, "Data conventions"):

- camera axes: nerfstudio uses OpenGL (+x right, +y up, +z backwards), we use OpenCV
  (+y down, +z forward): ``T_world_from_cam_gl = T_world_from_cam_cv @ diag(1, -1, -1, 1)``;
- pixel centres: nerfstudio casts the ray of pixel ``(0, 0)`` through image coordinate
  ``(0.5, 0.5)``, we put that pixel's centre at ``(0, 0)``: so ``cx_ns = cx + 0.5``;
- units: poses are written in metres by default (``units="m"``) and depth stays ``.npy``
  float32 millimetres (0 = invalid), which matches nerfstudio's default
  ``depth_unit_scale_factor = 1e-3``; with ``units="mm"`` run nerfstudio with
  ``--depth-unit-scale-factor 1``.

Layout::

    DIR/transforms.json   camera_model OPENCV, fl_x, fl_y, cx, cy, w, h, k1, k2, k3, p1, p2, frames
    DIR/images/000000.png RGB (copied once it decodes to the camera's size)
    DIR/depth/000000.npy  float32 z-depth, mm, 0 = invalid (copied once it loads at that size)
    DIR/masks/000000.png  255 = use the pixel (field stop AND valid depth), 0 = ignore
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Literal

import numpy as np

from chisel.core.atomic import atomic_dir, check_output_outside
from chisel.core.errors import InvalidInputError, OutputError
from chisel.io.sequence import Sequence, imwrite

T_CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])
"""(4, 4) maps OpenGL camera-frame points to OpenCV camera-frame points (and back)."""

UNIT_SCALE = {"m": 1e-3, "mm": 1.0}


def gl_from_cv_pose(T_world_from_cam_cv: np.ndarray) -> np.ndarray:
    """(..., 4, 4) OpenCV ``T_world_from_cam`` -> nerfstudio/OpenGL camera-to-world."""
    return np.asarray(T_world_from_cam_cv, dtype=np.float64) @ T_CV_FROM_GL


def cv_from_gl_pose(T_world_from_cam_gl: np.ndarray) -> np.ndarray:
    """(..., 4, 4) nerfstudio/OpenGL camera-to-world -> OpenCV ``T_world_from_cam``."""
    return np.asarray(T_world_from_cam_gl, dtype=np.float64) @ T_CV_FROM_GL


def export_nerfstudio(
    sequence_dir: str | Path,
    out_dir: str | Path,
    use_true_poses: bool = False,
    units: Literal["m", "mm"] = "m",
) -> Path:
    """Write ``out_dir`` (atomically) from a sequence folder; returns its transforms.json path.

    ``use_true_poses`` exports ``poses_true.txt`` instead of the tracked ``poses.txt``.
    Raises :class:`InvalidInputError` for a malformed sequence (a frame that is missing,
    does not decode or is not the camera's size) or an ``out_dir`` that is, holds or lies
    inside the sequence folder; ``out_dir`` is then left as it was.
    """
    if units not in UNIT_SCALE:
        raise InvalidInputError("units", f"expected 'm' or 'mm', got {units!r}")
    # The atomic write replaces out_dir whole: refuse before it could delete the input.
    check_output_outside(out_dir, sequence_dir)
    seq = Sequence(sequence_dir)
    if not seq.has_rgb:
        raise InvalidInputError(seq.path, "sequence has no RGB images; nerfstudio needs images")
    if use_true_poses and seq.true_poses is None:
        raise InvalidInputError(seq.path, "sequence has no true poses (poses_true.txt)")
    poses = seq.true_poses if use_true_poses else seq.poses
    assert poses is not None
    cam = seq.camera
    k1, k2, p1, p2, k3 = (float(x) for x in cam.dist)
    scale = UNIT_SCALE[units]
    out = Path(out_dir)
    with atomic_dir(out, "transforms.json") as tmp:
        (tmp / "images").mkdir()
        (tmp / "masks").mkdir()
        if seq.has_depth:
            (tmp / "depth").mkdir()
        frames = []
        for i in range(len(seq)):
            name = f"{i:06d}"
            # Decode before copying the bytes: the accessors refuse a missing, corrupt or
            # wrongly sized frame, which nerfstudio would only discover mid-training.
            seq.rgb(i)
            shutil.copyfile(seq.path / "rgb" / f"{name}.png", tmp / "images" / f"{name}.png")
            T = gl_from_cv_pose(poses[i])
            T[:3, 3] *= scale
            frame = {"file_path": f"images/{name}.png", "transform_matrix": T.tolist()}
            mask = seq.mask(i)
            if mask is not None:
                try:
                    imwrite(
                        str(tmp / "masks" / f"{name}.png"), np.where(mask, 255, 0).astype(np.uint8)
                    )
                except OSError as exc:  # name the final file, not the temporary one
                    raise OutputError(out / "masks" / f"{name}.png", exc) from exc
                frame["mask_path"] = f"masks/{name}.png"
            if seq.has_depth:
                seq.depth_mm(i)
                shutil.copyfile(seq.path / "depth" / f"{name}.npy", tmp / "depth" / f"{name}.npy")
                frame["depth_file_path"] = f"depth/{name}.npy"
            frames.append(frame)
        if not any("mask_path" in f for f in frames):
            (tmp / "masks").rmdir()
        header = {
            "camera_model": "OPENCV",
            "fl_x": cam.fx,
            "fl_y": cam.fy,
            "cx": cam.cx + 0.5,
            "cy": cam.cy + 0.5,
            "w": int(cam.width),
            "h": int(cam.height),
            "k1": k1,
            "k2": k2,
            "k3": k3,
            "p1": p1,
            "p2": p2,
            "frames": frames,
            "endoscopic_chisel": {
                "source_sequence": str(seq.path.absolute()),
                "poses": "true" if use_true_poses else "tracked",
                "pose_units": units,
                "depth_units": "mm (float32 .npy, 0 = invalid)",
                "depth_unit_scale_factor": 1e-3 if units == "m" else 1.0,
                "camera_axes": "OpenGL (+x right, +y up, +z backwards)",
            },
        }
        (tmp / "transforms.json").write_text(json.dumps(header, indent=2) + "\n")
    return out / "transforms.json"
