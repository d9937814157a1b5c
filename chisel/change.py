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

from chisel.core.config import check_fields, check_ranges
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.geometry import Camera, invert_rigid
from chisel.fusion import distort
from chisel.io.limits import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE_PX

MIN_SCALE_PIXELS = 50
"""Fewest pixels valid in both the render and the estimate for a scale to be solved."""
NOISE_TAIL_RATIO = 3.0
"""The noise-adaptive threshold's spread is at most this many times the shallow side's."""
MAX_SCALE_PIXELS = 8000
"""About this many pixels (a regular stride) enter the scale's medians."""
MAX_CHANGE_MM = 1e3
"""Largest change threshold or visibility distance, mm: a metre is past any endoscopic
scene, so a larger value is a unit slip (um for mm) that would switch detection off."""
MAX_MIN_VIEWS = 10_000
"""Largest ``min_views``: a step holds tens of frames (24 in config/config.yaml); more
other frames than any step holds would refuse every change, silently."""
MAX_NOISE_K = 100.0
"""Largest ``noise_k``: 100 robust deviations put the threshold past any depth error,
switching detection off (3 is the default)."""


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
    min_views: int = 5
    """Batch multi-view check: a changed pixel needs at least this many *other* frames that
    see its old surface and also see it removed (0 = off, every frame trusted alone)."""
    min_agreement: float = 0.8
    """... and those must be at least this fraction of the other frames that see it."""
    visible_mm: float = 1.0
    """Another frame sees a pixel's old surface point when its own render of M_t reaches
    that point within this distance, mm."""
    contradict_fraction: float = 0.5
    """Multi-view check: another frame contradicts a change only when its estimate is deeper
    than its render by at most this fraction of its threshold; between that and the
    threshold (an oblique view of the cut's side face just behind the old surface) its
    view is ambiguous and not counted (1.0 = the strict rule)."""
    noise_k: float = 3.0
    """Noise-adaptive threshold: per frame, max(threshold_mm, noise_k * sigma) with sigma
    the robust spread of M' - M_t (see :func:`frame_threshold`) (0 = off: fixed threshold)."""
    noise_with_depth: bool = False
    """The noise-adaptive threshold grows with the render's depth: per pixel
    max(threshold_mm, noise_k * sigma_rel * M_t), sigma_rel the robust spread of
    (M' - M_t) / M_t. A learnt estimate's error is a fraction of the depth, so one
    threshold per frame is set by its far field and hides a removal nearby
    (:func:`frame_threshold`)."""

    def __post_init__(self) -> None:
        check_fields(self, "change")  # kinds, NaN and infinity
        d = MAX_CHANGE_MM
        checks = (
            ("threshold_mm", 0 < self.threshold_mm <= d, f"in (0, {d:g}] mm"),
            ("open_px", self.open_px >= 0, ">= 0"),
            ("close_px", self.close_px >= 0, ">= 0"),
            # A kernel wider than any image is meaningless, and OpenCV would allocate its square.
            ("open_px", self.open_px <= MAX_IMAGE_SIDE_PX,
             f"at most {MAX_IMAGE_SIDE_PX} px (the widest image read)"),
            ("close_px", self.close_px <= MAX_IMAGE_SIDE_PX,
             f"at most {MAX_IMAGE_SIDE_PX} px (the widest image read)"),
            ("min_area_px", 0 <= self.min_area_px <= MAX_IMAGE_PIXELS,
             f"in [0, {MAX_IMAGE_PIXELS}] px (the largest image read)"),
            ("min_views", 0 <= self.min_views <= MAX_MIN_VIEWS, f"in [0, {MAX_MIN_VIEWS}]"),
            ("min_agreement", 0 <= self.min_agreement <= 1, "in [0, 1]"),
            ("visible_mm", 0 < self.visible_mm <= d, f"in (0, {d:g}] mm"),
            ("contradict_fraction", 0 <= self.contradict_fraction <= 1, "in [0, 1]"),
            ("noise_k", 0 <= self.noise_k <= MAX_NOISE_K, f"in [0, {MAX_NOISE_K:g}]"),
        )  # fmt: skip
        check_ranges(self, "change", checks)


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


