"""Aligning the model's render to the frame by shading: a pose signal with no depth network.

An endoscope carries its light at the lens, so the radiance of a matte surface seen in
the frame falls as ``cos(theta) / r^2`` (theta between the surface normal and the ray,
r the distance along it). The model's depth render at a pose predicts that pattern from
geometry alone; where the pose is off by the tracker's error, the frame's pattern lies
shifted from the prediction. The shift is found by a masked normalised cross-correlation
(every integer shift in a window at once, by FFT) of the high-passed log luminance and
the high-passed log shading, and converted into the camera-side sideways translation that
moves the render onto the frame at the depth it looks at; a step's frames share one
correction, their median. Unlike registration of an estimate to the model, no network's
shape error can bias it (docs/results.md, thirty-eighth and thirty-ninth sessions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
import scipy.fft

from chisel.core.config import check_fields
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera

# sRGB-like encoding of the simulator's and most endoscopes' frames: undone before the
# log so that luminance ratios are radiance ratios.
DISPLAY_GAMMA = 2.2
# Below this mean 8-bit value a pixel is mostly sensor floor: no shading signal.
DARK_LEVEL = 0.5
# A shift must be supported by at least this share of the frame's pixels.
MIN_OVERLAP_FRACTION = 0.1


@dataclass(frozen=True)
class ShadingShift:
    """The image shift that best aligns the render's shading with the frame.

    dx_px, dy_px : the frame's pixel u shows what the render shows at u + (dx, dy).
    ncc : the masked normalised cross-correlation at that shift (-1..1); 0 with no shift
    found. n_px : pixels that supported it.
    """

    dx_px: int
    dy_px: int
    ncc: float
    n_px: int


@dataclass(frozen=True)
class ShadingConfig:
    """Correcting a step's tracked poses by the frames' shading (``UpdateConfig.shading``)."""

    align_by_shading: bool = False
    """Correct a step's tracked poses by the frames' shading before anything else sees
    them: each frame's image shift between the model's predicted shading and its own
    luminance, as a sideways camera translation at the depth it looks at; the step's
    median of those is a constant camera-side correction for all its frames (streaming:
    each frame corrected by the median of the frames two or more before it). Needs the
    frames' RGB, so it is off unless asked for; the workflow's experiments ask for it
    (``config/*.yaml``) in every row but the exact-depth ones: both network rows gained
    14-27 % on held-out seeds (the paper's row 8 % on seeds 0-4, the change-aware row
    level there) and two of ten seeds lost at every step; the registration ablation
    gained 12 % and the sweep-only row 5 % on seeds 0-4; the exact-depth row lost 3 %
    (docs/results.md, thirty-ninth to forty-first sessions)."""
    shading_max_shift_px: int = 16
    """Image shifts up to this many pixels each way are searched."""
    shading_sigma_px: float = 12.0
    """The high pass's Gaussian: albedo and the light's fall-off vary slower than this."""
    shading_min_ncc: float = 0.1
    """A frame whose best shift correlates less than this gives no translation."""

    def __post_init__(self) -> None:
        check_fields(self, "shading")
        if not 1 <= self.shading_max_shift_px <= 128:
            raise InvalidInputError(
                "shading.shading_max_shift_px",
                f"must be in [1, 128], got {self.shading_max_shift_px}",
            )
        if not (np.isfinite(self.shading_sigma_px) and 0.5 <= self.shading_sigma_px <= 100.0):
            raise InvalidInputError(
                "shading.shading_sigma_px", f"must be in [0.5, 100] px, got {self.shading_sigma_px}"
            )
        if not (np.isfinite(self.shading_min_ncc) and -1.0 <= self.shading_min_ncc <= 1.0):
            raise InvalidInputError(
                "shading.shading_min_ncc", f"must be in [-1, 1], got {self.shading_min_ncc}"
            )


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _log_shading_kernel(
    z: np.ndarray, rays: np.ndarray, out: np.ndarray, ok: np.ndarray
) -> None:  # pragma: no cover - compiled
    H, W = z.shape
    for v in range(1, H - 1):
        for u in range(1, W - 1):
            zc, zl, zr, zt, zb = z[v, u], z[v, u - 1], z[v, u + 1], z[v - 1, u], z[v + 1, u]
            # NaN fails both comparisons: one test for "finite and in front of the camera".
            if not (
                0.0 < zc < math.inf
                and 0.0 < zl < math.inf
                and 0.0 < zr < math.inf
                and 0.0 < zt < math.inf
                and 0.0 < zb < math.inf
            ):
                continue
            # Central differences of the back-projected points P = z * ray along u and v.
            ax = zr * rays[v, u + 1, 0] - zl * rays[v, u - 1, 0]
            ay = zr * rays[v, u + 1, 1] - zl * rays[v, u - 1, 1]
            az = zr * rays[v, u + 1, 2] - zl * rays[v, u - 1, 2]
            bx = zb * rays[v + 1, u, 0] - zt * rays[v - 1, u, 0]
            by = zb * rays[v + 1, u, 1] - zt * rays[v - 1, u, 1]
            bz = zb * rays[v + 1, u, 2] - zt * rays[v - 1, u, 2]
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            n_len = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
            px, py, pz = zc * rays[v, u, 0], zc * rays[v, u, 1], zc * rays[v, u, 2]
            r = max(math.sqrt(px * px + py * py + pz * pz), 1e-6)
            # Grazing pixels would send the log to -inf; the floor keeps them in the pattern.
            cos = min(max(abs(nx * px + ny * py + nz * pz) / (n_len * r), 0.05), 1.0)
            out[v, u] = math.log(cos / (r * r))
            ok[v, u] = True


def log_shading(depth_mm: np.ndarray, rays_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """log(cos / r^2) of a light at the camera centre, from a z-depth map.

    depth_mm : (H, W) z-depth, NaN = no surface; rays_cam : (H, W, 3) rays with z = 1
    (``Camera.rays_cam()``). Returns ((H, W) float32 log shading, (H, W) bool valid):
    normals from central differences of the back-projected points, so the border and
    pixels beside a hole are invalid. One compiled pass over the pixels: half the time of
    the same arithmetic on whole arrays (1.6 against 2.9 ms at 320x256), which matters at
    a streaming frame rate, and the GIL released for a thread that overlaps it.
    """
    z = np.ascontiguousarray(depth_mm, dtype=np.float64)
    rays = np.ascontiguousarray(rays_cam, dtype=np.float64)
    if rays.shape != (*z.shape, 3):
        raise InvalidInputError("log_shading", f"rays {rays.shape} for a depth map {z.shape}")
    out = np.zeros(z.shape, np.float32)
    ok = np.zeros(z.shape, np.bool_)
    _log_shading_kernel(z, rays, out, ok)
    return out, ok


# log of the mean of three 8-bit channels, for every possible channel sum: the frame's
# log luminance is a table look-up (the same float32 values as computing it per pixel).
_LOG_MEAN_OF_SUM = (
    DISPLAY_GAMMA * np.log(np.arange(3 * 255 + 1, dtype=np.float32) / np.float32(3) + 1.0)
).astype(np.float32)


def log_luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 log of the frame's linear luminance (gamma undone), from uint8 RGB."""
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        total = rgb[..., 0].astype(np.uint16)
        total += rgb[..., 1]
        total += rgb[..., 2]
        return _LOG_MEAN_OF_SUM[total]
    mean = rgb.astype(np.float32).mean(axis=-1)
    return (DISPLAY_GAMMA * np.log(mean + 1.0)).astype(np.float32)


def high_pass(
    image: np.ndarray, valid: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """``image`` minus its masked Gaussian mean (normalised convolution): albedo and the
    light's fall-off vary slowly, the geometry's shading does not. Pixels whose
    neighbourhood is mostly invalid become invalid. Returns (float32 image, bool valid)."""
    m = valid.astype(np.float32)
    x = np.where(valid, image, 0.0).astype(np.float32)
    # Weights and values blurred as one two-channel image: one pass instead of two.
    wb = cv2.GaussianBlur(cv2.merge([m, x]), (0, 0), sigma_px)
    w, b = wb[..., 0], wb[..., 1]
    keep = valid & (w > 0.3)
    return np.where(keep, x - b / np.maximum(w, 1e-6), 0.0).astype(np.float32), keep


def masked_ncc(
    a: np.ndarray, ma: np.ndarray, b: np.ndarray, mb: np.ndarray, max_shift_px: int
) -> tuple[np.ndarray, np.ndarray]:
    """Masked normalised cross-correlation of ``a`` with ``b`` shifted, for every integer
    shift d with |dx|, |dy| <= max_shift_px (Padfield, "Masked object registration in the
    Fourier domain", 2012): ncc[dy + S, dx + S] compares a(u) with b(u + d) over the pixels
    where both masks hold. Returns ((2S+1, 2S+1) float64 ncc, NaN where undefined;
    (2S+1, 2S+1) overlap pixel counts)."""
    S = int(max_shift_px)
    H, W = a.shape
    # Zero padding to a size with small prime factors only: 320x256 + 16 is 336x272, and
    # 272 = 16 * 17 takes pocketfft 1.6x as long as 288.
    shape = (scipy.fft.next_fast_len(H + S, real=True), scipy.fft.next_fast_len(W + S, real=True))
    # The overlap counts in double precision, so that they are exact at any image size
    # (float32 is off by 0.5 at 1920x1080); the sums of values in single precision, a
    # third of the time: the NCC agrees with double precision to 1e-8 at 320x256.
    A_m = np.conj(scipy.fft.rfft2(ma.astype(np.float64), s=shape))
    B_m = scipy.fft.rfft2(mb.astype(np.float64), s=shape)
    a = np.where(ma, a, 0.0).astype(np.float32)
    b = np.where(mb, b, 0.0).astype(np.float32)
    A = {"m": A_m.astype(np.complex64)}
    B = {"m": B_m.astype(np.complex64)}
    A.update({k: np.conj(scipy.fft.rfft2(x, s=shape)) for k, x in (("a", a), ("aa", a * a))})
    B.update({k: scipy.fft.rfft2(x, s=shape) for k, x in (("b", b), ("bb", b * b))})

    # c(d) = sum_u f(u) g(u + d) sits at the circular index d mod shape: no wrap for |d| <= S.
    window = np.ix_(
        np.r_[np.arange(shape[0] - S, shape[0]), np.arange(0, S + 1)],
        np.r_[np.arange(shape[1] - S, shape[1]), np.arange(0, S + 1)],
    )

    def corr(ka: str, kb: str) -> np.ndarray:
        return scipy.fft.irfft2(A[ka] * B[kb], s=shape)[window].astype(np.float64)

    n = np.rint(scipy.fft.irfft2(A_m * B_m, s=shape)[window])
    sa, sb = corr("a", "m"), corr("m", "b")
    saa, sbb, sab = corr("aa", "m"), corr("m", "bb"), corr("a", "b")
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sab - sa * sb / n
        var = (saa - sa * sa / n) * (sbb - sb * sb / n)
        ncc = np.where((n > 0) & (var > 0), cov / np.sqrt(var), np.nan)
    return ncc, n.astype(np.int64)


def shading_shift(
    rgb: np.ndarray,
    render_mm: np.ndarray,
    camera: Camera,
    mask: np.ndarray | None = None,
    cfg: ShadingConfig = ShadingConfig(),  # noqa: B008 - frozen dataclass
) -> ShadingShift:
    """The integer image shift aligning the render's shading with the frame's luminance.

    rgb : (H, W, 3) uint8 frame; render_mm : (H, W) z-depth of the model at the pose to
    correct, NaN = none; mask : the frame's valid pixels (None = all). A frame with too
    little overlap at every shift gives (0, 0) with ncc 0.
    """
    H, W = camera.height, camera.width
    if render_mm.shape != (H, W) or np.asarray(rgb).shape[:2] != (H, W):
        raise InvalidInputError(
            "shading_shift",
            f"frame {np.asarray(rgb).shape[:2]} and render {render_mm.shape} must both be "
            f"the camera's {(H, W)}",
        )
    lum = log_luminance(rgb)
    seen = lum > DISPLAY_GAMMA * np.log(1.0 + DARK_LEVEL)
    if mask is not None:
        seen &= mask
    a, ma = high_pass(lum, seen, cfg.shading_sigma_px)
    s, ms = log_shading(render_mm, camera.rays_cam())
    b, mb = high_pass(s, ms, cfg.shading_sigma_px)
    ncc, n = masked_ncc(a, ma, b, mb, cfg.shading_max_shift_px)
    ncc = np.where(n >= MIN_OVERLAP_FRACTION * H * W, ncc, np.nan)
    if not np.isfinite(ncc).any():
        return ShadingShift(0, 0, 0.0, 0)
    iy, ix = np.unravel_index(np.nanargmax(ncc), ncc.shape)
    S = int(cfg.shading_max_shift_px)
    return ShadingShift(int(ix) - S, int(iy) - S, float(ncc[iy, ix]), int(n[iy, ix]))


def translation_for_shift(
    camera: Camera, dx_px: float, dy_px: float, depth_mm: float
) -> np.ndarray:
    """(4, 4) camera-side correction C (``T_corrected = T @ C``, a pure sideways
    translation): surfaces at ``depth_mm`` that the camera at ``T`` saw at u + (dx, dy)
    the corrected camera sees at u. The tracker's errors at an endoscope's working
    distance are mostly translation: 0.2 mm of jitter at 10 mm moves the view as much as
    1.1 deg of rotation."""
    C = np.eye(4)
    C[0, 3] = dx_px * depth_mm / camera.fx
    C[1, 3] = dy_px * depth_mm / camera.fy
    return C


def shift_passes(sh: ShadingShift, cfg: ShadingConfig) -> bool:
    """Whether a frame's best shift counts: at least ``cfg.shading_min_ncc`` and inside
    the search window (one on its edge may have the true one beyond it, or be spurious)."""
    return (
        sh.ncc >= cfg.shading_min_ncc
        and max(abs(sh.dx_px), abs(sh.dy_px)) < cfg.shading_max_shift_px
    )


def shading_translation(
    rgb: np.ndarray,
    render_mm: np.ndarray,
    camera: Camera,
    mask: np.ndarray | None = None,
    cfg: ShadingConfig = ShadingConfig(),  # noqa: B008 - frozen dataclass
) -> np.ndarray | None:
    """One frame's camera-side sideways translation (3,) mm that moves the render onto
    its shading (:func:`translation_for_shift` at the render's median depth), or None
    when the frame gives none: the render holds no surface, or the best shift is weaker
    than ``cfg.shading_min_ncc`` or on the search window's edge (the true one may lie
    beyond it, or the match is spurious)."""
    finite = np.isfinite(render_mm)
    if not finite.any():
        return None
    sh = shading_shift(rgb, render_mm, camera, mask, cfg)
    if not shift_passes(sh, cfg):
        return None
    depth_mm = float(np.median(render_mm[finite]))
    return translation_for_shift(camera, sh.dx_px, sh.dy_px, depth_mm)[:3, 3]


def step_correction(translations: list[np.ndarray]) -> np.ndarray:
    """(4, 4) camera-side correction F (``T_corrected = T_tracked @ F``) of a step: the
    per-axis median of its frames' shading translations. The hand-eye error is the same
    in every frame of a step and the jitter is not: F takes the first, and a frame's own
    shift, which holds its jitter too, is not applied (turning every frame onto its own
    shading made the change-aware row 5 % worse in the table; docs/results.md,
    thirty-ninth session). Identity for no translation."""
    F = np.eye(4)
    if translations:
        F[:3, 3] = np.median(np.asarray(translations, dtype=np.float64), axis=0)
    return F
