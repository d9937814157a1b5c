"""One surgical step scored for every method: the file-level wrapper ``evaluate_step``
and the cells it writes (docs/evaluation.md)."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera
from chisel.eval.masks import (
    CHANGE_THRESHOLD_MM,
    MaskScores,
    _check_masks,
    mask_precision_recall,
    true_change_masks_from_depths,
)
from chisel.eval.metrics import (
    CorrespondenceError,
    RoiBox,
    _check_mesh,
    _check_poses,
    correspondence_error,
    render_depths,
)
from chisel.eval.surface import (
    FSCORE_THRESHOLD_MM,
    SurfaceMetricConfig,
    SurfaceMetrics,
    sample_surface_in_box,
    surface_metrics,
)
from chisel.eval.tables import (
    METRICS_VERSION,
    STEP_METRICS_FORMAT,
    step_label,
)
from chisel.eval.volume import RemovalScores, model_removal, removal_scores, true_removal
from chisel.io.images import decode_image
from chisel.io.limits import read_npz
from chisel.io.meshfile import read_mesh_file
from chisel.io.sequence import Sequence as SequenceFolder

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------
# One step, all methods


def _finite_or_none(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def method_cell(
    corr: CorrespondenceError,
    surf: SurfaceMetrics,
    masks: MaskScores | None,
    removal: RemovalScores | None = None,
) -> dict[str, float | int | None]:
    """One method's cell of ``metrics.json`` (every key of :data:`METRIC_KEYS`)."""
    if surf.threshold_mm != FSCORE_THRESHOLD_MM:
        raise InvalidInputError(
            "surface metrics",
            f"the table reports the F-score at {FSCORE_THRESHOLD_MM} mm, got {surf.threshold_mm} mm",
        )
    return {
        "mean_mm": corr.mean_mm,
        "std_mm": corr.std_mm,
        "median_mm": corr.median_mm,
        "n_points": corr.n_points,
        "n_gt_in_box": corr.n_gt_in_box,
        "missing_fraction": corr.missing_fraction,
        "accuracy_mm": surf.accuracy_mm,
        "completeness_mm": surf.completeness_mm,
        "accuracy_hd95_mm": surf.accuracy_hd95_mm,
        "completeness_hd95_mm": surf.completeness_hd95_mm,
        "hd95_mm": surf.hd95_mm,
        "chamfer_mm": surf.chamfer_mm,
        "precision_1mm": surf.precision,
        "recall_1mm": surf.recall,
        "fscore_1mm": surf.fscore,
        "mask_precision": None if masks is None else _finite_or_none(masks.precision),
        "mask_recall": None if masks is None else _finite_or_none(masks.recall),
        "removed_dice": None if removal is None else removal.dice,
        "removed_hd95_mm": None if removal is None else removal.hd95_mm,
        "removed_precision": None if removal is None else removal.precision,
        "removed_recall": None if removal is None else removal.recall,
    }


@dataclass(frozen=True)
class ChangeMaskInput:
    """Predicted change masks of one method and the truth they are scored against."""

    pred_masks: np.ndarray
    """(N, H, W) bool, True = changed, one per frame of the step's update sequence."""
    true_masks: np.ndarray
    """(N, H, W) bool true change in the same images (see :func:`_mask_inputs`)."""
    valid: np.ndarray | None = None
    """(H, W) or (N, H, W) bool pixels to score (e.g. the camera mask), or None = all."""


