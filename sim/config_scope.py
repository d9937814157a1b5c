"""Configuration of the endoscope itself: camera optics, tip light and sensor.

Sections ``camera`` (:class:`CameraConfig`: intrinsics, distortion, field stop,
vignetting), ``light`` (:class:`LightConfig`: the spot light beside the lens) and
``imaging`` (:class:`ImagingConfig`: exposure, noise, gamma, samples per pixel) of
:class:`sim.config.SimConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chisel.core.config import check_fields
from chisel.core.errors import CameraError
from chisel.core.geometry import Camera
from chisel.io.undistort import check_lens_model
from sim.config_checks import check
from sim.errors import ConfigError

MAX_IMAGE_SIDE = 8192
"""Largest image width/height in pixels: beyond it the per-pixel ray arrays exhaust memory."""


@dataclass(frozen=True)
class CameraConfig:
    """Endoscope camera: pinhole intrinsics, OpenCV distortion, field stop, vignetting."""

    width: int = 320
    """Image width in pixels."""
    height: int = 256
    """Image height in pixels."""
    fov_deg: float = 85.0
    """Diagonal field of view of the undistorted pinhole model, degrees (endoscopes: 70-90)."""
    principal_offset_px: tuple[float, float] = (2.5, -1.5)
    """Shift of the principal point (cx, cy) from the image centre, pixels."""
    dist: tuple[float, float, float, float, float] = (-0.18, 0.04, 0.0004, -0.0003, 0.0)
    """OpenCV distortion k1, k2, p1, p2, k3 (barrel: k1 < 0); all zeros = none."""
    K: tuple[tuple[float, float, float], ...] | None = None
    """Optional explicit 3x3 intrinsics (pixels); overrides ``fov_deg``/``principal_offset_px``."""
    field_stop_radius_frac: float = 0.75
    """Radius of the circular field stop as a fraction of half the image diagonal."""
    field_stop_center_offset_px: tuple[float, float] = (0.0, 0.0)
    """Offset of the field-stop centre from the image centre, pixels."""
    vignetting: float = 0.45
    """Brightness loss at the field-stop edge: gain = 1 - vignetting * (r / r_stop)^2."""
    near_clip_mm: float = 0.05
    """Near clip distance of the Mitsuba sensor, mm (the scope never gets this close)."""
    max_render_upscale: float = 3.0
    """Refuse distortions whose undistorted render grid exceeds this many times the pixels."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="camera")
        check(
            self.width >= 8 and self.height >= 8,
            "camera.width/height",
            f"image must be at least 8x8 pixels, got {self.width}x{self.height}",
        )
        for name in ("width", "height"):
            check(
                getattr(self, name) <= MAX_IMAGE_SIDE,
                f"camera.{name}",
                f"must be at most {MAX_IMAGE_SIDE} pixels, got {getattr(self, name)}",
            )
        check(
            1.0 < self.fov_deg < 170.0, "camera.fov_deg", f"must be in (1, 170), got {self.fov_deg}"
        )
        check(
            0.05 <= self.field_stop_radius_frac <= 2.0,
            "camera.field_stop_radius_frac",
            f"must be in [0.05, 2], got {self.field_stop_radius_frac}",
        )
        check(
            0.0 <= self.vignetting < 1.0,
            "camera.vignetting",
            f"must be in [0, 1), got {self.vignetting}",
        )
        check(
            0.0 < self.near_clip_mm < 2.0,
            "camera.near_clip_mm",
            f"must be in (0, 2) mm, got {self.near_clip_mm}",
        )
        check(
            self.max_render_upscale >= 1.0,
            "camera.max_render_upscale",
            f"must be >= 1, got {self.max_render_upscale}",
        )
        if self.K is not None:
            K = np.asarray(self.K, dtype=float)
            check(K.shape == (3, 3), "camera.K", f"expected a 3x3 matrix, got shape {K.shape}")
        camera = self.camera()  # validates K and dist through chisel.core.geometry.Camera
        # The bound a sequence.json is read with, so that every render can be read back.
        check(
            camera.principal_point_in_image,
            "camera.K" if self.K is not None else "camera.principal_offset_px",
            f"principal point ({camera.cx:g}, {camera.cy:g}) lies outside the "
            f"{self.width}x{self.height} image: the intrinsics do not match the image size",
        )
        try:  # depth is rendered at every pixel, so the lens must hold up to the corners
            check_lens_model(camera, None, "camera.dist")
        except CameraError as exc:
            raise ConfigError("camera.dist", exc.problem) from None

    def camera(self) -> Camera:
        """The :class:`chisel.core.geometry.Camera` this configuration describes."""
        dist = np.asarray(self.dist, dtype=np.float64)
        if self.K is not None:
            return Camera(int(self.width), int(self.height), np.asarray(self.K, float), dist)
        return Camera.from_fov(
            int(self.width),
            int(self.height),
            float(self.fov_deg),
            (float(self.principal_offset_px[0]), float(self.principal_offset_px[1])),
            dist,
        )

    def field_stop(self) -> tuple[float, float, float]:
        """(centre u, centre v, radius) of the field stop, pixels."""
        cu = (self.width - 1) / 2.0 + self.field_stop_center_offset_px[0]
        cv = (self.height - 1) / 2.0 + self.field_stop_center_offset_px[1]
        r = self.field_stop_radius_frac * 0.5 * math.hypot(self.width, self.height)
        return cu, cv, r


