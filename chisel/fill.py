"""Which pixels of a step may fill a model's never-observed voxels (batch mode).

A model built from the preoperative sweep alone (the paper's build) has voxels that no
frame ever observed. ``UpdateConfig.fill_unseen`` fuses a frame's estimate into them where
the model shows no surface at all, with no check: one view is all there is of a hole. A
never-observed voxel can also lie next to a surface the model shows (the side of a hole
seen through its rim, tissue behind a lamella's edge), and there a single view's estimate
is not enough: a frame of garbage depth would write surfaces into every unobserved voxel
it reaches. ``UpdateConfig.fill_confirmed`` lets a pixel fill there only when other
frames of the step put the same surface point where it does, as the change mask's
multi-view check does for removal (:func:`chisel.change.multiview_support`). A changed
pixel is held to the same rule: deletion first keeps the surface the model holds behind
the removed layer and fuses nothing, but in a sweep-built model the free space behind a
lamella often ends in voxels no frame observed, and there the estimate is all there is.
"""

from __future__ import annotations

from dataclasses import replace
from typing import cast

import cv2
import numba
import numpy as np

from chisel.change import _apply, _project_into
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, invert_rigid
from chisel.detect import Detection, stack_maps, stack_poses
from chisel.model import TsdfModel
from chisel.update_config import UpdateConfig


@numba.njit(parallel=True, cache=True, nogil=True)
def _near_unobserved_kernel(depth, rays, T_vc, weight, band, step, out):  # fmt: skip
    H, W = depth.shape
    nx, ny, nz = weight.shape
    n_s = int(np.floor(2.0 * band / step)) + 1
    for v in numba.prange(H):
        for u in range(W):
            d = depth[v, u]
            if not (d > 0.0):
                continue
            for s in range(n_s):
                z = d - band + s * step
                if z <= 1e-3:
                    continue
                x = rays[v, u, 0] * z
                y = rays[v, u, 1] * z
                zz = rays[v, u, 2] * z
                a, b, c = _apply(T_vc, 0, x, y, zz)
                ia = int(np.floor(a + 0.5))
                ib = int(np.floor(b + 0.5))
                ic = int(np.floor(c + 0.5))
                if ia < 0 or ib < 0 or ic < 0 or ia >= nx or ib >= ny or ic >= nz:
                    continue
                if weight[ia, ib, ic] <= 0.0:
                    out[v, u] = True
                    break


def near_unobserved(
    model: TsdfModel, camera: Camera, T_world_from_cam: np.ndarray, depth_mm: np.ndarray
) -> np.ndarray:
    """(H, W) bool: pixels whose depth has a voxel the model never observed (weight 0)
    within two voxels in front of or behind it along the ray.

    depth_mm : (H, W) float32 z-depth, NaN or <= 0 = none. The voxels next to a surface
    are those that place it (the zero crossing); farther from it, a voxel that the sweep
    missed at the edge of its truncation band changes no surface. Points outside the grid
    count as observed: nothing can be written there.
    """
    d = np.asarray(depth_mm, dtype=np.float32)
    if d.shape != camera.shape:
        raise InvalidInputError("depth_mm", f"shape {d.shape} is not the camera's {camera.shape}")
    # Camera mm -> voxel index (T_world_from_voxel scales by the voxel size: not rigid).
    T_vc = np.linalg.inv(model.T_world_from_voxel) @ np.asarray(T_world_from_cam, np.float64)
    T_vc = np.ascontiguousarray(T_vc[None])  # a stack of one, for the shared transform
    out = np.zeros(camera.shape, dtype=np.bool_)
    _near_unobserved_kernel(
        np.nan_to_num(d, nan=0.0), np.ascontiguousarray(camera.rays_cam()), T_vc,
        model.weight, min(2.0 * model.voxel_size_mm, float(model.trunc_mm)),
        0.5 * float(model.voxel_size_mm), out,
    )  # fmt: skip
    return out