def evaluate_methods(
    gt_mesh: trimesh.Trimesh,
    method_meshes: Mapping[str, trimesh.Trimesh],
    camera: Camera,
    poses: np.ndarray,
    box: RoiBox,
    step: int,
    cfg: SurfaceMetricConfig = SurfaceMetricConfig(),  # noqa: B008 - frozen, immutable
    change_masks: Mapping[str, ChangeMaskInput] | None = None,
    pixel_mask: np.ndarray | None = None,
    removals: Mapping[str, RemovalScores] | None = None,
) -> dict[str, Any]:
    """Evaluate every method's mesh against the step's GT mesh; returns a step dict.

    poses : (N, 4, 4) float64 evaluation ``T_world_from_cam`` viewing the box.
    pixel_mask : (H, W) bool or None; False pixels never count in the correspondence error.
    removals : name -> removed-tissue scores (:mod:`chisel.eval.volume`), or None.
    Returns ``{"step", "label", "methods": {name: cell}}`` (cells as in ``metrics.json``).
    """
    if not method_meshes:
        raise InvalidInputError("method_meshes", "no method to evaluate")
    if step < 0:
        raise InvalidInputError("step", f"must be >= 0, got {step}")
    unknown = set(change_masks or {}) - set(method_meshes)
    if unknown:
        raise InvalidInputError(
            "change_masks", f"masks given for methods without a mesh: {sorted(unknown)}"
        )
    _check_mesh(gt_mesh, "gt_mesh")
    poses = _check_poses(poses)
    gt_depths = render_depths(gt_mesh, camera, poses)
    gt_samples = sample_surface_in_box(gt_mesh, box, cfg.n_samples, cfg.seed, "gt_mesh")
    methods: dict[str, Any] = {}
    for name, mesh in method_meshes.items():
        _check_mesh(mesh, f"method {name!r}")
        corr = correspondence_error(
            gt_depths,
            render_depths(mesh, camera, poses),
            camera,
            poses,
            box,
            pixel_mask,
            source=f"method {name!r}",
        )
        surf = surface_metrics(mesh, gt_mesh, box, cfg, gt_samples, source=f"method {name!r}")
        masks = None
        if change_masks and name in change_masks:
            cm = change_masks[name]
            masks = mask_precision_recall(cm.pred_masks, cm.true_masks, cm.valid)
        methods[name] = method_cell(corr, surf, masks, (removals or {}).get(name))
        log.info(
            "step %d %s: %.3f +- %.3f mm (n=%d), chamfer %.3f mm",
            step,
            name,
            corr.mean_mm,
            corr.std_mm,
            corr.n_points,
            surf.chamfer_mm,
        )
    return {"step": int(step), "label": step_label(step), "methods": methods}


def protocol_dict(
    box: RoiBox, cfg: SurfaceMetricConfig, n_poses: int, pose_source: str
) -> dict[str, Any]:
    """What a step was evaluated with (stored beside the numbers)."""
    return {
        "roi_box_mm": box.to_list(),
        "n_eval_poses": int(n_poses),
        "eval_poses": pose_source,
        "surface_samples": int(cfg.n_samples),
        "surface_seed": int(cfg.seed),
        "fscore_threshold_mm": FSCORE_THRESHOLD_MM,
        "change_threshold_mm": CHANGE_THRESHOLD_MM,
        "std": "population (ddof=0)",
    }


# --------------------------------------------------------------------------------------
# File-level wrapper


def load_mesh(path: str | Path, source: str) -> trimesh.Trimesh:
    """Read a triangle mesh (PLY/STL/OBJ) through the one mesh reader; ``source`` names
    its role ("gt", "preop") in the errors."""
    return read_mesh_file(path, f"{source} mesh")


def _frame_index(path: Path, raw: np.ndarray, n: int, n_frames: int) -> np.ndarray:
    """A mask file's ``frame_index``: ``n`` distinct integer indices in ``0..n_frames-1``
    (strings or floats are refused, not converted or truncated)."""
    if raw.dtype.kind not in "iu" or raw.shape != (n,):
        raise InvalidInputError(
            path,
            f"frame_index must be {n} integer-typed frame indices, shape ({n},), got "
            f"{raw.dtype} {raw.shape}",
        )
    if raw.size and (raw.min() < 0 or raw.max() >= n_frames):
        raise InvalidInputError(
            path,
            f"frame_index must hold non-negative indices in 0..{n_frames - 1} (the change "
            f"sequence's frames), got {raw.min()}..{raw.max()}",
        )
    idx = raw.astype(np.int64)
    values, counts = np.unique(idx, return_counts=True)
    if (counts > 1).any():
        raise InvalidInputError(
            path, f"frame_index names frame {int(values[counts > 1][0])} more than once"
        )
    return idx


