"""The endoscope's image formation after the renderer: field stop, vignetting, sensor.

Rendered linear radiance -> vignetting -> auto exposure x ``exposure`` gain -> shot + read noise ->
clip to [0, 1] -> display gamma -> uint8; pixels outside the circular field stop are black.
:func:`sensor_image` is the numpy model (``scalar_rgb``); on the JIT variants
``MeshRenderer.render`` runs the same model in drjit
(:meth:`sim.spot_direct.SpotDirectIntegrator.sensor`: same tone curve, same noise
statistics, noise drawn from a counter-based hash instead of numpy's generator).
"""

from __future__ import annotations

import numpy as np

from sim.config import CameraConfig, ImagingConfig


def field_stop_mask(cfg: CameraConfig) -> np.ndarray:
    """(H, W) bool, True inside the circular field stop."""
    cu, cv, r = cfg.field_stop()
    v, u = np.mgrid[0 : cfg.height, 0 : cfg.width].astype(np.float64)
    return (u - cu) ** 2 + (v - cv) ** 2 <= r * r


def vignetting_gain(cfg: CameraConfig) -> np.ndarray:
    """(H, W) float32 gain ``1 - vignetting * (r / r_stop)^2``, 0 outside the field stop."""
    cu, cv, r = cfg.field_stop()
    v, u = np.mgrid[0 : cfg.height, 0 : cfg.width].astype(np.float64)
    rr = ((u - cu) ** 2 + (v - cv) ** 2) / (r * r)
    gain = np.where(rr <= 1.0, 1.0 - cfg.vignetting * rr, 0.0)
    return gain.astype(np.float32)


def sensor_image(
    radiance: np.ndarray, gain: np.ndarray, cfg: ImagingConfig, rng: np.random.Generator
) -> np.ndarray:
    """Turn linear radiance into the 8-bit endoscope image.

    radiance : (H, W, 3) float32 linear RGB from the renderer.
    gain : (H, W) float32 vignetting gain (0 outside the field stop).
    Returns (H, W, 3) uint8 RGB.
    """
    signal = np.clip(radiance, 0.0, None) * gain[..., None]
    exposure = cfg.exposure
    if cfg.auto_exposure:
        inside = gain > 0
        mean = float(signal[inside].mean()) if inside.any() else 0.0
        exposure *= float(np.clip(cfg.ae_target / max(mean, 1e-9), 0.05, 20.0))
    signal = signal * np.float32(exposure)
    if cfg.shot_noise > 0 or cfg.read_noise > 0:
        std = np.sqrt(cfg.shot_noise * np.minimum(signal, 1.0) + cfg.read_noise**2)
        signal = signal + rng.standard_normal(signal.shape, dtype=np.float32) * std
    signal = np.clip(signal, 0.0, 1.0) ** (1.0 / cfg.gamma)
    out = np.rint(signal * 255.0).astype(np.uint8)
    out[gain <= 0] = 0
    return out