@dataclass(frozen=True)
class LightConfig:
    """Spot light at the scope tip, moving with the camera (near-field, inverse square)."""

    offset_mm: tuple[float, float, float] = (0.0, 1.2, 0.0)
    """Light position in the camera frame (OpenCV axes), mm: beside the lens, not on it."""
    intensity: float = 500.0
    """Radiant intensity on the axis (linear units per steradian); irradiance = I / d^2."""
    cutoff_deg: float = 80.0
    """Half-angle where the spot light's cone ends, degrees."""
    beam_width_deg: float = 60.0
    """Half-angle of the spot's full-intensity core, degrees (smooth falloff beyond)."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="light")
        check(
            float(np.linalg.norm(self.offset_mm)) < 2.0,
            "light.offset_mm",
            "the light must sit within 2 mm of the optical centre (inside the scope's clearance)",
        )
        check(self.intensity > 0, "light.intensity", f"must be > 0, got {self.intensity}")
        check(
            0 < self.beam_width_deg <= self.cutoff_deg < 90,
            "light.beam_width_deg/cutoff_deg",
            f"need 0 < beam_width <= cutoff < 90, got {self.beam_width_deg}, {self.cutoff_deg}",
        )


@dataclass(frozen=True)
class ImagingConfig:
    """Sensor model applied after rendering: exposure, noise, gamma; and the sampling budget."""

    spp: int = 16
    """Samples per pixel of the RGB render (direct lighting)."""
    exposure: float = 1.0
    """Linear gain applied to rendered radiance before the sensor noise."""
    shot_noise: float = 0.003
    """Shot-noise scale: std = sqrt(shot_noise * signal), signal in [0, 1]."""
    read_noise: float = 0.002
    """Read-noise std, in [0, 1] signal units."""
    gamma: float = 2.2
    """Display gamma applied before 8-bit quantisation."""
    auto_exposure: bool = True
    """Scale each frame so the mean signal inside the field stop is ``ae_target`` (like a
    real endoscope camera's auto exposure, gain limited to [0.05, 20]); ``exposure`` then
    multiplies that gain."""
    ae_target: float = 0.2
    """Auto-exposure target: mean linear signal inside the field stop."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="imaging")
        check(1 <= self.spp <= 4096, "imaging.spp", f"must be in [1, 4096], got {self.spp}")
        check(self.exposure > 0, "imaging.exposure", f"must be > 0, got {self.exposure}")
        check(
            self.shot_noise >= 0 and self.read_noise >= 0, "imaging.*_noise", "noise must be >= 0"
        )
        check(0.5 <= self.gamma <= 4.0, "imaging.gamma", f"must be in [0.5, 4], got {self.gamma}")
        check(
            0.0 < self.ae_target < 1.0,
            "imaging.ae_target",
            f"must be in (0, 1), got {self.ae_target}",
        )