def load_change_masks(path: str | Path, n_frames: int, shape: tuple[int, int]) -> np.ndarray:
    """Read predicted change masks: an ``.npz`` with key ``masks`` or a folder of PNGs.

    npz: ``masks`` (N, H, W) bool or uint8 (nonzero = changed), read without pickle; with
    an optional ``frame_index`` (N,) int (as ``chisel update --masks`` writes), the masks are
    placed at those frames of the sequence and the other frames count as unchanged.
    Folder: ``000000.png`` ... one uint8 PNG per frame, 255 = changed.
    Returns (N, H, W) bool, checked against ``n_frames`` and ``shape`` = (H, W).
    """
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.png"))
        if not files:
            raise InvalidInputError(path, "change-mask folder holds no PNG file")
        masks = []
        for f in files:
            img = decode_image(f, cv2.IMREAD_GRAYSCALE, "change-mask PNG")
            masks.append(img > 127)
        arr = np.stack(masks) if len({m.shape for m in masks}) == 1 else None
        if arr is None:
            raise InvalidInputError(path, "change-mask PNGs differ in size")
    elif path.is_file():
        z = read_npz(path, "change masks")
        if "masks" not in z:
            raise InvalidInputError(path, f"expected key 'masks', found {sorted(z)}")
        arr = _check_masks(z["masks"], f"{path}: masks")
        if "frame_index" in z:
            # `chisel update --masks` stores one mask per frame it considered, with the
            # frame's index; frames it did not consider count as "no change".
            idx = _frame_index(path, z["frame_index"], len(arr), n_frames)
            full = np.zeros((n_frames, *arr.shape[1:]), dtype=bool)
            full[idx] = arr
            arr = full
    else:
        raise InvalidInputError(path, "change masks are missing (expected an .npz or a folder)")
    if arr.shape != (n_frames, *shape):
        raise InvalidInputError(
            path,
            f"expected {n_frames} masks of {shape[1]}x{shape[0]} (WxH), got shape {arr.shape}",
        )
    return arr


def load_mask_poses(path: str | Path, sequence_poses: np.ndarray) -> np.ndarray:
    """The pose each predicted mask's pixels belong to: (N, 4, 4) ``T_world_from_cam``.

    A method's change mask lives in the image of the pose it rendered its model at, its
    tracked pose (the paper registers the estimate to the render and re-projects it into
    that image). ``chisel update --masks`` stores those poses (key ``T_world_from_cam``,
    at ``frame_index``); any other masks are taken at ``sequence_poses`` (the update
    sequence's tracked poses, ``poses.txt``).
    """
    poses = np.array(sequence_poses, dtype=np.float64, copy=True)
    path = Path(path)
    if not path.is_file():
        return poses
    z = read_npz(path, "change masks")
    if "T_world_from_cam" not in z:
        return poses
    given = z["T_world_from_cam"]
    if given.dtype.kind not in "iuf":
        raise InvalidInputError(
            path, f"T_world_from_cam must be numbers (N, 4, 4), got dtype {given.dtype}"
        )
    if given.ndim != 3 or given.shape[1:] != (4, 4):
        raise InvalidInputError(
            path, f"T_world_from_cam must be (N, 4, 4) poses, got shape {given.shape}"
        )
    given = given.astype(np.float64)
    idx = (
        _frame_index(path, z["frame_index"], len(given), len(poses))
        if "frame_index" in z
        else np.arange(len(poses))
    )
    if len(given) != len(idx):
        raise InvalidInputError(
            path, f"T_world_from_cam must hold {len(idx)} poses (N, 4, 4), got {given.shape}"
        )
    poses[idx] = _check_poses(given, f"{path}: T_world_from_cam")
    return poses


def load_start_surface(path: str | Path, source: str) -> trimesh.Trimesh:
    """The surface a method's step started from: a model (``.npz``, its surface extracted
    as the updater renders it) or a mesh file."""
    if Path(path).suffix.lower() == ".npz":
        from chisel.mesh import extract_mesh
        from chisel.model import TsdfModel

        return extract_mesh(TsdfModel.load(path), with_color=False)
    return load_mesh(path, source)