MAX_SHIFT_SCALE_RATIO = 2.0
"""A scale-and-shift fit is kept only when its scale is within this factor of the scale
alone: a view of nearly one depth (a wall seen head-on) makes the two collinear, and an
unconstrained fit could trade the scale for the shift (the collapse of issue 19)."""


def shift_to_render(
    render_mm: np.ndarray, estimate: np.ndarray, outlier_mm: float = 1.0, iterations: int = 4
) -> tuple[np.ndarray, float, float]:
    """A relative estimate shifted so that a scale alone maps it to the render.

    Monocular networks give depth up to scale *and* shift (Ranftl et al., MiDaS); fitting
    ``a * estimate + b ~= render_mm`` on unchanged pixels (least squares inside a robust band
    of max(outlier_mm, 2.5 sigma), removed tissue lying outside it) and returning
    ``estimate + b / a`` lets the scale machinery work unchanged. Falls back to the estimate
    as it is (shift 0) when the fit is degenerate: its scale outside
    ``MAX_SHIFT_SCALE_RATIO`` of the scale alone (:func:`solve_scale`'s rule, on the same
    pixels), or too few pixels. Returns (shifted estimate (H, W) float32 with NaN where it
    is not positive, the shift in the estimate's units, the scale that maps it to the
    render).
    """
    r = np.asarray(render_mm, dtype=np.float32)
    e = np.asarray(estimate, dtype=np.float32)
    # A regular pixel stride (as solve_scale): ~10^4 pixels fit two numbers as well as 10^5.
    stride = max(1, int(np.ceil(np.sqrt(r.size / MAX_SCALE_PIXELS))))
    rs, es = r[::stride, ::stride], e[::stride, ::stride]
    valid = np.isfinite(rs) & np.isfinite(es) & (es > 0) & (rs > 0)
    if int(valid.sum()) < MIN_SCALE_PIXELS:
        raise EmptyResultError(
            f"only {int(valid.sum())} pixels are valid in both the render and the estimate "
            f"(need {MIN_SCALE_PIXELS}): cannot fit a scale and shift"
        )
    rv, ev = rs[valid].astype(np.float64), es[valid].astype(np.float64)
    s, _ = solve_scale(rv[None, :], ev[None, :], outlier_mm)
    unchanged = np.asarray(estimate, dtype=np.float32), 0.0, s
    resid = s * ev - rv
    keep = np.abs(resid) <= max(outlier_mm, 3.0 * 1.4826 * float(np.median(np.abs(resid))))
    a, b = s, 0.0
    for _ in range(iterations):
        n = int(keep.sum())
        if n < MIN_SCALE_PIXELS:
            return unchanged
        x, y = ev[keep], rv[keep]
        mx, my = float(x.mean()), float(y.mean())
        var = float(((x - mx) ** 2).sum())
        if var <= 0.0:
            return unchanged
        a = float(((x - mx) * (y - my)).sum()) / var
        b = my - a * mx
        resid = a * ev + b - rv
        keep = np.abs(resid) <= max(
            outlier_mm, 2.5 * 1.4826 * float(np.median(np.abs(resid[keep])))
        )
    if not (s / MAX_SHIFT_SCALE_RATIO <= a <= s * MAX_SHIFT_SCALE_RATIO):
        return unchanged
    shift = float(b / a)
    out = e + np.float32(shift)
    out[~(out > 0)] = np.nan
    return out, shift, float(a)


@numba.njit(cache=True, nogil=True)
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


@numba.njit(cache=True, inline="always")
def _pixel_of(X, Y, Z, fx, fy, cx, cy, k1, k2, p1, p2, k3):
    """Nearest raw (distorted) pixel (u, v) of a camera-frame point with Z > 0."""
    xd, yd = distort(X / Z, Y / Z, k1, k2, p1, p2, k3)
    return int(np.floor(fx * xd + cx + 0.5)), int(np.floor(fy * yd + cy + 0.5))


