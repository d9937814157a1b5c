"""The updated CT: the preoperative CT with the tissue the model removed set to air.

A navigation system and 3D Slicer show a CT, not a TSDF. :func:`updated_ct` is a pure
function of (CT volume, model); the file I/O lives in ``chisel export-ct``
(:mod:`chisel.cli.cmd_ct`) and in :mod:`chisel.io.ct`.

*Removed* = CT voxels that are tissue in the CT (label > 0, or HU above the -480 HU
iso-level) and observed free space in the model (its signed distance at the voxel centre
> 0, trilinear, with weight > 0). The model may have been built from the CT or from a
preoperative sweep; either way it is sampled at the CT's voxel centres, so the result is
on the CT's own grid with its header and orientation.

Given the *preoperative* model the update started from, a voxel counts as removed only
where that model did not already hold observed free space: what the update carved, not
what the preoperative model could not represent. Without it, CT tissue thinner than the
model's voxels (partial-volume voxels just above -480 HU on the thin sinus bone, which a
1 mm model sampled half a voxel off the CT's grid reads as air) would be set to air
everywhere the model is observed: the smoke phantom's preop model alone "removed" 122
such voxels.

* label CT: removed voxels take the air label (0);
* intensity CT: a partial-volume ramp one voxel wide across the new boundary, from the
  model's signed distance d (mm) and the CT's voxel size s (mm):
  ``f = clip(0.5 - d / s, 0, 1)``, ``HU = air + (HU_ct - air) * f`` on removed voxels
  (f < 0.5: they read as air) and on the CT tissue voxels that touch them (a face
  neighbour; 0.5 <= f <= 1), never raising a value. Far from the new boundary removed
  voxels are exactly air (-1000 HU).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from chisel.core.errors import InvalidInputError
from chisel.io.ct import DEFAULT_HU_ISO, CtVolume
from chisel.model import TsdfModel

AIR_HU = -1000.0
AIR_LABEL = 0
OUTSIDE_TISSUE_FRACTION = 0.01
"""Largest fraction of the model's observed tissue voxels allowed outside the CT (beyond
a truncation band) before the CT is said not to cover the model."""


@dataclass(frozen=True, eq=False)
class UpdatedCt:
    """volume : the updated CT (same grid, header, kind, dtype as the input).
    removed : (X, Y, Z) bool on the CT's grid, the voxels set to air."""

    volume: CtVolume
    removed: np.ndarray


