"""Change detection of one frame: scale, re-projection, imputation and the change mask.

Given the model's render M_t and a depth estimate of the same view (possibly up to an
unknown scale):

1. :func:`solve_scale` -- a robust median of ratios M_t / estimate, iterated with the
   changed pixels (estimate clearly deeper than the model: removed tissue) and outliers
   left out, so a bite in view does not bias the scale;
2. :func:`reproject_depth` -- the registered estimate (world points) z-buffered back into
   the frame at its tracked pose -> M';
3. :func:`impute` -- pixels that received no point take M_t (no change there);
4. :func:`change_mask` -- m = (M' - M_t) > threshold (tissue is only removed, so depth only
   grows), cleaned by a morphological opening and closing and a minimum component area.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from chisel.errors import EmptyResultError, InvalidInputError
from chisel.geometry import Camera, invert_rigid

MIN_SCALE_PIXELS = 50
"""Fewest pixels valid in both the render and the estimate for a scale to be solved."""
MAX_SCALE_PIXELS = 8000
"""About this many pixels (a regular stride) enter the scale's medians."""


@dataclass(frozen=True)
class ChangeConfig:
    """Parameters of the change mask."""

    threshold_mm: float = 1.0
    """A pixel is changed when M' - M_t exceeds this, mm (the paper: 1.0 mm)."""
    open_px: int = 3
    """Side of the square opening kernel, pixels (removes speckle); 0 or 1 = off."""
    close_px: int = 5
    """Side of the square closing kernel, pixels (fills pin holes); 0 or 1 = off."""
    min_area_px: int = 30
    """Changed components smaller than this many pixels are dropped."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.threshold_mm) and self.threshold_mm > 0):
            raise InvalidInputError("threshold_mm", f"must be > 0 mm, got {self.threshold_mm}")
        for name in ("open_px", "close_px", "min_area_px"):
            if int(getattr(self, name)) < 0:
                raise InvalidInputError(name, f"must be >= 0, got {getattr(self, name)}")


def solve_scale(
    render_mm: np.ndarray,
    estimate: np.ndarray,
    outlier_mm: float = 1.0,
    iterations: int = 3,
) -> tuple[float, int]:
    """Robust monocular scale s with ``s * estimate ~= render_mm`` on unchanged pixels.

    render_mm : (H, W) float32 model depth M_t, mm, NaN = invalid.
    estimate : (H, W) float32 depth up to scale, NaN = invalid.
    outlier_mm : lower bound of the inlier band, mm; the band is max(outlier_mm, 3 MAD).
    Returns (scale, number of inlier pixels). Raises :class:`EmptyResultError` when fewer
    than ``MIN_SCALE_PIXELS`` pixels are valid in both maps.
    """
    r = np.asarray(render_mm, dtype=np.float64)
    e = np.asarray(estimate, dtype=np.float64)
    valid = np.isfinite(r) & np.isfinite(e) & (e > 0) & (r > 0)
    if int(valid.sum()) < MIN_SCALE_PIXELS:
        raise EmptyResultError(
            f"only {int(valid.sum())} pixels are valid in both the render and the estimate "
            f"(need {MIN_SCALE_PIXELS}): cannot solve the scale"
        )
    n_valid = int(valid.sum())
    if n_valid > 2 * MAX_SCALE_PIXELS:
        # A regular pixel stride: the median of ~10^4 ratios is just as good and cheaper.
        stride = int(np.ceil(np.sqrt(n_valid / MAX_SCALE_PIXELS)))
        sub = np.zeros_like(valid)
        sub[::stride, ::stride] = True
        if int((valid & sub).sum()) >= MIN_SCALE_PIXELS:
            valid &= sub
    rv, ev = r[valid], e[valid]
    s = float(np.median(rv / ev))
    keep = np.ones(rv.shape, dtype=bool)
    for _ in range(iterations):
        resid = s * ev - rv
        mad = float(np.median(np.abs(resid[keep] - np.median(resid[keep])))) * 1.4826
        band = max(outlier_mm, 3.0 * mad)
        new_keep = np.abs(resid) <= band
        if new_keep.sum() < MIN_SCALE_PIXELS:
            break
        keep = new_keep
        s = float(np.median(rv[keep] / ev[keep]))
    return s, int(keep.sum())


@numba.njit(cache=True)
def _zbuffer(u, v, z, H, W, out):
    for n in range(u.shape[0]):
        uu = u[n]
        vv = v[n]
        if 0 <= uu < W and 0 <= vv < H:
            zz = z[n]
            cur = out[vv, uu]
            if not (cur <= zz):  # NaN (empty) or farther: take the nearer point
                out[vv, uu] = zz
    return out


def reproject_depth(
    points_world_mm: np.ndarray, camera: Camera, T_world_from_cam: np.ndarray
) -> np.ndarray:
    """Z-buffer world points into a camera: nearest point per pixel.

    points_world_mm : (N, 3) float, world mm.
    Returns (H, W) float32 z-depth, mm, NaN where no point lands (lost in projection).
    """
    p = np.asarray(points_world_mm, dtype=np.float64).reshape(-1, 3)
    T_cam_from_world = invert_rigid(T_world_from_cam)
    pc = p @ T_cam_from_world[:3, :3].T + T_cam_from_world[:3, 3]
    front = pc[:, 2] > 1e-6
    uv, z = camera.project(pc[front])
    u = np.floor(uv[:, 0] + 0.5).astype(np.int64)
    v = np.floor(uv[:, 1] + 0.5).astype(np.int64)
    out = np.full(camera.shape, np.nan, dtype=np.float32)
    return _zbuffer(u, v, z.astype(np.float32), camera.height, camera.width, out)


@numba.njit(cache=True)
def _warp_kernel(depth, rays, D, fx, fy, cx, cy, dist, out):
    H, W = depth.shape
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for v in range(H):
        for u in range(W):
            d = depth[v, u]
            if not (d > 0.0):
                continue
            x = rays[v, u, 0] * d
            y = rays[v, u, 1] * d
            z = rays[v, u, 2] * d
            X = D[0, 0] * x + D[0, 1] * y + D[0, 2] * z + D[0, 3]
            Y = D[1, 0] * x + D[1, 1] * y + D[1, 2] * z + D[1, 3]
            Z = D[2, 0] * x + D[2, 1] * y + D[2, 2] * z + D[2, 3]
            if Z <= 1e-6:
                continue
            xn = X / Z
            yn = Y / Z
            r2 = xn * xn + yn * yn
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
            yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
            uu = int(np.floor(fx * xd + cx + 0.5))
            vv = int(np.floor(fy * yd + cy + 0.5))
            if 0 <= uu < W and 0 <= vv < H:
                cur = out[vv, uu]
                if not (cur <= Z):
                    out[vv, uu] = Z
    return out


def warp_depth(depth_mm: np.ndarray, camera: Camera, T_dst_from_src: np.ndarray) -> np.ndarray:
    """Re-project a depth map of one pose of ``camera`` into another pose (z-buffered).

    depth_mm : (H, W) float32 z-depth in the source camera, mm, NaN = invalid.
    T_dst_from_src : (4, 4) float64 source camera frame -> destination camera frame.
    Returns (H, W) float32 z-depth in the destination camera, NaN where nothing lands.
    Same result as back-projecting, transforming and :func:`reproject_depth`, in one pass.
    """
    camera.check_image(depth_mm, "depth_mm")
    d = np.nan_to_num(np.asarray(depth_mm, dtype=np.float64), nan=0.0)
    out = np.full(camera.shape, np.nan, dtype=np.float32)
    return _warp_kernel(
        d,
        np.ascontiguousarray(camera.rays_cam()),
        np.ascontiguousarray(T_dst_from_src, dtype=np.float64),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        np.ascontiguousarray(camera.dist, dtype=np.float64),
        out,
    )


def impute(m_prime: np.ndarray, m_t: np.ndarray) -> np.ndarray:
    """Fill pixels of M' lost in projection with M_t (no change there).

    m_prime, m_t : (H, W) float32 depth, mm, NaN = invalid. Returns (H, W) float32.
    """
    return np.where(np.isfinite(m_prime), m_prime, m_t).astype(np.float32)


def _square(px: int) -> np.ndarray:
    return np.ones((px, px), dtype=np.uint8)


def change_mask(m_prime: np.ndarray, m_t: np.ndarray, cfg: ChangeConfig) -> np.ndarray:
    """Cleaned change mask m = (M' - M_t) > threshold.

    m_prime, m_t : (H, W) float32 depth, mm, NaN = invalid (invalid -> unchanged).
    Returns (H, W) bool, True = changed (tissue removed along this pixel's ray).
    """
    if m_prime.shape != m_t.shape:
        raise InvalidInputError("m_prime", f"shape {m_prime.shape} differs from M_t {m_t.shape}")
    with np.errstate(invalid="ignore"):
        raw = (m_prime - m_t) > cfg.threshold_mm
    raw &= np.isfinite(m_prime) & np.isfinite(m_t)
    m = raw.astype(np.uint8)
    if cfg.open_px > 1:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _square(cfg.open_px))
    if cfg.close_px > 1:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _square(cfg.close_px))
        # Closing may bridge into pixels without data; only valid pixels can change.
        m &= (np.isfinite(m_prime) & np.isfinite(m_t)).astype(np.uint8)
    if cfg.min_area_px > 1 and m.any():
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < cfg.min_area_px)
        small = small[small != 0]
        if small.size:
            m[np.isin(labels, small)] = 0
    return m.astype(bool)
