"""Intraoperative image effects on linear radiance: cautery smoke, motion blur, lens smear.

All act between the renderer's linear radiance and the sensor model, so noise, exposure
and gamma apply to them as to a real camera. Each is seeded (same seed, same bytes) and
each at zero strength is switched off: the frame then takes exactly the path (and the
bytes) of a render without it.

- **Smoke** (:func:`apply_smoke`): a calibrated screen-space approximation of a
  participating medium, not Mitsuba's volumetric path tracer. Light leaves the tip (next
  to the lens), crosses the smoke to the tissue and back, so the tissue's radiance is
  attenuated by ``exp(-2 sigma z)`` (``z`` the visible z-depth, mm) and the light the smoke
  scatters back fills in ``albedo x mean radiance x (1 - exp(-2 sigma z))`` (a veil as
  bright as the lit scene, tinted ``color_rgb``). ``sigma`` varies over the image with a
  seeded smooth noise (patches). Why not a Mitsuba medium: the tip light is a delta spot
  light inside the medium, and a volumetric path tracer needs far more than 16 samples
  per pixel for a noise-free single-scattering veil (an order of magnitude slower than the
  one-bounce surface integrator); the screen-space form keeps the frame rate and has the
  two properties that matter for depth networks (depth-dependent contrast loss, a veil).
- **Motion blur** (:func:`blur_poses`): the average of ``subframes`` renders at poses
  interpolated (translation linear, rotation slerp) from this frame's pose back towards the
  previous frame's over the ``shutter`` fraction of the interval: the camera's own motion,
  exact parallax and occlusion (the ground-truth depth stays the frame's own pose, the end
  of the exposure). Chosen over a flow-based screen-space blur because it needs no flow
  field and handles disocclusions; it costs ``subframes`` renders.
- **Lens smear** (:func:`smear_mask`, :func:`apply_smear`): blood or mucus on the distal
  window: a seeded soft blob where the image is blurred and veiled; it starts with
  probability ``smear_probability`` per frame and stays ``smear_frames`` frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from sim.config import BlurConfig, LensConfig, SmokeConfig


@dataclass(frozen=True)
class FrameEffects:
    """The effects of one frame (built by :func:`frame_effects`)."""

    smoke: SmokeConfig
    """Smoke parameters; ``density_per_mm == 0`` = no smoke."""
    smoke_seed: int
    """Seed of the smoke's patch pattern."""
    blur: BlurConfig
    """Motion blur; ``shutter == 0`` = none."""
    T_prev: np.ndarray | None
    """(4, 4) float64 previous frame's true pose, mm (None: first frame, no blur)."""
    smear: np.ndarray | None
    """(H, W) float32 smear opacity in [0, 1], or None."""
    smear_blur_px: float = 6.0
    """Gaussian sigma under the smear, pixels."""

    @property
    def active(self) -> bool:
        """True when any effect changes the frame."""
        return self.smoke.density_per_mm > 0 or self.blurred or self.smear is not None

    @property
    def blurred(self) -> bool:
        return self.blur.shutter > 0 and self.T_prev is not None


def _smooth_noise_2d(
    shape: tuple[int, int], scale_px: float, rng: np.random.Generator
) -> np.ndarray:
    """(H, W) float32 zero-mean, unit-std smooth noise with features of ``scale_px``."""
    h, w = shape
    gh = max(2, int(np.ceil(h / max(scale_px, 1.0))) + 2)
    gw = max(2, int(np.ceil(w / max(scale_px, 1.0))) + 2)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    out = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
    out -= out.mean()
    return out / max(float(out.std()), 1e-6)


def smoke_density(shape: tuple[int, int], cfg: SmokeConfig, seed: int) -> np.ndarray:
    """(H, W) float32 extinction coefficient, 1/mm: ``density x (1 + patchiness x noise)``, >= 0."""
    rng = np.random.default_rng([int(seed), 61])
    noise = _smooth_noise_2d(shape, cfg.scale_frac * shape[1], rng)
    return np.maximum(cfg.density_per_mm * (1.0 + cfg.patchiness * noise), 0.0).astype(np.float32)


