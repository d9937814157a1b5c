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

Speed: the kernel visits only the voxels of the axis-aligned sub-box around the camera
frustum (camera centre to the farthest valid depth plus the truncation) and runs in
parallel over voxel columns. CPU only: there is no GPU path.
"""

from __future__ import annotations

import numba
import numpy as np

from chisel.errors import InvalidInputError, PoseError
from chisel.geometry import Camera, check_rigid, invert_rigid
from chisel.model import TsdfModel


@numba.njit(parallel=True, fastmath=True, cache=True)
def _integrate_kernel(
    tsdf,
    weight,
    color,
    use_color,
    reset,
    use_reset,
    depth,
    pix_w,
    rgb,
    R,
    t,
    fx,
    fy,
    cx,
    cy,
    dist,
    r2_max,
    box,
    trunc_mm,
    xb,
    z_near,
    z_far,
    lateral_px,
    use_lateral,
):
    # Inputs are sanitised by the caller: depth <= 0 means invalid (no NaN reaches here,
    # which keeps fastmath's no-NaN assumption true).
    H, W = depth.shape
    i0, i1, j0, j1, k0, k1 = box[0], box[1], box[2], box[3], box[4], box[5]
    nj = j1 - j0
    ncol = (i1 - i0) * nj
    k1_, k2_, p1_, p2_, k3_ = dist[0], dist[1], dist[2], dist[3], dist[4]
    distorted = (k1_ != 0.0) or (k2_ != 0.0) or (p1_ != 0.0) or (p2_ != 0.0) or (k3_ != 0.0)
    inv_trunc = 1.0 / trunc_mm
    counts = np.zeros(ncol, dtype=np.int64)
    for col in numba.prange(ncol):
        i = i0 + col // nj
        j = j0 + col % nj
        bx = R[0, 0] * i + R[0, 1] * j + t[0]
        by = R[1, 0] * i + R[1, 1] * j + t[1]
        bz = R[2, 0] * i + R[2, 1] * j + t[2]
        # Along the column, X, Y, Z are linear in k; the frustum (the image's normalised
        # bounds, z_near < Z < z_far) is an intersection of half-lines a + b k >= 0, so
        # the visible k-interval is found without visiting the voxels outside it.
        lo = float(k0)
        hi = float(k1) - 1.0
        for h in range(6):
            if h == 0:
                a = bz - z_near
                b = R[2, 2]
            elif h == 1:
                a = z_far - bz
                b = -R[2, 2]
            elif h == 2:
                a = bx - xb[0] * bz
                b = R[0, 2] - xb[0] * R[2, 2]
            elif h == 3:
                a = xb[1] * bz - bx
                b = xb[1] * R[2, 2] - R[0, 2]
            elif h == 4:
                a = by - xb[2] * bz
                b = R[1, 2] - xb[2] * R[2, 2]
            else:
                a = xb[3] * bz - by
                b = xb[3] * R[2, 2] - R[1, 2]
            if b > 1e-12:
                lo = max(lo, -a / b)
            elif b < -1e-12:
                hi = min(hi, -a / b)
            elif a < 0.0:
                hi = lo - 1.0
        if hi < lo:
            counts[col] = 0
            continue
        ka = max(k0, int(np.floor(lo)) - 1)
        kb = min(k1, int(np.ceil(hi)) + 2)
        n = 0
        for k in range(ka, kb):
            zc = bz + R[2, 2] * k
            if zc <= 1e-3:
                continue
            xc = (bx + R[0, 2] * k) / zc
            yc = (by + R[1, 2] * k) / zc
            r2 = xc * xc + yc * yc
            if r2 > r2_max:
                continue
            if distorted:
                radial = 1.0 + r2 * (k1_ + r2 * (k2_ + r2 * k3_))
                xd = xc * radial + 2.0 * p1_ * xc * yc + p2_ * (r2 + 2.0 * xc * xc)
                yd = yc * radial + p1_ * (r2 + 2.0 * yc * yc) + 2.0 * p2_ * xc * yc
            else:
                xd = xc
                yd = yc
            uf = fx * xd + cx + 0.5
            vf = fy * yd + cy + 0.5
            if uf < 0.0 or vf < 0.0:
                continue
            u = int(uf)
            v = int(vf)
            if u >= W or v >= H:
                continue
            w = pix_w[v, u]
            if w <= 0.0:
                continue
            dm = depth[v, u]
            if dm <= 0.0:
                continue
            sd = dm - zc
            if sd < -trunc_mm:
                continue
            if use_lateral and sd > 0.0:
                # Projective distance overestimates free space beside a silhouette: bound it
                # by the lateral distance (at this depth) to the nearest pixel left alone.
                lat = lateral_px[v, u] * zc / fx
                if sd > lat:
                    sd = lat
            d = sd * inv_trunc
            if d > 1.0:
                d = 1.0
            if use_reset and reset[i, j, k] == 0:
                reset[i, j, k] = 1
                weight[i, j, k] = 0.0
            W0 = weight[i, j, k]
            W1 = W0 + w
            tsdf[i, j, k] = (W0 * tsdf[i, j, k] + w * d) / W1
            weight[i, j, k] = W1
            if use_color and d < 1.0:
                for c in range(3):
                    val = (W0 * color[i, j, k, c] + w * rgb[v, u, c]) / W1
                    color[i, j, k, c] = np.uint8(min(255.0, max(0.0, val + 0.5)))
            n += 1
        counts[col] = n
    return counts.sum()


def frustum_box(
    model: TsdfModel, camera: Camera, T_world_from_cam: np.ndarray, z_far_mm: float
) -> np.ndarray | None:
    """Voxel index sub-box ``[i0, i1, j0, j1, k0, k1]`` (int64, half-open) around a frustum.

    The frustum runs from the camera centre to ``z_far_mm`` through the image border
    (distortion included). Returns None when it misses the grid.
    """
    rays = camera.rays_cam()
    border = np.concatenate([rays[0], rays[-1], rays[:, 0], rays[:, -1]], axis=0)
    pts_cam = np.concatenate([np.zeros((1, 3)), border * z_far_mm], axis=0)
    T_voxel_from_cam = invert_rigid_scaled(model.T_world_from_voxel) @ T_world_from_cam
    pts = pts_cam @ T_voxel_from_cam[:3, :3].T + T_voxel_from_cam[:3, 3]
    lo = np.floor(pts.min(axis=0)).astype(np.int64)
    hi = np.ceil(pts.max(axis=0)).astype(np.int64) + 1
    shape = np.array(model.shape)
    lo = np.clip(lo, 0, shape)
    hi = np.clip(hi, 0, shape)
    if np.any(hi <= lo):
        return None
    return np.array([lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]], dtype=np.int64)


def invert_rigid_scaled(T_world_from_voxel: np.ndarray) -> np.ndarray:
    """Inverse of an axis-aligned scaled transform (voxel grid placement): T_voxel_from_world."""
    T = np.asarray(T_world_from_voxel, dtype=np.float64)
    s = T[0, 0]
    out = np.eye(4)
    out[:3, :3] = np.eye(3) / s
    out[:3, 3] = -T[:3, 3] / s
    return out


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


_BOUNDS_CACHE: dict[tuple, tuple[float, np.ndarray]] = {}


def _camera_bounds(camera: Camera) -> tuple[float, np.ndarray]:
    """(max r^2 of the image's normalised rays, [x_min, x_max, y_min, y_max]); cached.

    The bounds reach half a pixel beyond the border rays; with distortion they come from
    the undistorted rays of every pixel, so they hold whatever the lens model.
    """
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes())
    hit = _BOUNDS_CACHE.get(key)
    if hit is None:
        rays = camera.rays_cam()
        r2_max = float(((rays[..., 0] ** 2 + rays[..., 1] ** 2).max()) * 1.02 + 1e-9)
        pad_x, pad_y = 0.5 / camera.fx, 0.5 / camera.fy
        xb = np.array(
            [
                rays[..., 0].min() - pad_x,
                rays[..., 0].max() + pad_x,
                rays[..., 1].min() - pad_y,
                rays[..., 1].max() + pad_y,
            ]
        )
        if len(_BOUNDS_CACHE) > 64:
            _BOUNDS_CACHE.clear()
        hit = _BOUNDS_CACHE[key] = (r2_max, xb)
    return hit


def integrate(
    model: TsdfModel,
    camera: Camera,
    T_world_from_cam: np.ndarray,
    depth_mm: np.ndarray,
    pixel_weight: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
    reset: np.ndarray | None = None,
    lateral_px: np.ndarray | None = None,
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
    """
    T = check_rigid(T_world_from_cam, "T_world_from_cam")
    depth = np.asarray(depth_mm, dtype=np.float32)
    camera.check_image(depth, "depth_mm")
    depth = np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(depth, 0.0, out=depth)
    if pixel_weight is None:
        pix_w = np.ones(depth.shape, dtype=np.float32)
    else:
        camera.check_image(pixel_weight, "pixel_weight")
        pix_w = np.asarray(pixel_weight, dtype=np.float32)
        if not np.all(np.isfinite(pix_w)) or np.any(pix_w < 0):
            raise InvalidInputError("pixel_weight", "weights must be finite and >= 0")
    active = (depth > 0) & (pix_w > 0)
    if not active.any():
        return 0
    z_far = float(depth[active].max()) + model.trunc_mm
    box = frustum_box(model, camera, T, z_far)
    if box is None:
        return 0
    use_color = model.color is not None and rgb is not None
    if use_color:
        camera.check_image(rgb, "rgb")
        rgb_arr = np.ascontiguousarray(rgb, dtype=np.uint8)
        color = model.color
    else:
        rgb_arr = np.zeros((1, 1, 3), dtype=np.uint8)
        color = np.zeros((1, 1, 1, 3), dtype=np.uint8)
    use_reset = reset is not None
    if use_reset:
        if reset.shape != model.shape or reset.dtype != np.uint8:
            raise InvalidInputError(
                "reset", f"expected {model.shape} uint8, got {reset.shape} {reset.dtype}"
            )
        reset_arr = reset
    else:
        reset_arr = np.zeros((1, 1, 1), dtype=np.uint8)
    use_lateral = lateral_px is not None
    if use_lateral:
        camera.check_image(lateral_px, "lateral_px")
        lateral = np.ascontiguousarray(lateral_px, dtype=np.float32)
    else:
        lateral = np.zeros((1, 1), dtype=np.float32)
    # Voxel index -> camera frame in one affine map (rotation block scaled by the voxel).
    T_cam_from_voxel = invert_rigid(T) @ model.T_world_from_voxel
    r2_max, xb = _camera_bounds(camera)
    n = _integrate_kernel(
        model.tsdf,
        model.weight,
        color,
        use_color,
        reset_arr,
        use_reset,
        depth,
        pix_w,
        rgb_arr,
        np.ascontiguousarray(T_cam_from_voxel[:3, :3]),
        np.ascontiguousarray(T_cam_from_voxel[:3, 3]),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        np.ascontiguousarray(camera.dist, dtype=np.float64),
        r2_max,
        box,
        float(model.trunc_mm),
        xb,
        1e-3,
        z_far,
        lateral,
        use_lateral,
    )
    return int(n)