@numba.njit(cache=True, inline="always")
def _apply(T, n, x, y, z):
    """Point (x, y, z) through the rigid transform ``T[n]`` of a stack (N, 4, 4)."""
    return (
        T[n, 0, 0] * x + T[n, 0, 1] * y + T[n, 0, 2] * z + T[n, 0, 3],
        T[n, 1, 0] * x + T[n, 1, 1] * y + T[n, 1, 2] * z + T[n, 1, 3],
        T[n, 2, 0] * x + T[n, 2, 1] * y + T[n, 2, 2] * z + T[n, 2, 3],
    )


@numba.njit(cache=True, inline="always")
def _project_into(T_cw, j, X, Y, Z, fx, fy, cx, cy, k1, k2, p1, p2, k3, W, H):
    """World point -> (u, v, z-depth) in frame ``j``; u = -1 outside its image or behind it."""
    xc, yc, zc = _apply(T_cw, j, X, Y, Z)
    if zc <= 1e-3:
        return -1, -1, zc
    uu, vv = _pixel_of(xc, yc, zc, fx, fy, cx, cy, k1, k2, p1, p2, k3)
    if uu < 0 or vv < 0 or uu >= W or vv >= H:
        return -1, -1, zc
    return uu, vv, zc


@numba.njit(cache=True, nogil=True)
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
            uu, vv = _pixel_of(X, Y, Z, fx, fy, cx, cy, k1, k2, p1, p2, k3)
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


def _morph(m: np.ndarray, op: int, px: int) -> np.ndarray:
    """OpenCV morphology ``op`` of a uint8 mask with a ``px`` x ``px`` square (uint8 out)."""
    return cv2.morphologyEx(m, op, _square(px))


def frame_threshold(m_raw: np.ndarray, m_t: np.ndarray, cfg: ChangeConfig) -> tuple[float, float]:
    """The change threshold of one frame: (threshold_mm, per_mm).

    The threshold at a pixel is ``max(threshold_mm, per_mm * M_t)`` (:func:`threshold_map`).
    Without ``cfg.noise_with_depth`` it is one number, ``cfg.threshold_mm`` raised to
    ``cfg.noise_k`` robust standard deviations of the noise of M' - M_t (``per_mm`` = 0).
    With it, ``per_mm`` is ``noise_k`` robust deviations of (M' - M_t) / M_t and
    ``threshold_mm`` is ``cfg.threshold_mm``. ``noise_k`` = 0: the fixed threshold.

    m_raw : (H, W) float32 M' before imputation, mm, NaN = lost; m_t : (H, W) float32 M_t.
    """
    floor = float(cfg.threshold_mm)
    if cfg.noise_k <= 0:
        return floor, 0.0
    sigma = noise_sigma(m_raw, m_t, relative=cfg.noise_with_depth)
    if sigma is None:
        return floor, 0.0
    if cfg.noise_with_depth:
        return floor, cfg.noise_k * sigma
    return max(floor, cfg.noise_k * sigma), 0.0


def threshold_map(threshold_mm: float, per_mm: float, m_t: np.ndarray) -> np.ndarray:
    """(H, W) float32 change threshold per pixel, mm: ``max(threshold_mm, per_mm * M_t)``
    (NaN where M_t is)."""
    m_t = np.asarray(m_t, dtype=np.float32)
    return np.maximum(np.float32(threshold_mm), np.float32(per_mm) * m_t)


def typical_threshold(threshold_mm: float, per_mm: float, m_t: np.ndarray) -> float:
    """One frame's threshold as a number, mm: at the median depth of its render (the
    threshold itself when it does not grow with depth)."""
    if per_mm <= 0:
        return float(threshold_mm)
    z = np.asarray(m_t)[np.isfinite(m_t)]
    return float(threshold_mm) if z.size == 0 else max(threshold_mm, per_mm * float(np.median(z)))