def _world_box(T: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """AABB of a grid's voxel *extent* (centres +- half a voxel) in world mm."""
    corners = np.array(
        [
            [i, j, k]
            for i in (-0.5, shape[0] - 0.5)
            for j in (-0.5, shape[1] - 0.5)
            for k in (-0.5, shape[2] - 0.5)
        ]
    )
    w = corners @ T[:3, :3].T + T[:3, 3]
    return w.min(axis=0), w.max(axis=0)


def _ct_tissue(ct: CtVolume, data: np.ndarray) -> np.ndarray:
    if ct.kind == "label":
        return data > 0
    return data > DEFAULT_HU_ISO


def check_coverage(
    ct: CtVolume,
    model: TsdfModel,
    model_source: str = "model",
    tissue_model: TsdfModel | None = None,
) -> None:
    """Refuse a model whose grid does not overlap the CT (built on another CT) and a CT
    that does not cover the model: more than 1 % of the observed tissue voxels of
    ``tissue_model`` (default: ``model``) lie outside the CT's voxels by more than the
    truncation plus a voxel."""
    ct_lo, ct_hi = _world_box(ct.T_world_from_voxel, ct.shape)
    m_lo, m_hi = _world_box(model.T_world_from_voxel, model.shape)
    if np.any(m_hi <= ct_lo) or np.any(m_lo >= ct_hi):
        raise InvalidInputError(
            model_source,
            f"the model's grid (world box {np.round(m_lo, 1).tolist()}..{np.round(m_hi, 1).tolist()}"
            f" mm) does not overlap the CT {ct.source or ''} (box {np.round(ct_lo, 1).tolist()}.."
            f"{np.round(ct_hi, 1).tolist()} mm): a model built on another CT?",
        )
    m = model if tissue_model is None else tissue_model
    tissue = np.argwhere((m.tsdf < 0) & (m.weight > 0))
    if len(tissue) == 0:
        return
    world = tissue @ m.T_world_from_voxel[:3, :3].T + m.T_world_from_voxel[:3, 3]
    T_inv = np.linalg.inv(ct.T_world_from_voxel)
    idx = world @ T_inv[:3, :3].T + T_inv[:3, 3]
    tol = (m.trunc_mm + m.voxel_size_mm) / ct.spacing_mm
    outside = np.any((idx < -0.5 - tol) | (idx > np.array(ct.shape) - 0.5 + tol), axis=1)
    frac = float(outside.mean())
    if frac > OUTSIDE_TISSUE_FRACTION:
        whose = "model's" if tissue_model is None else "preoperative model's"
        raise InvalidInputError(
            ct.source or "CT",
            f"the CT does not cover the model's grid: {100 * frac:.1f} % of the {whose} "
            f"observed tissue ({int(outside.sum())} voxels) lies outside the CT's voxels "
            f"(CT box {np.round(ct_lo, 1).tolist()}..{np.round(ct_hi, 1).tolist()} mm)",
        )


def _sample_model(model: TsdfModel, ijk_ct: np.ndarray, T_model_from_ct: np.ndarray):
    """Model signed distance (mm) and observation at CT voxel indices (N, 3).

    Returns (d_mm (N,) float32, observed (N,) bool): trilinear where all eight corners are
    observed, else the nearest voxel's value; observed = the nearest voxel has weight > 0.
    """
    q = (ijk_ct @ T_model_from_ct[:3, :3].T + T_model_from_ct[:3, 3]).T  # (3, N) model idx
    obs = model.weight > 0
    near_obs = ndimage.map_coordinates(obs.astype(np.uint8), q, order=0, mode="constant") > 0
    all_obs = ndimage.map_coordinates(obs.astype(np.float32), q, order=1, mode="constant") > 0.999
    lin = ndimage.map_coordinates(model.tsdf, q, order=1, mode="nearest")
    near = ndimage.map_coordinates(model.tsdf, q, order=0, mode="nearest")
    d = np.where(all_obs, lin, near).astype(np.float32) * np.float32(model.trunc_mm)
    return d, near_obs


def updated_ct(
    ct: CtVolume,
    model: TsdfModel,
    model_source: str = "model",
    air_hu: float = AIR_HU,
    air_label: int = AIR_LABEL,
    preop: TsdfModel | None = None,
) -> UpdatedCt:
    """The CT with the tissue the model removed set to air (see the module docstring).

    ct : the preoperative CT (:func:`chisel.io.ct.read_ct_volume`), any orientation.
    model : the updated TSDF model, world mm (same LPS world as the CT).
    model_source : the model's file name, for error messages.
    preop : the preoperative model the update started from (any grid); when given, voxels
        that it already held as observed free space are never removed.
    Raises :class:`InvalidInputError` (naming the file) when the model's grid does not
    overlap the CT or the CT does not cover the model (:func:`check_coverage`): given the
    preoperative model, the CT must cover *its* tissue. What ties a model to its CT is the
    tissue it started from; an update may fuse tissue beyond the CT's box, which the
    endoscope sees past (a sweep-only model's hole filling put 1.1 % of its tissue there,
    docs/results.md, twenty-seventh session).
    """
    check_coverage(ct, model, model_source, tissue_model=preop)
    data = ct.data
    T_model_from_ct = np.linalg.inv(model.T_world_from_voxel) @ ct.T_world_from_voxel
    # CT index box that the model's grid reaches (+1 voxel for the partial-volume rim)
    m_corners = np.array(
        [
            [i, j, k]
            for i in (-1, model.shape[0])
            for j in (-1, model.shape[1])
            for k in (-1, model.shape[2])
        ],
        dtype=np.float64,
    )
    T_ct_from_model = np.linalg.inv(T_model_from_ct)
    c = m_corners @ T_ct_from_model[:3, :3].T + T_ct_from_model[:3, 3]
    lo = np.clip(np.floor(c.min(axis=0)).astype(int) - 1, 0, ct.shape)
    hi = np.clip(np.ceil(c.max(axis=0)).astype(int) + 2, 0, ct.shape)
    removed = np.zeros(ct.shape, bool)
    out = data.copy()
    if np.any(hi <= lo):
        return UpdatedCt(_like(ct, out), removed)
    sl = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    sub = data[sl]
    grid = (
        np.stack(
            np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi, strict=True)], indexing="ij"),
            axis=-1,
        )
        .reshape(-1, 3)
        .astype(np.float64)
    )
    d_mm, observed = _sample_model(model, grid, T_model_from_ct)
    d_mm = d_mm.reshape(sub.shape)
    observed = observed.reshape(sub.shape)
    tissue = _ct_tissue(ct, sub)
    rem = tissue & observed & (d_mm > 0)
    if preop is not None:
        T_pre_from_ct = np.linalg.inv(preop.T_world_from_voxel) @ ct.T_world_from_voxel
        d_pre, obs_pre = _sample_model(preop, grid, T_pre_from_ct)
        rem &= ~(obs_pre & (d_pre > 0)).reshape(sub.shape)
    removed[sl] = rem
    if ct.kind == "label":
        new = np.where(rem, np.asarray(air_label, dtype=sub.dtype), sub)
    else:
        s = float(ct.spacing_mm.mean())
        f = np.clip(0.5 - d_mm / s, 0.0, 1.0)
        rim = ndimage.binary_dilation(rem) & tissue & observed
        blended = air_hu + (sub.astype(np.float64) - air_hu) * f
        new_f = np.where(rim, np.minimum(blended, sub), sub)
        new = _cast_like(new_f, sub.dtype)
    out[sl] = new
    return UpdatedCt(_like(ct, out), removed)


