"""TSDF fusion of depth maps into a :class:`~chisel.model.TsdfModel` (numba, CPU).

One rule serves both stages of the paper:

* preoperative fusion (Curless & Levoy): every valid pixel has weight w = 1;
* the masked update of a surgical step: w = m (the change mask, 0 or 1) and the first
  time a changed pixel touches a voxel during the step the voxel's old weight is reset
  to 0 (the paper's ``w = 0 * W_t + m``), so the voxel takes the new depth; pixels with
  m = 0 leave the model alone.

For each voxel X inside the camera frustum: X_c = T_cam_from_world X, z_c its depth and
x its (nearest-pixel) projection in the raw, distorted image; d* = M(x) - z_c (mm);
voxels with d* < -trunc are occluded and untouched, the others take
d = min(1, d* / trunc) -- voxels in front of the surface beyond the truncation get
d = +1 (free space is carved, so removed tissue can disappear later) -- and are averaged
with ``D <- (W D + w d) / (W + w)``, ``W <- W + w``. Colour, when given, is averaged with
the same weights inside the truncation band only.

Speed: the image plane is cut into tiles (about ``TILE_PX`` pixels, half-open rectangles
of undistorted normalised coordinates, so each voxel belongs to exactly one tile
whatever the distortion). A tile's sub-frustum runs only to the farthest depth among
the active pixels its voxels can project to (depth > 0 and weight > 0) plus the
truncation, and tiles without active pixel are skipped: the voxels behind the surface
and, in the masked update, those outside the change mask are never visited. Per tile,
the kernel walks voxel columns along the grid axis closest to the optical axis, finds
each column's interval inside the tile's pyramid analytically and runs in parallel over
tiles (disjoint voxel sets, no write conflict), dealt to one bucket per thread by their
pyramid's volume. Per preoperative benchmark frame this visits ~31k voxels (~23k
updated) instead of the ~157k of the frustum's bounding box. CPU only: there is no GPU
path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from chisel.core.errors import InvalidInputError, PoseError
from chisel.core.geometry import Camera, check_rigid, distort_normalized, invert_rigid
from chisel.model import TsdfModel

distort = numba.njit(cache=True)(distort_normalized)
"""The lens polynomial of :func:`chisel.core.geometry.distort_normalized`, inlined into the
numba kernels (fusion, carving, change): one home for the model, no call overhead."""


@numba.njit(cache=True, nogil=True)
def nearest_pixel(xc, yc, r2_max, distorted, dist, fx, fy, cx, cy, W, H):
    # The raw (distorted) pixel whose area holds the normalised point (xc, yc), or
    # (-1, -1) outside the image or beyond the lens model's valid radius (r2_max): the
    # voxel-to-pixel step that fusion and carving share.
    if xc * xc + yc * yc > r2_max:
        return -1, -1
    if distorted:
        xd, yd = distort(xc, yc, dist[0], dist[1], dist[2], dist[3], dist[4])
    else:
        xd = xc
        yd = yc
    uf = fx * xd + cx + 0.5
    vf = fy * yd + cy + 0.5
    if uf < 0.0 or vf < 0.0:
        return -1, -1
    u = int(uf)
    v = int(vf)
    if u >= W or v >= H:
        return -1, -1
    return u, v


@numba.njit(cache=True, nogil=True)
def _nearest_pixels(pc, r2_max, distorted, dist, fx, fy, cx, cy, W, H):
    out = np.full((pc.shape[0], 2), -1, dtype=np.int64)
    for i in range(pc.shape[0]):
        z = pc[i, 2]
        if z <= 1e-3:
            continue
        u, v = nearest_pixel(
            pc[i, 0] / z, pc[i, 1] / z, r2_max, distorted, dist, fx, fy, cx, cy, W, H
        )
        out[i, 0] = u
        out[i, 1] = v
    return out


def nearest_pixels(points_cam_mm: np.ndarray, camera: Camera) -> np.ndarray:
    """(N, 2) int64 pixel (u, v) of camera-frame points, as fusion and carving map a voxel
    (:func:`nearest_pixel`); (-1, -1) behind the camera, outside the image or beyond the
    lens model's valid radius (where the distortion polynomial folds back into the image)."""
    pc = np.ascontiguousarray(np.asarray(points_cam_mm, dtype=np.float64).reshape(-1, 3))
    dist = np.ascontiguousarray(camera.dist, dtype=np.float64)
    return _nearest_pixels(
        pc, _camera_tiles(camera, TILE_PX).r2_max, bool(np.any(dist != 0.0)), dist,
        camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _clean_depth(depth):
    # No fastmath here: this is where NaN and inf are told apart from depths; <= 0 out.
    out = np.empty(depth.shape, dtype=np.float32)
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            d = depth[v, u]
            out[v, u] = d if (d > 0.0 and d < np.inf) else 0.0
    return out


@numba.njit(cache=True, nogil=True)
def _weights_ok(pix_w):
    # No fastmath: NaN must fail the test. (Two numpy passes cost ~0.07 ms per frame.)
    for v in range(pix_w.shape[0]):
        for u in range(pix_w.shape[1]):
            w = pix_w[v, u]
            if not (w >= 0.0 and w < np.inf):
                return False
    return True


@numba.njit(cache=True, nogil=True)
def _tile_depth(depth, pix_w, use_weight, offsets, pixels):
    # Per tile, the largest depth among the active pixels that a voxel of the tile may
    # project to (0 = none): ``pixels[offsets[t]:offsets[t + 1]]`` lists them (flat).
    d_flat = depth.reshape(-1)
    w_flat = pix_w.reshape(-1)
    n = offsets.shape[0] - 1
    out = np.zeros(n, dtype=np.float32)
    for t in range(n):
        m = np.float32(0.0)
        for j in range(offsets[t], offsets[t + 1]):
            p = pixels[j]
            d = d_flat[p]
            if d > m and (not use_weight or w_flat[p] > 0.0):
                m = d
        out[t] = m
    return out


@numba.njit(cache=True, nogil=True)
def _plan(tile_depth, nx, pad_mm, n_buckets):
    # The active tiles (depth bound > 0) as [tx, ty] with z_far = bound + pad_mm, dealt to
    # ``n_buckets`` buckets (one per thread) in decreasing cost, snake order, so that the
    # buckets cost about the same; a tile's cost is taken as its pyramid's volume, z_far^3
    # (the tiles span equal normalised areas). A static split of the tiles in image order
    # would hand one thread the near half of the scene.
    act = np.flatnonzero(tile_depth > 0.0)
    n = act.shape[0]
    z = tile_depth[act].astype(np.float64) + pad_mm
    rank = np.argsort(-z)
    bucket = np.empty(n, dtype=np.int64)
    for r in range(n):
        lap = r // n_buckets
        pos = r % n_buckets
        bucket[rank[r]] = pos if lap % 2 == 0 else n_buckets - 1 - pos
    offsets = np.zeros(n_buckets + 1, dtype=np.int64)
    for i in range(n):
        offsets[bucket[i] + 1] += 1
    for b in range(n_buckets):
        offsets[b + 1] += offsets[b]
    fill = offsets[:-1].copy()
    work = np.empty((n, 2), dtype=np.int64)
    z_far = np.empty(n, dtype=np.float64)
    for i in range(n):
        j = fill[bucket[i]]
        fill[bucket[i]] += 1
        work[j, 0] = act[i] % nx
        work[j, 1] = act[i] // nx
        z_far[j] = z[i]
    return work, z_far, offsets


@numba.njit(inline="always")
def _inv(b):
    return 1.0 / b if abs(b) > 1e-12 else 0.0


@numba.njit(inline="always")
def _clip(lo, hi, a, b, inv_b):
    # Narrow [lo, hi] to the k where a + b k >= 0.
    if b > 1e-12:
        lo = max(lo, -a * inv_b)
    elif b < -1e-12:
        hi = min(hi, -a * inv_b)
    elif a < 0.0:
        hi = lo - 1.0
    return lo, hi


@numba.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def _integrate_kernel(
    tsdf,
    weight,
    color,
    use_color,
    reset,
    use_reset,
    depth,
    pix_w,
    use_weight,
    rgb,
    R,
    t,
    strides,
    n_col,
    fx,
    fy,
    cx,
    cy,
    dist,
    r2_max,
    grid,
    nx,
    ny,
    tiles,
    z_far,
    bucket_offsets,
    Ri,
    ti,
    n_a,
    n_b,
    trunc_mm,
    lateral_px,
    use_lateral,
    unobserved_only,
):
    # Inputs are sanitised by the caller: depth <= 0 means invalid (no NaN reaches here,
    # which keeps fastmath's no-NaN assumption true). The volume arrays are flat; R's
    # columns and ``strides`` are ordered (a, b, c) with c the column axis, so voxel
    # (ia, ib, k) is at ia * strides[0] + ib * strides[1] + k * strides[2] and its camera
    # coordinates are R @ (ia, ib, k) + t.
    H, W = depth.shape
    k1_, k2_, p1_, p2_, k3_ = dist[0], dist[1], dist[2], dist[3], dist[4]
    distorted = (k1_ != 0.0) or (k2_ != 0.0) or (p1_ != 0.0) or (p2_ != 0.0) or (k3_ != 0.0)
    inv_trunc = 1.0 / trunc_mm
    x0, y0, tw, th = grid[0], grid[1], grid[2], grid[3]
    inv_tw = 1.0 / tw
    inv_th = 1.0 / th
    sa, sb, sc = strides[0], strides[1], strides[2]
    n_tiles = tiles.shape[0]
    counts = np.zeros(n_tiles, dtype=np.int64)
    # Tiles come in one bucket per thread, balanced by the caller (a static split of
    # tiles in image order would give one thread the near half of the scene).
    for bk in numba.prange(bucket_offsets.shape[0] - 1):
        for it in range(bucket_offsets[bk], bucket_offsets[bk + 1]):
            tx = tiles[it, 0]
            ty = tiles[it, 1]
            # The tile's rectangle of normalised coordinates, padded by a hair so that the
            # analytic interval below never drops a voxel of the tile to rounding; the exact
            # (half-open) membership test is done per voxel.
            xl = x0 + tx * tw - 1e-7
            xh = x0 + (tx + 1) * tw + 1e-7
            yl = y0 + ty * th - 1e-7
            yh = y0 + (ty + 1) * th + 1e-7
            zf = z_far[it]
            # Along a column the half-spaces' slopes b depend on the tile only.
            b0 = R[2, 2]
            b1 = -R[2, 2]
            b2 = R[0, 2] - xl * R[2, 2]
            b3 = xh * R[2, 2] - R[0, 2]
            b4 = R[1, 2] - yl * R[2, 2]
            b5 = yh * R[2, 2] - R[1, 2]
            i0, i1, i2, i3, i4, i5 = _inv(b0), _inv(b1), _inv(b2), _inv(b3), _inv(b4), _inv(b5)
            # The tile's pyramid (camera centre, 4 corner rays at z_far) in voxel coordinates
            # (a, b); the columns that cross it are those whose (a, b) lies in the convex hull
            # of these 5 points, i.e. per row a between the extreme crossings of the 10
            # segments joining them.
            pa = np.empty(5)
            pb = np.empty(5)
            pa[0] = ti[0]
            pb[0] = ti[1]
            for q in range(4):
                X = (xl if q % 2 == 0 else xh) * zf
                Y = (yl if q < 2 else yh) * zf
                pa[q + 1] = Ri[0, 0] * X + Ri[0, 1] * Y + Ri[0, 2] * zf + ti[0]
                pb[q + 1] = Ri[1, 0] * X + Ri[1, 1] * Y + Ri[1, 2] * zf + ti[1]
            ia0 = max(0, int(np.ceil(pa.min() - 1e-6)))
            ia1 = min(n_a, int(np.floor(pa.max() + 1e-6)) + 1)
            n = 0
            for ia in range(ia0, ia1):
                blo = np.inf
                bhi = -np.inf
                for p in range(5):
                    for q in range(p, 5):
                        da = pa[q] - pa[p]
                        if p == q or abs(da) < 1e-12:
                            if abs(pa[p] - ia) <= 1e-6:
                                blo = min(blo, pb[p], pb[q])
                                bhi = max(bhi, pb[p], pb[q])
                            continue
                        s = (ia - pa[p]) / da
                        if s < -1e-9 or s > 1.0 + 1e-9:
                            continue
                        bb = pb[p] + s * (pb[q] - pb[p])
                        blo = min(blo, bb)
                        bhi = max(bhi, bb)
                if bhi < blo:
                    continue
                ib0 = max(0, int(np.ceil(blo - 1e-6)))
                ib1 = min(n_b, int(np.floor(bhi + 1e-6)) + 1)
                for ib in range(ib0, ib1):
                    bx = R[0, 0] * ia + R[0, 1] * ib + t[0]
                    by = R[1, 0] * ia + R[1, 1] * ib + t[1]
                    bz = R[2, 0] * ia + R[2, 1] * ib + t[2]
                    # Along the column, X, Y, Z are linear in k; the tile's sub-frustum (its
                    # rectangle, 1e-3 < Z < z_far) is an intersection of half-lines
                    # a + b k >= 0, so the k-interval is found without visiting the rest.
                    lo, hi = _clip(0.0, n_col - 1.0, bz - 1e-3, b0, i0)
                    lo, hi = _clip(lo, hi, zf - bz, b1, i1)
                    lo, hi = _clip(lo, hi, bx - xl * bz, b2, i2)
                    lo, hi = _clip(lo, hi, xh * bz - bx, b3, i3)
                    lo, hi = _clip(lo, hi, by - yl * bz, b4, i4)
                    lo, hi = _clip(lo, hi, yh * bz - by, b5, i5)
                    if hi < lo:
                        continue
                    ka = int(np.ceil(lo - 1e-6))
                    kb = int(np.floor(hi + 1e-6)) + 1
                    base = ia * sa + ib * sb
                    for k in range(ka, kb):
                        zc = bz + R[2, 2] * k
                        if zc <= 1e-3:
                            continue
                        xc = (bx + R[0, 2] * k) / zc
                        yc = (by + R[1, 2] * k) / zc
                        # Each voxel belongs to the one tile its (xc, yc) falls in: no voxel
                        # is visited by two tiles, whatever the lens distortion.
                        gx = (xc - x0) * inv_tw
                        gy = (yc - y0) * inv_th
                        if gx < 0.0 or gy < 0.0 or gx >= nx or gy >= ny:
                            continue
                        if int(gx) != tx or int(gy) != ty:
                            continue
                        u, v = nearest_pixel(xc, yc, r2_max, distorted, dist, fx, fy, cx, cy, W, H)
                        if u < 0:
                            continue
                        w = pix_w[v, u] if use_weight else 1.0
                        if w <= 0.0:
                            continue
                        dm = depth[v, u]
                        if dm <= 0.0:
                            continue
                        sd = dm - zc
                        if sd < -trunc_mm:
                            continue
                        if use_lateral and sd > 0.0:
                            # Projective distance overestimates free space beside a silhouette:
                            # bound it by the lateral distance (at this depth) to the nearest
                            # pixel left alone.
                            lat = lateral_px[v, u] * zc / fx
                            if sd > lat:
                                sd = lat
                        d = sd * inv_trunc
                        if d > 1.0:
                            d = 1.0
                        idx = base + k * sc
                        if (
                            unobserved_only
                            and weight[idx] > 0.0
                            and not (use_reset and reset[idx] != 0)
                        ):
                            continue  # observed before this step: keep what was seen
                        if use_reset and reset[idx] == 0:
                            reset[idx] = 1
                            weight[idx] = 0.0
                        W0 = weight[idx]
                        W1 = W0 + w
                        tsdf[idx] = (W0 * tsdf[idx] + w * d) / W1
                        weight[idx] = W1
                        if use_color and d < 1.0:
                            for c in range(3):
                                val = (W0 * color[idx, c] + w * rgb[v, u, c]) / W1
                                color[idx, c] = np.uint8(min(255.0, max(0.0, val + 0.5)))
                        n += 1
            counts[it] = n
    return counts.sum()


def check_pose_in_model(model: TsdfModel, T_world_from_cam: np.ndarray, source: str) -> np.ndarray:
    """Validate a camera pose and require its centre inside the model's box; returns (4, 4)."""
    T = check_rigid(T_world_from_cam, source)
    if T.shape != (4, 4):
        raise PoseError(source, f"expected one (4, 4) pose, got shape {T.shape}")
    if not model.contains_mm(T[:3, 3]):
        lo, hi = model.bounds_mm
        raise PoseError(
            source,
            f"camera centre {np.round(T[:3, 3], 2).tolist()} mm lies outside the model's "
            f"volume [{np.round(lo, 2).tolist()}, {np.round(hi, 2).tolist()}] mm: wrong "
            "registration of the tracker, wrong units, or the wrong model",
        )
    return T


TILE_PX = 16
"""Nominal tile size in pixels (see :func:`_camera_tiles`), chosen by measurement."""


@dataclass(frozen=True)
class _TileGrid:
    """A camera's image plane cut into tiles in undistorted normalised coordinates."""

    r2_max: float
    """Largest x^2 + y^2 of the image's normalised rays (plus 2 %)."""
    grid: np.ndarray
    """(4,) float64 x0, y0 (the frustum's lower bounds) and the tile width, height."""
    nx: int
    """Number of tile columns."""
    ny: int
    """Number of tile rows."""
    offsets: np.ndarray
    """(nx * ny + 1,) int64: tile t (= ty * nx + tx) owns ``pixels[offsets[t]:offsets[t + 1]]``."""
    pixels: np.ndarray
    """(n,) int32 flat indices of the pixels whose ray lies within one pitch of each tile."""


_TILES_CACHE: dict[tuple, _TileGrid] = {}


def _camera_tiles(camera: Camera, tile_px: int = TILE_PX) -> _TileGrid:
    """The tiling of ``camera``'s frustum; cached per camera.

    The tiles are half-open rectangles of normalised coordinates (x, y) = (X/Z, Y/Z)
    that partition the frustum's bounds, about ``tile_px`` pixels wide. The bounds reach
    half a pixel pitch beyond the border rays (the pitch taken from the undistorted rays
    of every pixel, so they hold whatever the lens model). A voxel projecting into pixel p
    has its ray within half a pitch (in u and in v) of p's ray; every pixel is therefore
    assigned to all the tiles within one full pitch of its ray, which bounds the depth a
    tile's voxels can meet whatever the distortion.
    """
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), tile_px)
    hit = _TILES_CACHE.get(key)
    if hit is not None:
        return hit
    rays = camera.rays_cam()
    x, y = rays[..., 0], rays[..., 1]
    r2_max = float(((x**2 + y**2).max()) * 1.02 + 1e-9)
    # Pitch: the largest step of x (of y) between neighbouring pixels, along u plus along v.
    pitch_x = np.abs(np.diff(x, axis=1)).max(initial=0.0) + np.abs(np.diff(x, axis=0)).max(
        initial=0.0
    )
    pitch_y = np.abs(np.diff(y, axis=1)).max(initial=0.0) + np.abs(np.diff(y, axis=0)).max(
        initial=0.0
    )
    pitch_x = max(pitch_x, 1.0 / camera.fx)
    pitch_y = max(pitch_y, 1.0 / camera.fy)
    x0, x1 = x.min() - 0.5 * pitch_x, x.max() + 0.5 * pitch_x
    y0, y1 = y.min() - 0.5 * pitch_y, y.max() + 0.5 * pitch_y
    nx = max(1, -(-camera.width // tile_px))
    ny = max(1, -(-camera.height // tile_px))
    tw, th = (x1 - x0) / nx, (y1 - y0) / ny

    def span(c: np.ndarray, c0: float, step: float, pad: float, n: int):
        lo = np.clip(np.floor((c - pad - c0) / step), 0, n - 1).astype(np.int32)
        hi = np.clip(np.floor((c + pad - c0) / step), 0, n - 1).astype(np.int32)
        return lo, hi

    tx_lo, tx_hi = span(x, x0, tw, pitch_x, nx)
    ty_lo, ty_hi = span(y, y0, th, pitch_y, ny)
    # (pixel, tile) pairs: the pitch is below a tile, so a pixel meets at most 2 x 2 tiles.
    flat = np.arange(x.size, dtype=np.int32)
    pairs_p, pairs_t = [], []
    for ty in (ty_lo.ravel(), ty_hi.ravel()):
        for tx in (tx_lo.ravel(), tx_hi.ravel()):
            pairs_p.append(flat)
            pairs_t.append(ty.astype(np.int64) * nx + tx)
    pix = np.concatenate(pairs_p)
    til = np.concatenate(pairs_t)
    uniq = np.unique(til * x.size + pix)  # drops the duplicates, sorted by tile then pixel
    til, pix = uniq // x.size, (uniq % x.size).astype(np.int32)
    offsets = np.searchsorted(til, np.arange(nx * ny + 1)).astype(np.int64)
    hit = _TileGrid(r2_max, np.array([x0, y0, tw, th]), nx, ny, offsets, pix)
    if len(_TILES_CACHE) > 64:
        _TILES_CACHE.clear()
    _TILES_CACHE[key] = hit
    return hit


def _flat(a: np.ndarray, name: str) -> np.ndarray:
    """A flat view of ``a`` (updated in place by the kernel); C order required."""
    if not a.flags.c_contiguous:
        raise InvalidInputError(name, "must be a C-contiguous array (updated in place)")
    return a.reshape(-1)


def integrate(
    model: TsdfModel,
    camera: Camera,
    T_world_from_cam: np.ndarray,
    depth_mm: np.ndarray,
    pixel_weight: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
    reset: np.ndarray | None = None,
    lateral_px: np.ndarray | None = None,
    unobserved_only: bool = False,
) -> int:
    """Fuse one depth map into ``model`` **in place**; returns the number of voxels updated.

    Parameters
    ----------
    model : TsdfModel, updated in place (tsdf, weight, colour).
    camera : the camera of ``depth_mm`` (raw image grid, distortion honoured).
    T_world_from_cam : (4, 4) float64 camera pose, mm.
    depth_mm : (H, W) float32 z-depth, mm, NaN or <= 0 = invalid.
    pixel_weight : (H, W) float32 or bool weight per pixel (None = 1 everywhere); 0 skips
        the pixel. In the masked update this is the change mask m.
    rgb : (H, W, 3) uint8 colour of the frame, used when the model has colour.
    reset : (X, Y, Z) uint8, per-step "touched" flags. When given, a voxel touched for
        the first time in this step has its old weight reset to 0 before averaging (the
        paper's ``w = 0 * W_t + m``) and its flag set to 1.
    lateral_px : (H, W) float32 or None. Image distance (pixels) from each pixel to the
        nearest pixel that is *not* integrated (e.g. ``cv2.distanceTransform`` of the change
        mask). When given, the positive distance of a voxel is bounded by that lateral
        distance at the voxel's depth: along a changed ray that grazes the remaining tissue
        (the rim of a bite), the projective distance d* says "far from any surface" while
        the true distance is the gap to the rim, and an unbounded d* would pull the rim
        back by up to a voxel. Signs never change, so no surface is created.
    unobserved_only : write only voxels the model has never observed (weight 0) or that
        ``reset`` marks as already rewritten in this step: filling a model's holes without
        overwriting what it observed.
    """
    T = check_rigid(T_world_from_cam, "T_world_from_cam")
    depth = np.asarray(depth_mm, dtype=np.float32)
    camera.check_image(depth, "depth_mm")
    depth = _clean_depth(depth)
    use_weight = pixel_weight is not None
    if pixel_weight is None:
        pix_w = np.ones((1, 1), dtype=np.float32)  # not read
    else:
        camera.check_image(pixel_weight, "pixel_weight")
        pix_w = np.ascontiguousarray(pixel_weight, dtype=np.float32)
        if not _weights_ok(pix_w):
            raise InvalidInputError("pixel_weight", "weights must be finite and >= 0")
    use_color = model.color is not None and rgb is not None
    if use_color:
        assert rgb is not None and model.color is not None  # use_color
        camera.check_image(rgb, "rgb")
        rgb_arr = np.ascontiguousarray(rgb, dtype=np.uint8)
        color = model.color
    else:
        rgb_arr = np.zeros((1, 1, 3), dtype=np.uint8)
        color = np.zeros((1, 1, 1, 3), dtype=np.uint8)
    use_reset = reset is not None
    if reset is not None:
        if reset.shape != model.shape or reset.dtype != np.uint8:
            raise InvalidInputError(
                "reset", f"expected {model.shape} uint8, got {reset.shape} {reset.dtype}"
            )
        reset_arr = reset
    else:
        reset_arr = np.zeros((1, 1, 1), dtype=np.uint8)
    use_lateral = lateral_px is not None
    if lateral_px is not None:
        camera.check_image(lateral_px, "lateral_px")
        lateral = np.ascontiguousarray(lateral_px, dtype=np.float32)
    else:
        lateral = np.zeros((1, 1), dtype=np.float32)
    # Voxel index -> camera frame in one affine map (rotation block scaled by the voxel).
    T_cam_from_voxel = invert_rigid(T) @ model.T_world_from_voxel
    # Columns run along the voxel axis closest to the optical axis: a tile's thin pyramid
    # then has a small footprint of columns.
    c = int(np.argmax(np.abs(T_cam_from_voxel[2, :3])))
    axes = np.array([a for a in range(3) if a != c] + [c])
    tiles = _camera_tiles(camera, TILE_PX)
    tile_depth = _tile_depth(depth, pix_w, use_weight, tiles.offsets, tiles.pixels)
    work, z_far, bucket_offsets = _plan(
        tile_depth, tiles.nx, float(model.trunc_mm) + 1e-6, numba.get_num_threads()
    )
    if len(work) == 0:
        return 0
    shape = np.array(model.shape)
    T_voxel_from_cam = np.linalg.inv(T_cam_from_voxel)
    strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)[axes]
    n = _integrate_kernel(
        _flat(model.tsdf, "model.tsdf"), _flat(model.weight, "model.weight"),
        _flat(color, "model.color").reshape(-1, 3), use_color,
        _flat(reset_arr, "reset"), use_reset, depth, pix_w, use_weight, rgb_arr,
        np.ascontiguousarray(T_cam_from_voxel[:3, :3][:, axes]),
        np.ascontiguousarray(T_cam_from_voxel[:3, 3]), strides, int(shape[c]),
        camera.fx, camera.fy, camera.cx, camera.cy,
        np.ascontiguousarray(camera.dist, dtype=np.float64),
        tiles.r2_max, tiles.grid, tiles.nx, tiles.ny, work, z_far, bucket_offsets,
        np.ascontiguousarray(T_voxel_from_cam[:3, :3][axes]),
        np.ascontiguousarray(T_voxel_from_cam[:3, 3][axes]),
        int(shape[axes[0]]), int(shape[axes[1]]), float(model.trunc_mm),
        lateral, use_lateral, bool(unobserved_only),
    )  # fmt: skip
    return int(n)