def noise_sigma(m_raw: np.ndarray, m_t: np.ndarray, relative: bool = False) -> float | None:
    """Robust standard deviation of the noise of M' - M_t, mm (None: too few pixels);
    ``relative``: of (M' - M_t) / M_t, a fraction.

    m_raw : (H, W) float32 M' before imputation, mm, NaN = lost; m_t : (H, W) float32 M_t.
    """
    r = (m_raw - m_t)[::2, ::2]
    if relative:
        r = r / m_t[::2, ::2]
    r = r[np.isfinite(r)]
    neg = -r[r < 0]
    if neg.size < MIN_SCALE_PIXELS:
        return None
    # The spread of all residuals (1.4826 MAD) measures the estimate's noise when most of the
    # view is unchanged, heavy tails included. A large real change inflates it too, but only
    # on the deeper side (tissue is only removed), so it is capped at a few times the spread
    # of the shallower half, which is noise alone (0.6745 sigma is a half-normal's median).
    sigma_all = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    sigma_neg = 1.4826 * float(np.median(neg))
    return min(sigma_all, NOISE_TAIL_RATIO * sigma_neg)


def change_mask(
    m_prime: np.ndarray,
    m_t: np.ndarray,
    cfg: ChangeConfig,
    threshold_mm: float | np.ndarray | None = None,
) -> np.ndarray:
    """Cleaned change mask m = (M' - M_t) > threshold.

    m_prime, m_t : (H, W) float32 depth, mm, NaN = invalid (invalid -> unchanged).
    threshold_mm : the frame's threshold, a number or (H, W) per pixel (:func:`threshold_map`)
    (None = ``cfg.threshold_mm``).
    Returns (H, W) bool, True = changed (tissue removed along this pixel's ray).
    """
    if m_prime.shape != m_t.shape:
        raise InvalidInputError("m_prime", f"shape {m_prime.shape} differs from M_t {m_t.shape}")
    thr: float | np.ndarray = cfg.threshold_mm if threshold_mm is None else threshold_mm
    if np.ndim(thr) == 0:
        thr = float(thr)
    elif np.shape(thr) != m_t.shape:
        raise InvalidInputError("threshold_mm", f"shape {np.shape(thr)} is not M_t's {m_t.shape}")
    with np.errstate(invalid="ignore"):
        raw = (m_prime - m_t) > thr
    raw &= np.isfinite(m_prime) & np.isfinite(m_t)
    m: np.ndarray = raw.astype(np.uint8)
    if cfg.open_px > 1:
        m = _morph(m, cv2.MORPH_OPEN, cfg.open_px)
    if cfg.close_px > 1:
        m = _morph(m, cv2.MORPH_CLOSE, cfg.close_px)
        # Closing may bridge into pixels without data; only valid pixels can change.
        m &= (np.isfinite(m_prime) & np.isfinite(m_t)).astype(np.uint8)
    return clean_mask(m.astype(bool), cfg)


def clean_mask(mask: np.ndarray, cfg: ChangeConfig) -> np.ndarray:
    """Drop changed components smaller than ``cfg.min_area_px``; (H, W) bool in and out."""
    m = np.asarray(mask, dtype=np.uint8)
    if cfg.min_area_px > 1 and m.any():
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < cfg.min_area_px)
        small = small[small != 0]
        if small.size:
            m[np.isin(labels, small)] = 0
    return m.astype(bool)


@numba.njit(parallel=True, cache=True, nogil=True)
def _consistency_kernel(masks, renders, diffs, rays, T_wc, T_cw, used, fx, fy, cx, cy, dist,
                        threshold_mm, per_mm, visible_mm, contradict, support, observed):  # fmt: skip
    N, H, W = masks.shape
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for i in numba.prange(N):
        if not used[i]:
            continue
        for v in range(H):
            for u in range(W):
                if not masks[i, v, u]:
                    continue
                d = renders[i, v, u]
                # The old surface point this pixel claims was removed, in world mm.
                x = rays[v, u, 0] * d
                y = rays[v, u, 1] * d
                z = rays[v, u, 2] * d
                X, Y, Z = _apply(T_wc, i, x, y, z)
                n_sup = 0
                n_obs = 0
                for j in range(N):
                    if j == i or not used[j]:
                        continue
                    uu, vv, zc = _project_into(
                        T_cw, j, X, Y, Z, fx, fy, cx, cy, k1, k2, p1, p2, k3, W, H
                    )
                    if uu < 0:
                        continue
                    rj = renders[j, vv, uu]
                    # Frame j sees the same old surface point (not occluded, not beside it)...
                    if not (abs(rj - zc) <= visible_mm):
                        continue
                    dj = diffs[j, vv, uu]
                    if not (dj == dj):  # NaN: no estimate there (lost in projection)
                        continue
                    # ...and its own estimate also says the surface moved away (support), or
                    # says it is still there (contradiction); in between it is ambiguous
                    # (e.g. an oblique view of the cut's side face just behind) and not counted.
                    thr = max(threshold_mm[j], per_mm[j] * rj)
                    if dj > thr:
                        n_sup += 1
                        n_obs += 1
                    elif dj <= contradict * thr:
                        n_obs += 1
                support[i, v, u] = n_sup
                observed[i, v, u] = n_obs


