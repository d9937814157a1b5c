"""Deletion-first carving of a step's change (numba, CPU).

Where a frame shows that tissue is gone, the first layer of tissue along the ray is
deleted up to the next surface the model already holds (the CT holds the cell behind a
lamella), and the new depth is fused only where the model holds nothing behind (the
paper's masked update, :func:`chisel.fusion.integrate`). A ray-centric plan finds, per
changed pixel, the depth intervals of the layers to delete; a voxel-centric pass frees
the voxels whose centres project into them, as fusion decides (see docs/updater.md).
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, check_rigid, invert_rigid
from chisel.fusion import TILE_PX, _camera_tiles, _flat, nearest_pixel
from chisel.model import TsdfModel

CARVE_NONE = 0
"""Pixel status of :func:`carve_first_layer`: not changed, or no surface where M_t says."""
CARVE_DELETED = 1
"""The first layer along the ray was deleted up to a surface the model already holds (or
an earlier frame of the step deleted it): nothing to fuse."""
CARVE_FUSE = 2
"""The model holds nothing behind the first surface within reach of the estimate
(unobserved voxels, or solid tissue beyond the estimate): fuse the new depth there."""

CARVE_RIM = 3
"""Beside a changed pixel, unchanged by the threshold, with a precise estimate: the tissue
the model holds in front of the estimate near its own surface goes (the cut's edge)."""


@numba.njit(inline="always")
def _voxel_at(A, z, rx, ry, nx, ny, nz):
    # Nearest voxel of the camera point (rx z, ry z, z); -1 outside the grid.
    fi = A[0, 0] * rx * z + A[0, 1] * ry * z + A[0, 2] * z + A[0, 3]
    fj = A[1, 0] * rx * z + A[1, 1] * ry * z + A[1, 2] * z + A[1, 3]
    fk = A[2, 0] * rx * z + A[2, 1] * ry * z + A[2, 2] * z + A[2, 3]
    i = int(np.floor(fi + 0.5))
    j = int(np.floor(fj + 0.5))
    k = int(np.floor(fk + 0.5))
    if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
        return -1
    return (i * ny + j) * nz + k


@numba.njit(parallel=True, cache=True, nogil=True)
def _carve_plan(tsdf, weight, shape, A, rays, m_t, m_new, mask, voxel_mm, trunc_mm, tol_mm,
                max_layers, precise, max_layer_mm, max_depth_mm, z0, z1, reach):  # fmt: skip
    # Read-only pass: per changed pixel, its status and the depth intervals [z0, z1) of the
    # layers to delete (up to ``max_layers``). No voxel is written here, so the result does
    # not depend on the order the pixels are visited in. ``precise`` is per pixel.
    # Not ``precise`` (a noisy estimate): one layer at most, deleted only when the estimate
    # lies past the middle of the cavity behind it, no thicker along the ray than
    # ``max_layer_mm``, nothing where the old surface lies deeper than ``max_depth_mm``,
    # and no new surface inside held tissue.
    # ``precise`` and deletion stopped at a surface the model holds (the estimate lies less
    # than the threshold past it, or inside its layer): ``reach`` is where the estimate
    # says that surface now lies, at most ``tol_mm`` behind its front. The walk samples the
    # nearest voxel every half voxel, so without it a cut's rim seen at an angle stays.
    H, W = mask.shape
    nx, ny, nz = shape[0], shape[1], shape[2]
    status = np.zeros((H, W), dtype=np.uint8)
    for v in numba.prange(H):
        for u in range(W):
            if not mask[v, u]:
                continue
            zt = np.float64(m_t[v, u])
            ze = np.float64(m_new[v, u])
            if not (zt > 0.0 and ze > 0.0 and np.isfinite(zt) and np.isfinite(ze)):
                continue
            pr = precise[v, u]
            if not pr and zt > max_depth_mm:
                continue  # too far for a noisy estimate's verdict: left alone
            rx = rays[v, u, 0]
            ry = rays[v, u, 1]
            ray_mm = np.sqrt(rx * rx + ry * ry + rays[v, u, 2] * rays[v, u, 2])
            # Half a voxel of ray length per step, in z units.
            dz = 0.5 * voxel_mm / ray_mm
            # Phase A: the first tissue voxel near the old surface M_t.
            z = zt - voxel_mm
            found = False
            unknown = False
            while z <= zt + trunc_mm:
                idx = _voxel_at(A, z, rx, ry, nx, ny, nz)
                if idx < 0:
                    unknown = True
                    break
                if weight[idx] > 0.0 and tsdf[idx] < 0.0:
                    found = True
                    break
                if weight[idx] <= 0.0 and z > zt:
                    unknown = True
                    break
                z += dz
            if not found:
                # Free all along: an earlier frame of the step deleted it.
                status[v, u] = CARVE_FUSE if unknown else CARVE_DELETED
                continue
            st = CARVE_FUSE
            n = 0
            while n < max_layers:
                start = z
                # Through the tissue layer, to the free space behind it.
                ok = False
                held = True  # the model holds what lies behind the layer's front
                while True:
                    z += dz
                    if z > ze + tol_mm:
                        break  # the estimate ends inside this tissue: new surface there
                    idx = _voxel_at(A, z, rx, ry, nx, ny, nz)
                    if idx < 0 or weight[idx] <= 0.0:
                        # Nothing known behind. Past more held tissue than a truncation
                        # band (a sweep-only model's), it is the CT's solid tissue at the
                        # edge of its grid: still no place for a noisy estimate's cut.
                        held = z - start > trunc_mm + voxel_mm
                        break
                    if tsdf[idx] > 0.0:
                        ok = True
                        break
                # The estimate must see past this layer's back face, not only past its front
                # (the change mask's threshold): a lamella thinner than the threshold, or a
                # pixel the mask's closing added, would otherwise be deleted while the
                # estimate still lies on it.
                if not ok or ze < z + 0.5 * tol_mm:
                    if n == 0 and held and not pr:
                        st = CARVE_NONE  # a noisy estimate cannot place a cut inside tissue
                    if n > 0 and pr:
                        reach[v, u] = min(ze, start + tol_mm)
                    break
                back = z
                if not pr and (back - start) * ray_mm > max_layer_mm:
                    if n == 0:
                        st = CARVE_NONE  # thicker than what surgery takes: the estimate errs
                    break
                # Through the cavity to the next surface the model holds.
                nxt = False
                while True:
                    z += dz
                    idx = _voxel_at(A, z, rx, ry, nx, ny, nz)
                    if idx < 0 or weight[idx] <= 0.0:
                        break
                    if tsdf[idx] < 0.0:
                        nxt = True
                        break
                if nxt and not pr and ze < 0.5 * (start + z):
                    # Nearer the layer's front than the surface its removal would reveal.
                    if n == 0:
                        st = CARVE_NONE
                    break
                z0[v, u, n] = start
                z1[v, u, n] = back
                n += 1
                st = CARVE_DELETED
                if not nxt or z >= ze - tol_mm or not pr:
                    if nxt and pr:
                        reach[v, u] = min(ze, z + tol_mm)
                    break  # the estimate agrees with the next surface: deletion stops here
            status[v, u] = st
    return status


@numba.njit(parallel=True, cache=True, nogil=True)
def _carve_apply(tsdf, weight, reset, use_reset, shape, lo, hi, R, t, fx, fy, cx, cy, dist, r2_max,
                 status, z0, z1, half_voxel_mm, votes, need_votes, precise, reach, reach_free,
                 reach_from, trunc_mm):  # fmt: skip
    # Voxel-centric, like the fusion kernel: a voxel is set free when its centre projects
    # (nearest pixel, lens distortion honoured) to a pixel whose ray deleted a layer and
    # its depth lies in that layer. A ray-centric walk would free every voxel a changed
    # ray merely grazes, eroding the rim of an opening by up to a voxel per view.
    # need_votes > 1: a pixel that is not ``precise`` votes, and the voxel goes at its
    # need_votes-th vote of the step. Behind the last deleted layer, tissue in front of the
    # pixel's ``reach`` (0 = none) takes the projective distance to it when its centre lies
    # in front of ``reach_free`` (see carve_first_layer).
    H, W = status.shape
    ny, nz = shape[1], shape[2]
    k1_, k2_, p1_, p2_, k3_ = dist[0], dist[1], dist[2], dist[3], dist[4]
    distorted = (k1_ != 0.0) or (k2_ != 0.0) or (p1_ != 0.0) or (p2_ != 0.0) or (k3_ != 0.0)
    n_layers = z0.shape[2]
    counts = np.zeros(hi[0] - lo[0], dtype=np.int64)
    for ii in numba.prange(hi[0] - lo[0]):
        i = lo[0] + ii
        n = 0
        for j in range(lo[1], hi[1]):
            for k in range(lo[2], hi[2]):
                zc = R[2, 0] * i + R[2, 1] * j + R[2, 2] * k + t[2]
                if zc <= 1e-3:
                    continue
                xc = (R[0, 0] * i + R[0, 1] * j + R[0, 2] * k + t[0]) / zc
                yc = (R[1, 0] * i + R[1, 1] * j + R[1, 2] * k + t[1]) / zc
                u, v = nearest_pixel(xc, yc, r2_max, distorted, dist, fx, fy, cx, cy, W, H)
                if u < 0 or (status[v, u] != CARVE_DELETED and status[v, u] != CARVE_RIM):
                    continue
                inside = False
                zb_last = 0.0
                for layer in range(n_layers):
                    za = z0[v, u, layer]
                    zb = z1[v, u, layer]
                    if not zb > za:
                        break
                    zb_last = zb
                    if za - half_voxel_mm <= zc < zb:
                        inside = True
                        idx = (i * ny + j) * nz + k
                        if need_votes > 1 and not precise[v, u] and tsdf[idx] < 1.0:
                            if votes[idx] < 255:
                                votes[idx] += 1
                            if votes[idx] < need_votes:
                                break
                        if tsdf[idx] < 1.0:
                            tsdf[idx] = 1.0
                            weight[idx] = 1.0
                            if use_reset:
                                reset[idx] = 1
                            n += 1
                        break
                if not inside and max(zb_last, reach_from[v, u]) <= zc < reach_free[v, u]:
                    idx = (i * ny + j) * nz + k
                    if tsdf[idx] < 0.0:
                        tsdf[idx] = min(1.0, (reach[v, u] - zc) / trunc_mm)
                        weight[idx] = 1.0
                        if use_reset:
                            reset[idx] = 1
                        n += 1
        counts[ii] = n
    return counts.sum()


@numba.njit(cache=True, nogil=True)
def _deleted_voxel_box(shape, rays, T_voxel_from_cam, status, z0, z1, reach, reach_from):
    # Index box [lo, hi) of the voxels that carving can reach: the hull, in voxel
    # coordinates, of each pixel's front (first layer's front, or the edge's reach_from) and
    # back (deepest layer back or reach).
    H, W = status.shape
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    R = T_voxel_from_cam
    for v in range(H):
        for u in range(W):
            if status[v, u] != CARVE_DELETED and status[v, u] != CARVE_RIM:
                continue
            za = z0[v, u, 0] if status[v, u] == CARVE_DELETED else reach_from[v, u]
            zb = z1[v, u, 0]
            for layer in range(1, z1.shape[2]):
                zb = max(zb, z1[v, u, layer])
            zb = max(zb, reach[v, u])
            for z in (za, zb):
                x, y, w = rays[v, u, 0] * z, rays[v, u, 1] * z, rays[v, u, 2] * z
                for a in range(3):
                    p = R[a, 0] * x + R[a, 1] * y + R[a, 2] * w + R[a, 3]
                    lo[a] = min(lo[a], p)
                    hi[a] = max(hi[a], p)
    box = np.zeros((2, 3), dtype=np.int64)
    for a in range(3):
        if lo[a] > hi[a]:
            return box  # nothing deleted: an empty box
        box[0, a] = min(max(int(np.floor(lo[a])) - 1, 0), shape[a])
        box[1, a] = min(max(int(np.ceil(hi[a])) + 2, 0), shape[a])
    return box


def _reach_free(
    reach: np.ndarray, rays: np.ndarray, estimate: np.ndarray, margin_mm: float
) -> np.ndarray:
    """(H, W) z-depth in front of which a voxel the model holds behind the deleted layers is
    set free: ``margin_mm`` from the estimate's surface along its normal. A voxel that near
    the surface is on it (pose jitter and the registration's residual), and seen at a grazing
    angle a lateral error of a tenth of a millimetre is a millimetre of depth; there the
    margin grows as 1 / cos of the incidence and a silhouette (no normal) frees nothing."""
    out = np.zeros(reach.shape)
    rows = np.flatnonzero((reach > 0).any(axis=1))
    cols = np.flatnonzero((reach > 0).any(axis=0))
    if rows.size == 0:
        return out
    # Only the pixels with a reach, and two around them for the central differences.
    H, W = reach.shape
    box = (
        slice(max(rows[0] - 2, 0), min(rows[-1] + 3, H)),
        slice(max(cols[0] - 2, 0), min(cols[-1] + 3, W)),
    )
    q, r, e = reach[box], rays[box], estimate[box]
    if min(q.shape) < 2:
        return out  # no normal from a single row or column
    P = r * np.where(np.isfinite(e), e, np.nan)[..., None]
    n = np.cross(np.gradient(P, axis=1), np.gradient(P, axis=0))
    ray_mm = np.linalg.norm(r, axis=-1)  # ray length per unit of z
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(np.sum(n * r, axis=-1)) / (np.linalg.norm(n, axis=-1) * ray_mm)
        free = q - margin_mm / (cos * ray_mm)
    out[box] = np.where((q > 0) & np.isfinite(free), free, 0.0)
    return out


def carve_first_layer(
    model: TsdfModel,
    camera: Camera,
    T_world_from_cam: np.ndarray,
    m_t: np.ndarray,
    m_new: np.ndarray,
    mask: np.ndarray,
    tol_mm: float,
    reset: np.ndarray | None = None,
    max_layers: int = 4,
    precise: bool | np.ndarray = True,
    votes: np.ndarray | None = None,
    noisy_votes: int = 1,
    noisy_layer_mm: float = np.inf,
    noisy_max_depth_mm: float = np.inf,
    rim_px: int = 0,
) -> tuple[np.ndarray, int]:
    """Deletion-first carving of one frame's change, **in place**; returns (status, voxels).

    For every changed pixel (``mask``), walk its ray from the old surface M_t through the
    tissue layer the model holds there. When free space the model already holds follows
    (a cavity, e.g. the cell behind a lamella) before the estimate's depth, the layer's
    voxels are set free (tsdf = +1, weight 1): the tissue is gone, and the surface behind it
    is the model's own, so the estimate's noisy depth is not fused. When the estimate is
    deeper than that next surface by more than ``tol_mm`` too, the next layer goes as well
    (at most ``max_layers``). Where the model holds nothing behind (unobserved voxels,
    or solid tissue reaching beyond the estimate) the pixel's status is
    :data:`CARVE_FUSE`: the caller fuses the new depth there (the paper's masked update).
    Where deletion stopped at a surface the model holds, a precise estimate also frees the
    tissue in front of it up to ``tol_mm`` past that surface's front (the rim of a cut seen
    at an angle), keeping a quarter voxel from it along its normal (:func:`_reach_free`).

    ``precise=False`` is for an estimate noisier than the threshold (a network's): it can
    say "deeper here" but not where. Then at most one layer is deleted, only when the
    estimate lies past the middle of the cavity between the layer's front and the next
    surface the model holds, and a pixel whose estimate ends inside tissue the model holds
    is left alone (:data:`CARVE_NONE`) instead of fused as a partial cut; only where the
    model holds nothing behind is the new depth fused. With ``votes`` (the step's per-voxel
    counts, updated in place) and ``noisy_votes`` > 1 such a frame only votes: a voxel is
    set free at its ``noisy_votes``-th vote of the step (one vote per frame), so that one
    frame's wrong estimate deletes nothing alone. Such a frame deletes no layer thicker
    along its ray than ``noisy_layer_mm`` and leaves a pixel whose old surface lies deeper
    than ``noisy_max_depth_mm`` (z-depth) alone. ``precise`` may be an (H, W) bool map:
    a learnt estimate that declares where it is reliable (``last_reliable_px``,
    :mod:`chisel.depth_source`) is carved as precise there and as noisy elsewhere.

    m_t, m_new : (H, W) float32 z-depth of the model (at step start) and the estimate M',
        mm, NaN invalid; mask : (H, W) bool change mask; tol_mm : the frame's change
        threshold, mm; reset : the step's per-voxel touched flags (set for deleted voxels).
    Returns status (H, W) uint8 (``CARVE_*``) and the number of voxels set free.
    """
    T = check_rigid(T_world_from_cam, "T_world_from_cam")
    for name, a in (("m_t", m_t), ("m_new", m_new), ("mask", mask)):
        camera.check_image(a, name)
    A = np.ascontiguousarray((np.linalg.inv(model.T_world_from_voxel) @ T)[:3])
    rays = np.ascontiguousarray(camera.rays_cam(), dtype=np.float64)
    depth = lambda d: np.asarray(d, np.float32)  # noqa: E731  (non-finite = invalid, in the kernel)
    shape = np.array(model.shape, dtype=np.int64)
    H, W = camera.shape
    z0 = np.zeros((H, W, max_layers))
    z1 = np.zeros((H, W, max_layers))
    reach = np.zeros((H, W))
    reach_from = np.zeros((H, W))
    m_t, m_new, mask = depth(m_t), depth(m_new), np.asarray(mask, bool)
    if np.ndim(precise) != 0:
        camera.check_image(np.asarray(precise), "precise")
    precise_px = np.ascontiguousarray(np.broadcast_to(np.asarray(precise, dtype=bool), (H, W)))
    tsdf = _flat(model.tsdf, "model.tsdf")
    weight = _flat(model.weight, "model.weight")
    status = _carve_plan(
        tsdf, weight, shape, A, rays, m_t, m_new, mask,
        float(model.voxel_size_mm), float(model.trunc_mm), float(tol_mm),
        int(max_layers), precise_px, float(noisy_layer_mm), float(noisy_max_depth_mm),
        z0, z1, reach,
    )  # fmt: skip
    # The rim is a precise estimate's: a noisy one cannot tell a cut's edge from its noise.
    changed = mask & (status != CARVE_NONE) & precise_px if rim_px > 0 else None
    if changed is not None and changed.any():
        zt, ze = m_t.astype(np.float64), m_new.astype(np.float64)
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rim_px + 1, 2 * rim_px + 1))
        near = cv2.dilate(changed.astype(np.uint8), k) > 0
        with np.errstate(invalid="ignore"):
            ring = near & (status == CARVE_NONE) & ~mask & (ze > zt) & precise_px
            ring &= ze < zt + tol_mm  # deeper by more is a change the mask or its check refused
        reach[ring] = np.minimum(ze, zt + tol_mm)[ring]
        reach_from[ring] = zt[ring] - 0.5 * float(model.voxel_size_mm)
        status[ring] = CARVE_RIM
    use_reset = reset is not None
    if reset is not None and (reset.shape != model.shape or reset.dtype != np.uint8):
        raise InvalidInputError("reset", f"expected {model.shape} uint8, got {reset.shape}")
    r = _flat(reset, "reset") if reset is not None else np.zeros(1, np.uint8)
    need_votes, vt = 1, np.zeros(1, np.uint8)
    if not precise_px.all() and votes is not None and noisy_votes > 1:
        if votes.shape != model.shape or votes.dtype != np.uint8:
            raise InvalidInputError("votes", f"expected {model.shape} uint8, got {votes.shape}")
        need_votes, vt = int(noisy_votes), _flat(votes, "votes")
    T_cam_from_voxel = invert_rigid(T) @ model.T_world_from_voxel
    box = _deleted_voxel_box(
        shape, rays, np.linalg.inv(T_cam_from_voxel), status, z0, z1, reach, reach_from
    )
    if not np.all(box[1] > box[0]):
        return status, 0
    n = _carve_apply(
        tsdf, weight, r, use_reset, shape, box[0], box[1],
        np.ascontiguousarray(T_cam_from_voxel[:3, :3]), np.ascontiguousarray(T_cam_from_voxel[:3, 3]),
        camera.fx, camera.fy, camera.cx, camera.cy,
        np.ascontiguousarray(camera.dist, dtype=np.float64), _camera_tiles(camera, TILE_PX).r2_max,
        status, z0, z1, 0.5 * float(model.voxel_size_mm), vt, need_votes, precise_px, reach,
        _reach_free(reach, rays, m_new, 0.25 * float(model.voxel_size_mm)), reach_from,
        float(model.trunc_mm),
    )  # fmt: skip
    return status, int(n)
