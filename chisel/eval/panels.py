"""Figure-4 panels: one frame of a step as a row of images, and their ``.npz`` file.

Split out of :mod:`chisel.eval.report` (which re-exports these names).
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh

from chisel.core.atomic import atomic_savez
from chisel.core.errors import FormatVersionError, InvalidInputError
from chisel.core.geometry import Camera
from chisel.core.raycast import MeshRaycaster
from chisel.io.limits import read_npz
from chisel.io.sequence import Frame as SeqFrame
from chisel.io.sequence import depth_from_disk, depth_to_disk

PANELS_FORMAT = "endoscopic-chisel/panels"
PANELS_VERSION = 1

PANEL_DEPTH_KEYS: tuple[str, ...] = (
    "preop_depth_mm",
    "gt_depth_mm",
    "estimated_depth_mm",
    "updated_depth_mm",
)
"""Depth images of a panel, in display order (all share one colour range)."""

PANEL_IMAGE_KEYS: tuple[str, ...] = ("rgb", *PANEL_DEPTH_KEYS, "change_mask")
"""Every image of a panel, in display order."""


def png_data_uri(rgb: np.ndarray) -> str:
    """(H, W, 3) uint8 RGB -> ``data:image/png;base64,...``."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise InvalidInputError("image", "PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


@dataclass(frozen=True)
class StepPanel:
    """One frame of one step, shown as a row of images (the paper's Figure 4).

    Every image is optional, but a panel has at least one, and all share one (H, W).
    """

    step: int
    """Surgical step (0 = preop)."""
    frame_index: int
    """Index of the frame in its sequence."""
    rgb: np.ndarray | None = None
    """(H, W, 3) uint8 RGB frame."""
    preop_depth_mm: np.ndarray | None = None
    """(H, W) float32 z-depth of the preoperative model, mm, NaN = no surface."""
    gt_depth_mm: np.ndarray | None = None
    """(H, W) float32 ground-truth z-depth, mm, NaN = no surface."""
    estimated_depth_mm: np.ndarray | None = None
    """(H, W) float32 depth estimate (network, after scale and registration), mm, NaN = none."""
    updated_depth_mm: np.ndarray | None = None
    """(H, W) float32 z-depth of the updated model, mm, NaN = no surface."""
    change_mask: np.ndarray | None = None
    """(H, W) bool, True = changed."""

    def __post_init__(self) -> None:
        src = f"panel (step {self.step}, frame {self.frame_index})"
        if int(self.step) < 0 or int(self.frame_index) < 0:
            raise InvalidInputError(src, "step and frame_index must be >= 0")
        shape: tuple[int, ...] | None = None
        for key in PANEL_IMAGE_KEYS:
            arr = getattr(self, key)
            if arr is None:
                continue
            arr = np.asarray(arr)
            if key == "rgb":
                if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
                    raise InvalidInputError(
                        f"{src} rgb", f"expected (H, W, 3) uint8, got {arr.shape} {arr.dtype}"
                    )
            elif key == "change_mask":
                if arr.ndim != 2 or arr.dtype != bool:
                    raise InvalidInputError(
                        f"{src} change_mask", f"expected (H, W) bool, got {arr.shape} {arr.dtype}"
                    )
            else:
                if arr.ndim != 2 or arr.dtype.kind != "f":
                    raise InvalidInputError(
                        f"{src} {key}",
                        f"expected (H, W) float depth in mm, got {arr.shape} {arr.dtype}",
                    )
                arr = np.where(np.isfinite(arr) & (arr > 0), arr, np.nan).astype(np.float32)
            object.__setattr__(self, key, arr)
            if shape is None:
                shape = arr.shape[:2]
            elif arr.shape[:2] != shape:
                raise InvalidInputError(
                    f"{src} {key}", f"image is {arr.shape[:2]} (H, W) but the panel's is {shape}"
                )
        if shape is None:
            raise InvalidInputError(src, "a panel needs at least one image")

    def images(self) -> dict[str, np.ndarray]:
        """The present images, in display order."""
        return {k: getattr(self, k) for k in PANEL_IMAGE_KEYS if getattr(self, k) is not None}


# --------------------------------------------------------------------------------------
# The panels file (npz, no pickle)