def _mask_inputs(
    change_mask_paths: Mapping[str, str | Path],
    start_surface_paths: Mapping[str, str | Path],
    change_sequence_path: str | Path,
    gt_mesh: trimesh.Trimesh,
    method_names: set[str],
) -> dict[str, ChangeMaskInput]:
    """Each method's predicted masks and the change they should have found.

    The truth is what the method's model was missing when the step began: the step's GT
    surface lies more than 1 mm beyond the model's surface along the mask's own rays (the
    pose the mask was made at, :func:`load_mask_poses`). Scored at the true poses instead,
    a perfect detector would lose every pixel its tracking error shifts; scored against
    the previous GT step, it would be penalised for finding what an earlier step missed.
    """
    cseq = SequenceFolder(change_sequence_path)
    camera = cseq.camera
    gt_cache: dict[bytes, np.ndarray] = {}
    starts: dict[str, trimesh.Trimesh] = {}  # at step 1 every method starts from one model
    start_depths: dict[tuple[str, bytes], np.ndarray] = {}  # ... and its masks share poses
    out: dict[str, ChangeMaskInput] = {}
    for name, p in change_mask_paths.items():
        if name not in method_names:
            raise InvalidInputError("change_mask_paths", f"masks for {name!r}, which has no mesh")
        if name not in start_surface_paths:
            raise InvalidInputError(
                "start_surface_paths",
                f"{name!r} has change masks but no start surface (the model its step began "
                "from, .npz, or a mesh)",
            )
        pred = load_change_masks(p, len(cseq), camera.shape)
        poses = load_mask_poses(p, cseq.poses)
        key = poses.tobytes()
        if key not in gt_cache:
            gt_cache[key] = render_depths(gt_mesh, camera, poses)
        start_path = str(start_surface_paths[name])
        if start_path not in starts:
            starts[start_path] = load_start_surface(start_path, f"start surface of {name!r}")
        if (start_path, key) not in start_depths:
            start_depths[start_path, key] = render_depths(starts[start_path], camera, poses)
        truth = true_change_masks_from_depths(start_depths[start_path, key], gt_cache[key])
        out[name] = ChangeMaskInput(pred, truth, cseq.camera_mask)
    return out


def _eval_poses(seq: SequenceFolder) -> tuple[np.ndarray, str]:
    # The protocol fixes exact camera poses: use the true ones when the sequence has them.
    if seq.true_poses is not None:
        return seq.true_poses, "poses_true.txt"
    log.info("%s has no true poses; evaluating at its tracked poses", seq.path)
    return seq.poses, "poses.txt"


def _removals(
    model_paths: Mapping[str, str | Path],
    preop_model_path: str | Path | Mapping[str, str | Path] | None,
    ct_label_paths: tuple[str | Path, str | Path] | None,
) -> dict[str, RemovalScores]:
    """Removed-tissue scores per method from files (see :mod:`chisel.eval.volume`).

    preop_model_path : the preoperative model every method started from, or one per method
    (the sweep-only build has its own grid)."""
    from chisel.io.ct import read_ct_volume
    from chisel.model import TsdfModel

    if preop_model_path is None or ct_label_paths is None:
        raise InvalidInputError(
            "removal_model_paths", "volumetric scores need preop_model_path and ct_label_paths"
        )
    pre_ct = read_ct_volume(ct_label_paths[0], "label")
    now_ct = read_ct_volume(ct_label_paths[1], "label")
    if not np.allclose(pre_ct.T_world_from_voxel, now_ct.T_world_from_voxel):
        raise InvalidInputError(ct_label_paths[1], "not on the preop label CT's grid")
    starts = (
        {name: preop_model_path[name] for name in model_paths}
        if isinstance(preop_model_path, Mapping)
        else dict.fromkeys(model_paths, preop_model_path)
    )
    cache: dict[str, tuple[TsdfModel, np.ndarray]] = {}
    out = {}
    for name, path in model_paths.items():
        key = str(starts[name])
        if key not in cache:
            preop = TsdfModel.load(starts[name])
            truth = true_removal(pre_ct.data, now_ct.data, pre_ct.T_world_from_voxel, preop)
            cache[key] = (preop, truth)
        preop, truth = cache[key]
        removed = model_removal(preop, TsdfModel.load(path))
        out[name] = removal_scores(removed, truth, preop.voxel_size_mm)
    return out