def multiview_support(
    masks: np.ndarray,
    renders_mm: np.ndarray,
    estimates_mm: np.ndarray,
    camera: Camera,
    T_world_from_cams: np.ndarray,
    used: np.ndarray,
    threshold_mm: float | np.ndarray,
    visible_mm: float,
    contradict_fraction: float = 1.0,
    per_mm: float | np.ndarray = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """How many other frames confirm each changed pixel: (support, observed), (N, H, W) int32.

    masks : (N, H, W) bool change masks of one step's frames.
    renders_mm : (N, H, W) float32 M_t at each frame's pose, mm, NaN = no surface.
    estimates_mm : (N, H, W) float32 registered estimates M' re-projected into each frame
        *before* imputation, mm, NaN = no estimate.
    T_world_from_cams : (N, 4, 4) float64 poses the renders and estimates are expressed in.
    used : (N,) bool, frames whose registration succeeded (the others neither vote nor count).
    For a changed pixel of frame i, its old surface point (M_t) is projected into every other
    used frame j. Frame j *observes* the point when its own render reaches it there (within
    ``visible_mm``: not occluded, not beside a silhouette) and its estimate is valid; it
    *supports* the change when its estimate is deeper than its render by its threshold there,
    ``max(threshold_mm, per_mm * render)`` (each a number, or (N,) per frame:
    :func:`frame_threshold`), and it contradicts it when the estimate is
    deeper by at most ``contradict_fraction`` times that threshold; an observation in
    between is ambiguous and counts in neither (``observed`` = supporters + contradictors;
    1.0 = every observation counts).
    Counts are 0 at unchanged pixels.
    """
    m = np.ascontiguousarray(masks, dtype=np.bool_)
    N = len(m)
    for name, a in (("renders_mm", renders_mm), ("estimates_mm", estimates_mm)):
        if np.shape(a) != m.shape:
            raise InvalidInputError(name, f"shape {np.shape(a)} differs from masks {m.shape}")
    P = np.asarray(T_world_from_cams, dtype=np.float64)
    if P.shape != (N, 4, 4) or np.shape(used) != (N,):
        raise InvalidInputError("T_world_from_cams", f"expected ({N}, 4, 4) poses and ({N},) used")
    if m.shape[1:] != camera.shape:
        raise InvalidInputError(
            "masks", f"image shape {m.shape[1:]} is not the camera's {camera.shape}"
        )
    r = np.ascontiguousarray(renders_mm, dtype=np.float32)
    diffs = np.ascontiguousarray(estimates_mm, dtype=np.float32) - r
    support = np.zeros(m.shape, dtype=np.int32)
    observed = np.zeros(m.shape, dtype=np.int32)
    _consistency_kernel(
        m, r, diffs, np.ascontiguousarray(camera.rays_cam()), np.ascontiguousarray(P),
        np.ascontiguousarray(np.stack([invert_rigid(T) for T in P])) if N else P,
        np.ascontiguousarray(used, dtype=np.bool_), camera.fx, camera.fy, camera.cx, camera.cy,
        np.ascontiguousarray(camera.dist, dtype=np.float64),
        np.broadcast_to(np.asarray(threshold_mm, dtype=np.float64), (N,)).copy(),
        np.broadcast_to(np.asarray(per_mm, dtype=np.float64), (N,)).copy(),
        float(visible_mm), float(contradict_fraction), support, observed,
    )  # fmt: skip
    return support, observed