def write_panels(path: str | Path, panels: Sequence[StepPanel]) -> Path:
    """Write panels to an ``.npz`` file (atomically, no pickle).

    Layout: ``format`` and ``version`` (0-d string / int), ``step`` and ``frame_index``
    (P,) int64, then for each image kind present in *every* panel one stacked array:
    ``rgb`` (P, H, W, 3) uint8; ``*_depth_mm`` (P, H, W) float32 mm with 0 = no surface
    (the on-disk depth rule); ``change_mask`` (P, H, W) bool. An image kind present in
    some panels only is an error.
    """
    if not panels:
        raise InvalidInputError(path, "no panel to write")
    arrays: dict[str, np.ndarray] = {
        "format": np.array(PANELS_FORMAT),
        "version": np.array(PANELS_VERSION),
        "step": np.array([p.step for p in panels], dtype=np.int64),
        "frame_index": np.array([p.frame_index for p in panels], dtype=np.int64),
    }
    for key in PANEL_IMAGE_KEYS:
        present = [getattr(p, key) is not None for p in panels]
        if not any(present):
            continue
        if not all(present):
            raise InvalidInputError(
                path, f"{key!r} is present in {sum(present)} of {len(panels)} panels; all or none"
            )
        shapes = {getattr(p, key).shape for p in panels}
        if len(shapes) != 1:
            raise InvalidInputError(
                path, f"{key!r} differs in size between panels: {sorted(shapes)}"
            )
        stack = np.stack([getattr(p, key) for p in panels])
        arrays[key] = depth_to_disk(stack) if key in PANEL_DEPTH_KEYS else stack
    return atomic_savez(path, arrays)


def read_panels(path: str | Path) -> list[StepPanel]:
    """Read a panels file written by :func:`write_panels`.

    Read as a model file is (:meth:`chisel.model.TsdfModel.load`): declared sizes and
    object arrays refused from the headers, no pickle; every problem (not an archive, no or
    another ``version``, missing or ill-typed arrays) is one error naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "panels file is missing")
    data = read_npz(path, "panels")
    if "format" not in data or data["format"].tolist() != PANELS_FORMAT:
        raise FormatVersionError(path, f"not a panels file (format must be {PANELS_FORMAT!r})")
    if "version" not in data:
        raise FormatVersionError(
            path, f"panels file has no 'version'; this reader reads version {PANELS_VERSION}"
        )
    # tolist(): a 0-d integer array gives an int; "1", [1], 1.0 or True stay refused.
    version = data["version"].tolist()
    if type(version) is not int or version != PANELS_VERSION:
        raise FormatVersionError(
            path, f"panels version {version!r}; this reader reads {PANELS_VERSION}"[:300]
        )
    for key in ("step", "frame_index"):
        if key not in data:
            raise InvalidInputError(path, f"panels file lacks the {key!r} array")
        if data[key].dtype.kind not in "iu" or data[key].ndim != 1:
            raise InvalidInputError(
                path,
                f"{key} must be a 1-D integer array, got {data[key].dtype} {data[key].shape}",
            )
    steps, frames = data["step"], data["frame_index"]
    n = len(steps)
    if len(frames) != n:
        raise InvalidInputError(path, f"'frame_index' holds {len(frames)} entries for {n} panels")
    images = {}
    for key in PANEL_IMAGE_KEYS:
        if key in data:
            arr = data[key]
            if arr.ndim == 0 or len(arr) != n:
                raise InvalidInputError(
                    path, f"{key!r} holds {len(arr) if arr.ndim else 0} images for {n} panels"
                )
            if key in PANEL_DEPTH_KEYS and arr.dtype.kind != "f":
                raise InvalidInputError(path, f"{key!r} must be float depth, got {arr.dtype}")
            images[key] = depth_from_disk(arr) if key in PANEL_DEPTH_KEYS else arr
    try:
        return [
            StepPanel(int(steps[i]), int(frames[i]), **{k: v[i] for k, v in images.items()})
            for i in range(n)
        ]
    except InvalidInputError as exc:  # it names the panel; the file is what the user has
        raise InvalidInputError(path, f"{exc.source}: {exc.problem}") from None


def make_step_panel(
    step: int,
    frame: SeqFrame,
    camera: Camera,
    preop_mesh: trimesh.Trimesh,
    updated_mesh: trimesh.Trimesh,
    estimated_depth_mm: np.ndarray | None = None,
    change_mask: np.ndarray | None = None,
) -> StepPanel:
    """A Figure-4 panel for one frame of a step's update sequence.

    The model depths are rendered at the frame's true pose when it has one (what the
    surgeon saw), else its tracked pose. ``estimated_depth_mm`` (H, W) float32, any scale,
    is median-scaled to the frame's ground-truth depth for display only.
    """
    T = (
        frame.T_world_from_cam
        if frame.T_world_from_cam_true is None
        else frame.T_world_from_cam_true
    )
    gt = frame.depth_mm
    est = None if estimated_depth_mm is None else np.asarray(estimated_depth_mm, np.float32)
    if est is not None and gt is not None:
        both = np.isfinite(est) & np.isfinite(gt)
        if both.any():
            est = est * np.float32(np.median(gt[both]) / np.median(est[both]))
    return StepPanel(
        step=step,
        frame_index=frame.index,
        rgb=frame.rgb,
        preop_depth_mm=MeshRaycaster.from_trimesh(preop_mesh).render_depth(camera, T),
        gt_depth_mm=gt,
        estimated_depth_mm=est,
        updated_depth_mm=MeshRaycaster.from_trimesh(updated_mesh).render_depth(camera, T),
        change_mask=change_mask,
    )