def apply_smoke(
    radiance: np.ndarray, depth_mm: np.ndarray, sigma_per_mm: np.ndarray, cfg: SmokeConfig
) -> np.ndarray:
    """Smoke over linear radiance (see the module docstring).

    radiance : (H, W, 3) float32 linear. depth_mm : (H, W) float32 visible z-depth, NaN on
    a miss (treated as far: full veil). sigma_per_mm : (H, W) from :func:`smoke_density`.
    Returns (H, W, 3) float32; 0 stays 0 where the radiance is 0 outside the field stop.
    """
    inside = np.any(radiance > 0, axis=-1)
    z = np.where(np.isfinite(depth_mm), depth_mm, 1.0e3).astype(np.float32)
    trans = np.exp(-2.0 * sigma_per_mm * z)[..., None]
    mean = float(radiance[inside].mean()) if inside.any() else 0.0
    veil = np.float32(cfg.albedo * mean) * np.asarray(cfg.color_rgb, dtype=np.float32)
    out = radiance * trans + veil * (1.0 - trans)
    return np.where(inside[..., None], out, 0.0).astype(np.float32)


def blur_poses(T_prev: np.ndarray, T: np.ndarray, shutter: float, n: int) -> np.ndarray:
    """(n, 4, 4) float64 poses from ``T`` back towards ``T_prev`` over ``shutter`` of the way.

    Sub-frame ``j`` sits at ``s_j = shutter x j / (n - 1)`` (``s = 0`` is ``T`` itself):
    translation linear, rotation slerp.
    """
    s = shutter * np.arange(n) / (n - 1)
    rots = Rotation.from_matrix(np.stack([T[:3, :3], T_prev[:3, :3]]))
    R = Slerp([0.0, 1.0], rots)(s).as_matrix()
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = (1.0 - s)[:, None] * T[:3, 3] + s[:, None] * T_prev[:3, 3]
    return out


def smear_mask(shape: tuple[int, int], strength: float, seed: int) -> np.ndarray:
    """(H, W) float32 opacity of a lens smear: a soft irregular blob (~15-35 % of the
    image width), ``strength`` at its core."""
    h, w = shape
    rng = np.random.default_rng([int(seed), 67])
    cx, cy = rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h
    rx, ry = rng.uniform(0.15, 0.35, size=2) * w
    ang = rng.uniform(0.0, np.pi)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    du, dv = u - cx, v - cy
    a = (du * np.cos(ang) + dv * np.sin(ang)) / rx
    b = (-du * np.sin(ang) + dv * np.cos(ang)) / ry
    r = np.sqrt(a * a + b * b) + 0.35 * _smooth_noise_2d(shape, 0.1 * w, rng)
    m = np.clip(1.5 - 1.5 * r, 0.0, 1.0)
    return (strength * m * m * (3.0 - 2.0 * m)).astype(np.float32)


def apply_smear(radiance: np.ndarray, mask: np.ndarray, blur_px: float) -> np.ndarray:
    """Blur and veil the radiance under a smear ``mask`` ((H, W) opacity)."""
    inside = np.any(radiance > 0, axis=-1)
    blurred = cv2.GaussianBlur(radiance, (0, 0), sigmaX=float(blur_px))
    mean = float(radiance[inside].mean()) if inside.any() else 0.0
    m = mask[..., None]
    out = (1.0 - m) * radiance + m * (0.8 * blurred + 0.2 * np.float32(mean))
    return np.where(inside[..., None], out, 0.0).astype(np.float32)


def smear_schedule(n_frames: int, cfg: LensConfig, seed: int) -> np.ndarray:
    """(N,) int: the smear seed of each frame, -1 where the lens is clean.

    A smear starts at a clean frame with probability ``smear_probability`` and stays
    ``smear_frames`` frames. Zero probability or strength: all -1.
    """
    out = np.full(n_frames, -1, dtype=np.int64)
    if cfg.smear_probability <= 0 or cfg.smear_strength <= 0:
        return out
    rng = np.random.default_rng([int(seed), 71])
    starts = rng.random(n_frames) < cfg.smear_probability
    seeds = rng.integers(0, 2**31, size=n_frames)
    i = 0
    while i < n_frames:
        if starts[i]:
            out[i : i + cfg.smear_frames] = seeds[i]
            i += cfg.smear_frames
        else:
            i += 1
    return out


def apply_effects(
    radiance: np.ndarray, depth_visible_mm: np.ndarray, fx: FrameEffects
) -> np.ndarray:
    """Smoke, then the lens smear, on a frame's (already motion-blurred) linear radiance."""
    out = radiance
    if fx.smoke.density_per_mm > 0:
        sigma = smoke_density(radiance.shape[:2], fx.smoke, fx.smoke_seed)
        out = apply_smoke(out, depth_visible_mm, sigma, fx.smoke)
    if fx.smear is not None:
        out = apply_smear(out, fx.smear, fx.smear_blur_px)
    return out