def depth_edges(depth_mm: np.ndarray, jump_mm: float) -> np.ndarray:
    """(H, W) bool: pixels without depth, next to one, or whose 3 x 3 neighbourhood spans
    more than ``jump_mm`` of depth (a silhouette).

    Projective fusion places a voxel beside a silhouette on the edge pixel's depth and so
    widens the near surface into the background by up to a pixel's footprint; where the
    model holds nothing to correct it, that stays.
    """
    d = np.asarray(depth_mm, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    k = np.ones((3, 3), np.uint8)
    hi = cv2.dilate(np.where(valid, d, 0.0).astype(np.float32), k)
    lo = cv2.erode(np.where(valid, d, np.inf).astype(np.float32), k)
    near_invalid = cv2.dilate((~valid).astype(np.uint8), k) > 0
    with np.errstate(invalid="ignore"):
        return near_invalid | ~(hi - lo <= jump_mm)


@numba.njit(parallel=True, cache=True, nogil=True)
def _agreement_kernel(cands, ests, rays, T_wc, T_cw, used, occluded, fx, fy, cx, cy, dist,
                      tol_mm, support, observed):  # fmt: skip
    N, H, W = cands.shape
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for i in numba.prange(N):
        if not used[i]:
            continue
        for v in range(H):
            for u in range(W):
                if not cands[i, v, u]:
                    continue
                e = ests[i, v, u]
                # The surface point this pixel's estimate puts in the world, mm.
                x = rays[v, u, 0] * e
                y = rays[v, u, 1] * e
                z = rays[v, u, 2] * e
                X, Y, Z = _apply(T_wc, i, x, y, z)
                n_sup = 0
                n_obs = 0
                for j in range(N):
                    if j == i or not used[j] or (occluded[i] and occluded[j]):
                        continue
                    uu, vv, zc = _project_into(
                        T_cw, j, X, Y, Z, fx, fy, cx, cy, k1, k2, p1, p2, k3, W, H
                    )
                    if uu < 0:
                        continue
                    ej = ests[j, vv, uu]
                    # No estimate there, or something in front of the point: frame j
                    # cannot say where the point's surface is.
                    if not (ej == ej) or ej < zc - tol_mm:
                        continue
                    n_obs += 1
                    # Within the tolerance it puts the surface there too; farther, it sees
                    # through the point (the point lies in its free space).
                    if ej <= zc + tol_mm:
                        n_sup += 1
                support[i, v, u] = n_sup
                observed[i, v, u] = n_obs


def estimate_support(
    candidates: np.ndarray,
    estimates_mm: np.ndarray,
    camera: Camera,
    T_world_from_cams: np.ndarray,
    used: np.ndarray,
    tol_mm: float,
    occluded: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """How many other frames put each candidate pixel's surface point where it does:
    (support, observed), (N, H, W) int32, 0 where not a candidate.

    candidates : (N, H, W) bool; estimates_mm : (N, H, W) float32 z-depth in each frame's
    pose, NaN = none; T_world_from_cams : (N, 4, 4); used : (N,) bool (the others neither
    vote nor count). A candidate's point is projected into every other used frame j; j
    *observes* it when its estimate there is valid and not nearer than the point by more
    than ``tol_mm`` (not occluded), and *supports* it when its estimate lies within
    ``tol_mm`` of the point's depth; deeper, it contradicts it (sees through it).
    occluded : (N,) bool or None; two occluded frames (:func:`occluded_frames`) neither
    support nor observe each other's points.
    """
    c = np.ascontiguousarray(candidates, dtype=np.bool_)
    N = len(c)
    e = np.ascontiguousarray(estimates_mm, dtype=np.float32)
    if e.shape != c.shape:
        raise InvalidInputError("estimates_mm", f"shape {e.shape} differs from {c.shape}")
    if c.shape[1:] != camera.shape:
        raise InvalidInputError("candidates", f"shape {c.shape[1:]} is not {camera.shape}")
    P = np.ascontiguousarray(T_world_from_cams, dtype=np.float64)
    if P.shape != (N, 4, 4) or np.shape(used) != (N,):
        raise InvalidInputError("T_world_from_cams", f"expected ({N}, 4, 4) poses and ({N},) used")
    if not (np.isfinite(tol_mm) and tol_mm > 0):
        raise InvalidInputError("tol_mm", f"must be > 0 mm, got {tol_mm}")
    occ = np.zeros(N, dtype=np.bool_) if occluded is None else np.asarray(occluded, np.bool_)
    if occ.shape != (N,):
        raise InvalidInputError("occluded", f"expected ({N},) bool, got shape {occ.shape}")
    c = c & (e > 0)  # a candidate needs a depth of its own (the caller's array is kept)
    support = np.zeros(c.shape, dtype=np.int32)
    observed = np.zeros(c.shape, dtype=np.int32)
    T_cw = np.ascontiguousarray(np.stack([invert_rigid(T) for T in P])) if N else P
    _agreement_kernel(
        c, e, np.ascontiguousarray(camera.rays_cam()), P, T_cw,
        np.ascontiguousarray(used, dtype=np.bool_), np.ascontiguousarray(occ), camera.fx,
        camera.fy, camera.cx, camera.cy,
        np.ascontiguousarray(camera.dist, dtype=np.float64), float(tol_mm), support, observed,
    )  # fmt: skip
    return support, observed


OCCLUDED_FRACTION = 0.02
"""A frame is occluded when its mask hides the model's surface over more than this
fraction of the pixels that most of the step's frames keep (:func:`occluded_frames`). On
the tools variant's renders a frame with an instrument hides a median 6-7 % of the view
this way; a tool-free frame at most 1.1 % (seeds 0-4 and 8-12: rays that leave the
phantom, masked by the simulator, where the model mostly shows nothing either)."""


def occluded_frames(masks: list[np.ndarray | None], renders_mm: np.ndarray) -> np.ndarray:
    """(N,) bool: the frames whose mask hides tissue that the step's other frames see.

    masks : per frame (H, W) bool, True = use the pixel (the sequence's mask and field
    stop), or None = every pixel. renders_mm : (N, H, W) float32 the model at each frame's
    pose, NaN = no surface. A pixel that at least half of the frames keep belongs to the
    view; a frame whose mask hides the model's surface over more than
    ``OCCLUDED_FRACTION`` of the view has something in front of the tissue, an
    instrument, say. A mask that every frame shares (the field stop) hides nothing of the
    view, and a masked pixel where the model shows no surface (a ray that meets no
    tissue) is no occluder.
    """
    n = len(masks)
    r = np.asarray(renders_mm)
    if r.ndim != 3 or len(r) != n:
        raise InvalidInputError("renders_mm", f"expected {n} renders (N, H, W), got {r.shape}")
    if all(m is None for m in masks):
        return np.zeros(n, dtype=bool)
    keep = np.stack(
        [np.ones(r.shape[1:], bool) if m is None else np.asarray(m, bool) for m in masks]
    )
    view = keep.mean(axis=0) >= 0.5
    hidden = (view[None] & ~keep & np.isfinite(r)).reshape(n, -1).sum(axis=1)
    return hidden > OCCLUDED_FRACTION * max(int(view.sum()), 1)


def confirm_fill(
    dets: list[Detection],
    model: TsdfModel,
    camera: Camera,
    cfg: UpdateConfig,
    masks: list[np.ndarray | None] | None = None,
) -> list[Detection]:
    """The step's detections with ``fill`` set: the pixels whose estimate may fill the
    voxels ``model`` (M_t) never observed, confirmed by other frames.

    A pixel, changed or not, fills when its estimate has a never-observed voxel within two
    voxels (:func:`near_unobserved`), is not on a silhouette (:func:`depth_edges`, a jump
    of the truncation distance), and at least ``cfg.change.min_views`` other frames, and
    at least ``cfg.change.min_agreement`` of those that observe its point, put the surface
    within the truncation distance of it (:func:`estimate_support`): what the TSDF would
    average into one surface. Two frames that both show an occluder (their ``masks``, the
    frames' own, hide tissue: :func:`occluded_frames`) do not count for each other: a
    network's depth is distorted across the whole frame when an instrument is in view,
    alike in the frames of one tool episode, so their agreement is not independent
    evidence (docs/updater.md, "Frames with an instrument in view"). Sweep-built models
    only: a whole-CT model's never-observed voxels lie outside the CT
    (``UpdateConfig.fill_confirmed``); its detections are returned as they are.
    """
    if model.build != "sweep":
        return list(dets)
    used = np.array([d.used for d in dets], dtype=bool)
    shape = camera.shape
    cands = np.zeros((len(dets), *shape), dtype=bool)
    for i, d in enumerate(dets):
        if d.used:
            # A used detection has its maps (chisel.detect.detect).
            m_raw = cast(np.ndarray, d.m_raw)
            cands[i] = ~depth_edges(m_raw, model.trunc_mm) & near_unobserved(
                model, camera, cast(np.ndarray, d.T_world_from_cam), m_raw
            )
    if used.sum() < 2 or not cands.any():
        return list(dets)
    ests, poses = stack_maps(dets, "m_raw", shape), stack_poses(dets)
    occluded = None if masks is None else occluded_frames(masks, stack_maps(dets, "m_t", shape))
    support, observed = estimate_support(cands, ests, camera, poses, used, model.trunc_mm, occluded)
    views, agreement = cfg.change.min_views, cfg.change.min_agreement
    keep = cands & (support >= max(views, 1)) & (support >= agreement * observed)
    return [replace(d, fill=k) if d.used else d for d, k in zip(dets, keep, strict=True)]