def evaluate_step(
    gt_mesh_path: str | Path,
    method_mesh_paths: Mapping[str, str | Path],
    eval_sequence_path: str | Path,
    roi_box_mm: RoiBox | Sequence[float],
    step: int,
    cfg: SurfaceMetricConfig = SurfaceMetricConfig(),  # noqa: B008 - frozen, immutable
    change_mask_paths: Mapping[str, str | Path] | None = None,
    change_sequence_path: str | Path | None = None,
    start_surface_paths: Mapping[str, str | Path] | None = None,
    removal_model_paths: Mapping[str, str | Path] | None = None,
    preop_model_path: str | Path | Mapping[str, str | Path] | None = None,
    ct_label_paths: tuple[str | Path, str | Path] | None = None,
) -> dict[str, Any]:
    """Evaluate one step from files; returns the step-metrics dict (see ``STEP_METRICS_SCHEMA``).

    gt_mesh_path : the step's ground-truth mesh.  method_mesh_paths : name -> mesh file.
    eval_sequence_path : sequence folder whose camera and poses are the evaluation poses
    (true poses when present); its camera mask, if any, limits the counted pixels.
    roi_box_mm : the ROI box, or six numbers xmin, ymin, zmin, xmax, ymax, zmax (mm).
    change_mask_paths : name -> predicted change masks (see :func:`load_change_masks`) of the
    step's update sequence ``change_sequence_path``; scored against what the method's
    model lacked: ``gt_mesh_path`` more than 1 mm beyond ``start_surface_paths[name]`` (the
    model, .npz, or mesh the method's step began from) at the masks' own poses
    (:func:`_mask_inputs`).
    removal_model_paths : name -> the method's model file (.npz) at this step; with
    ``preop_model_path`` (one file, or name -> the method's own preoperative model) and
    ``ct_label_paths`` (preop label CT, this step's label CT) the removed-tissue Dice and
    HD95 are scored (:mod:`chisel.eval.volume`).
    """
    box = roi_box_mm if isinstance(roi_box_mm, RoiBox) else RoiBox.from_values(roi_box_mm)
    if not method_mesh_paths:
        raise InvalidInputError("method_mesh_paths", "no method to evaluate")
    gt_mesh = load_mesh(gt_mesh_path, "ground-truth mesh")
    meshes = {name: load_mesh(p, f"method {name!r}") for name, p in method_mesh_paths.items()}
    seq = SequenceFolder(eval_sequence_path)
    poses, pose_source = _eval_poses(seq)

    change_inputs: dict[str, ChangeMaskInput] | None = None
    if change_mask_paths:
        if change_sequence_path is None or start_surface_paths is None:
            raise InvalidInputError(
                "change_mask_paths",
                "scoring change masks needs change_sequence_path and start_surface_paths",
            )
        change_inputs = _mask_inputs(
            change_mask_paths, start_surface_paths, change_sequence_path, gt_mesh, set(meshes)
        )

    removals = None
    if removal_model_paths:
        removals = _removals(removal_model_paths, preop_model_path, ct_label_paths)
    result = evaluate_methods(
        gt_mesh, meshes, seq.camera, poses, box, step, cfg, change_inputs, seq.camera_mask,
        removals,
    )  # fmt: skip
    return {
        "format": STEP_METRICS_FORMAT,
        "version": METRICS_VERSION,
        **result,
        "protocol": protocol_dict(box, cfg, len(poses), f"{seq.path}/{pose_source}"),
    }


# --------------------------------------------------------------------------------------
# Tables: assemble, validate, write