def _cast_like(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    return values.astype(dtype)


def _like(ct: CtVolume, data: np.ndarray) -> CtVolume:
    return CtVolume(
        data=data,
        T_world_from_voxel=ct.T_world_from_voxel,
        kind=ct.kind,
        source=ct.source,
        file_format=ct.file_format,
        header=ct.header,
    )


def removed_dice(predicted: np.ndarray, truth: np.ndarray) -> float:
    """Dice of two boolean masks on one grid; 1.0 when both are empty."""
    p = np.asarray(predicted, bool)
    t = np.asarray(truth, bool)
    if p.shape != t.shape:
        raise InvalidInputError("removed mask", f"shapes differ: {p.shape} vs {t.shape}")
    total = int(p.sum()) + int(t.sum())
    return 1.0 if total == 0 else 2.0 * int((p & t).sum()) / total


def removed_region_scores(
    before: CtVolume, updated: CtVolume, truth_after: CtVolume
) -> dict[str, float | int]:
    """Updated-CT score of the removed region against the true CT after the step.

    before : the preoperative CT the update started from; updated : its export;
    truth_after : the true CT of the step (label or intensity), all on one grid.
    Removed = tissue before and not tissue after (labels > 0, or HU above -480).
    Returns dice, predicted and true removed voxel counts.
    """
    for vol in (updated, truth_after):
        if vol.shape != before.shape or not np.allclose(
            vol.T_world_from_voxel, before.T_world_from_voxel, atol=1e-4
        ):
            raise InvalidInputError(vol.source or "CT", "not on the preoperative CT's grid")
    t0 = _ct_tissue(before, before.data)
    pred = t0 & ~_ct_tissue(updated, updated.data)
    truth = _ct_tissue(before, before.data) & ~_ct_tissue(truth_after, truth_after.data)
    return {
        "dice": removed_dice(pred, truth),
        "predicted_voxels": int(pred.sum()),
        "true_voxels": int(truth.sum()),
    }
