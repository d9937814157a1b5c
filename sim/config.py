"""Simulator configuration: small frozen dataclasses, loadable from YAML.

A YAML file mirrors :class:`SimConfig`: one mapping per section (``camera``, ``light``,
``appearance``, ``cut``, ``imaging``, ``randomization``, ``tracking``, ``paths``, ``tools``,
``smoke``, ``blur``, ``lens``) plus ``seed``.
Missing keys keep their defaults; unknown keys are refused (:class:`ConfigError`), so a
typo never passes silently. ``config/sim_default.yaml`` lists every key with its default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from chisel.core.config import check_fields, load_config_file, to_plain
from chisel.core.config import config_from_dict as config_from_dict_of
from chisel.core.config import replace_in as replace_dotted
from chisel.core.errors import CameraError
from chisel.core.geometry import Camera
from chisel.io.undistort import check_lens_model
from sim.errors import ConfigError

Range = tuple[float, float]
ToolKind = Literal["forceps", "suction", "microdebrider"]

MAX_IMAGE_SIDE = 8192
"""Largest image width/height in pixels: beyond it the per-pixel ray arrays exhaust memory."""
MAX_FRAMES = 100_000
"""Largest number of frames (or evaluation poses) of one sequence."""
MIN_CLEARANCE_MM = 0.1
"""Smallest camera-to-tissue clearance of the paths, mm."""
MAX_SMOKE_DENSITY_PER_MM = 1.0
"""Densest smoke accepted, 1/mm: beyond it a 1 mm layer hides the tissue."""


def _check(cond: bool, name: str, problem: str) -> None:
    if not cond:
        raise ConfigError(name, problem)


def _check_range(name: str, r: Range, lo: float = -math.inf, hi: float = math.inf) -> None:
    _check(
        len(r) == 2 and all(math.isfinite(float(x)) for x in r),
        name,
        f"expected a [min, max] pair of finite numbers, got {list(r)}",
    )
    _check(lo <= r[0] <= r[1] <= hi, name, f"expected {lo} <= min <= max <= {hi}, got {list(r)}")


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
        _check(
            self.width >= 8 and self.height >= 8,
            "camera.width/height",
            f"image must be at least 8x8 pixels, got {self.width}x{self.height}",
        )
        for name in ("width", "height"):
            _check(
                getattr(self, name) <= MAX_IMAGE_SIDE,
                f"camera.{name}",
                f"must be at most {MAX_IMAGE_SIDE} pixels, got {getattr(self, name)}",
            )
        _check(
            1.0 < self.fov_deg < 170.0, "camera.fov_deg", f"must be in (1, 170), got {self.fov_deg}"
        )
        _check(
            0.05 <= self.field_stop_radius_frac <= 2.0,
            "camera.field_stop_radius_frac",
            f"must be in [0.05, 2], got {self.field_stop_radius_frac}",
        )
        _check(
            0.0 <= self.vignetting < 1.0,
            "camera.vignetting",
            f"must be in [0, 1), got {self.vignetting}",
        )
        _check(
            0.0 < self.near_clip_mm < 2.0,
            "camera.near_clip_mm",
            f"must be in (0, 2) mm, got {self.near_clip_mm}",
        )
        _check(
            self.max_render_upscale >= 1.0,
            "camera.max_render_upscale",
            f"must be >= 1, got {self.max_render_upscale}",
        )
        if self.K is not None:
            K = np.asarray(self.K, dtype=float)
            _check(K.shape == (3, 3), "camera.K", f"expected a 3x3 matrix, got shape {K.shape}")
        camera = self.camera()  # validates K and dist through chisel.core.geometry.Camera
        # The bound a sequence.json is read with, so that every render can be read back.
        _check(
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
        _check(
            float(np.linalg.norm(self.offset_mm)) < 2.0,
            "light.offset_mm",
            "the light must sit within 2 mm of the optical centre (inside the scope's clearance)",
        )
        _check(self.intensity > 0, "light.intensity", f"must be > 0, got {self.intensity}")
        _check(
            0 < self.beam_width_deg <= self.cutoff_deg < 90,
            "light.beam_width_deg/cutoff_deg",
            f"need 0 < beam_width <= cutoff < 90, got {self.beam_width_deg}, {self.cutoff_deg}",
        )


@dataclass(frozen=True)
class AppearanceConfig:
    """Wet mucosa: principled BSDF over a seeded 3D procedural colour/vessel texture."""

    albedo_rgb: tuple[float, float, float] = (0.75, 0.2, 0.13)
    """Mean diffuse colour of mucosa, linear RGB in [0, 1]."""
    color_variation: float = 0.18
    """Relative amplitude of the low-frequency colour variation (0 = uniform)."""
    variation_scale_mm: float = 4.0
    """Feature size of the colour variation, mm."""
    vessel_strength: float = 0.6
    """Blend weight of vessels at their centre line (0 = no vessels)."""
    vessel_scale_mm: float = 6.0
    """Spacing of the vessel network, mm."""
    vessel_width: float = 0.07
    """Vessel half-width in units of the vessel noise (0.03 thin .. 0.15 wide)."""
    vessel_rgb: tuple[float, float, float] = (0.35, 0.03, 0.03)
    """Colour of vessels, linear RGB."""
    roughness: float = 0.3
    """Principled BSDF roughness (low = sharp wet highlights)."""
    specular: float = 0.5
    """Principled BSDF specular amount (mucus film)."""
    texture_voxel_mm: float = 0.3
    """Voxel size of the baked 3D texture volume, mm (coarsened to fit ``max_texture_voxels``)."""
    max_texture_voxels: int = 6_000_000
    """Cap on the texture volume's voxel count (memory: 12 bytes per voxel)."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="appearance")
        for name in ("albedo_rgb", "vessel_rgb"):
            v = getattr(self, name)
            _check(
                len(v) == 3 and all(0.0 <= x <= 1.0 for x in v),
                f"appearance.{name}",
                f"expected 3 values in [0, 1], got {list(v)}",
            )
        _check(
            0.0 <= self.color_variation <= 1.0,
            "appearance.color_variation",
            f"must be in [0, 1], got {self.color_variation}",
        )
        _check(
            0.0 <= self.vessel_strength <= 1.0,
            "appearance.vessel_strength",
            f"must be in [0, 1], got {self.vessel_strength}",
        )
        _check(
            self.variation_scale_mm > 0 and self.vessel_scale_mm > 0,
            "appearance.*_scale_mm",
            "scales must be > 0 mm",
        )
        _check(
            0.0 < self.vessel_width < 1.0,
            "appearance.vessel_width",
            f"must be in (0, 1), got {self.vessel_width}",
        )
        _check(
            0.0 < self.roughness <= 1.0,
            "appearance.roughness",
            f"must be in (0, 1], got {self.roughness}",
        )
        _check(
            0.0 <= self.specular <= 1.0,
            "appearance.specular",
            f"must be in [0, 1], got {self.specular}",
        )
        _check(
            self.texture_voxel_mm > 0,
            "appearance.texture_voxel_mm",
            f"must be > 0, got {self.texture_voxel_mm}",
        )
        _check(
            self.max_texture_voxels >= 1000,
            "appearance.max_texture_voxels",
            f"must be >= 1000, got {self.max_texture_voxels}",
        )


@dataclass(frozen=True)
class CutConfig:
    """Faces a cut created (the phantom's ``cut_faces`` labels): raw, bleeding tissue.

    Rendered with a second colour volume baked like the mucosa's (same BSDF lobes, same
    roughness and specular: wet tissue), whose base colour is raw tissue with blood
    blotches. Phantoms without labels, and step 0, render as before."""

    enabled: bool = True
    """Give the labelled cut faces the cut material (false: mucosa everywhere)."""
    albedo_rgb: tuple[float, float, float] = (0.62, 0.12, 0.09)
    """Mean colour of raw tissue (cut mucosa, bone), linear RGB in [0, 1]."""
    blood_rgb: tuple[float, float, float] = (0.22, 0.01, 0.008)
    """Colour of blood on the cut, linear RGB in [0, 1]."""
    blood_strength: float = 0.75
    """Blend weight of blood at the blotches' centre (0 = no blood)."""
    blood_scale_mm: float = 1.5
    """Spacing of the blood blotches, mm."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="cut")
        for name in ("albedo_rgb", "blood_rgb"):
            v = getattr(self, name)
            _check(
                all(0.0 <= x <= 1.0 for x in v),
                f"cut.{name}",
                f"expected 3 values in [0, 1], got {list(v)}",
            )
        _check(
            0.0 <= self.blood_strength <= 1.0,
            "cut.blood_strength",
            f"must be in [0, 1], got {self.blood_strength}",
        )
        _check(self.blood_scale_mm > 0, "cut.blood_scale_mm", "must be > 0 mm")


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
        _check(1 <= self.spp <= 4096, "imaging.spp", f"must be in [1, 4096], got {self.spp}")
        _check(self.exposure > 0, "imaging.exposure", f"must be > 0, got {self.exposure}")
        _check(
            self.shot_noise >= 0 and self.read_noise >= 0, "imaging.*_noise", "noise must be >= 0"
        )
        _check(0.5 <= self.gamma <= 4.0, "imaging.gamma", f"must be in [0.5, 4], got {self.gamma}")
        _check(
            0.0 < self.ae_target < 1.0,
            "imaging.ae_target",
            f"must be in (0, 1), got {self.ae_target}",
        )


@dataclass(frozen=True)
class RandomizationConfig:
    """Ranges sampled once per render for training data (``sim dataset``); each a [min, max].

    The effect ranges (``tools_fraction``, ``smoke_*``, ``blur_*``, ``lens_*``) default to
    [0, 0], which keeps the section's own value (off unless configured there)."""

    enabled: bool = False
    """Draw appearance, light and sensor once per render from these ranges with the master
    seed (``sim dataset`` always does, once per phantom); off: the fixed values."""
    albedo_scale: Range = (0.8, 1.15)
    """Multiplier of the mucosa albedo."""
    hue_shift: Range = (-0.06, 0.06)
    """Shift of red towards green/blue in the albedo (fraction of the channel value)."""
    vessel_strength: Range = (0.25, 0.85)
    """Vessel blend weight."""
    roughness: Range = (0.15, 0.5)
    """BSDF roughness."""
    specular: Range = (0.3, 0.8)
    """BSDF specular amount."""
    light_scale: Range = (0.6, 1.6)
    """Multiplier of the light intensity."""
    exposure: Range = (0.7, 1.4)
    """Exposure gain."""
    shot_noise: Range = (0.0005, 0.01)
    """Shot-noise scale."""
    read_noise: Range = (0.0005, 0.006)
    """Read-noise std."""
    tools_fraction: Range = (0.0, 0.0)
    """Fraction of intraoperative frames in a tool episode (``tools.fraction``; drawn only
    where ``tools.enabled``)."""
    smoke_density_per_mm: Range = (0.0, 0.0)
    """Cautery smoke extinction, 1/mm (``smoke.density_per_mm``; 0 = off)."""
    blur_shutter: Range = (0.0, 0.0)
    """Motion-blur shutter fraction (``blur.shutter``; 0 = off)."""
    lens_smear_probability: Range = (0.0, 0.0)
    """Chance per frame that a lens smear starts (``lens.smear_probability``; 0 = off)."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="randomization")
        bounds = {
            "albedo_scale": (0.1, 3.0),
            "hue_shift": (-0.5, 0.5),
            "vessel_strength": (0.0, 1.0),
            "roughness": (0.01, 1.0),
            "specular": (0.0, 1.0),
            "light_scale": (0.01, 100.0),
            "exposure": (0.01, 100.0),
            "shot_noise": (0.0, 1.0),
            "read_noise": (0.0, 1.0),
            "tools_fraction": (0.0, 1.0),
            "smoke_density_per_mm": (0.0, MAX_SMOKE_DENSITY_PER_MM),
            "blur_shutter": (0.0, 1.0),
            "lens_smear_probability": (0.0, 1.0),
        }
        for name, (lo, hi) in bounds.items():
            _check_range(f"randomization.{name}", getattr(self, name), lo, hi)


@dataclass(frozen=True)
class TrackingConfig:
    """How the navigation system's reported poses differ from the true ones."""

    jitter_mm: float = 0.2
    """Per-frame optical-tracking jitter: std per axis of the translation, mm."""
    jitter_deg: float = 0.1
    """Per-frame jitter: std per axis of the rotation vector, degrees."""
    handeye_mm: float = 0.5
    """Constant hand-eye calibration error: translation magnitude, mm (random direction)."""
    handeye_deg: float = 0.5
    """Constant hand-eye calibration error: rotation angle, degrees (random axis)."""
    latency_frames: int = 0
    """Tracking latency: frame i reports the true pose of frame max(i - latency, 0)."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="tracking")
        for name in ("jitter_mm", "jitter_deg", "handeye_mm", "handeye_deg"):
            v = getattr(self, name)
            _check(v >= 0, f"tracking.{name}", f"must be a finite number >= 0, got {v}")
        _check(
            self.latency_frames >= 0,
            "tracking.latency_frames",
            f"must be >= 0, got {self.latency_frames}",
        )


@dataclass(frozen=True)
class PathConfig:
    """Camera paths: preoperative sweep, intraoperative sequences, evaluation poses."""

    clearance_mm: float = 2.0
    """Minimum distance of the optical centre from tissue, mm (4 mm scope shaft)."""
    preop_frames: int = 60
    """Frames of the preoperative sweep along the airway."""
    intraop_frames: int = 80
    """Frames per intraoperative sequence (one per surgical step)."""
    eval_poses: int = 8
    """Fixed evaluation poses viewing the ROI, the same for every step."""
    lookahead_mm: float = 10.0
    """During the sweep the camera looks at the path point this far ahead, mm."""
    turn_fraction: float = 0.3
    """Last fraction of the sweep over which the view turns from ahead to the target."""
    view_distance_mm: Range = (6.0, 16.0)
    """Distance of intraoperative/evaluation viewpoints from the target centre, mm."""
    viewpoint_spread_mm: float = 6.0
    """Radius of the ball around the approach point where viewpoints are drawn, mm."""
    aim_jitter_mm: float = 2.0
    """Random offset of the aim point around the target (kept inside the ROI box), mm."""
    keyframes: int = 5
    """Keyframes of an intraoperative path (a smooth spline runs through them)."""
    roll_deg: float = 20.0
    """Amplitude of the smooth roll of the scope about its axis, degrees."""
    up_hint: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """World direction the image's up (-y) starts closest to (then transported smoothly)."""
    max_tries: int = 200
    """Attempts at drawing a collision-free intraoperative path before giving up."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="paths")
        # Paths are sampled every clearance / 4 mm: a near-zero clearance would mean
        # millions of collision queries (and the scope tip is ~2 mm in radius anyway).
        _check(
            self.clearance_mm >= MIN_CLEARANCE_MM,
            "paths.clearance_mm",
            f"must be >= {MIN_CLEARANCE_MM} mm, got {self.clearance_mm}",
        )
        for name in ("preop_frames", "intraop_frames", "eval_poses", "keyframes", "max_tries"):
            _check(
                getattr(self, name) >= 1,
                f"paths.{name}",
                f"must be >= 1, got {getattr(self, name)}",
            )
        for name in ("preop_frames", "intraop_frames", "eval_poses"):
            _check(
                getattr(self, name) <= MAX_FRAMES,
                f"paths.{name}",
                f"must be at most {MAX_FRAMES}, got {getattr(self, name)}",
            )
        _check(self.keyframes >= 2, "paths.keyframes", f"must be >= 2, got {self.keyframes}")
        _check(self.lookahead_mm > 0, "paths.lookahead_mm", f"must be > 0, got {self.lookahead_mm}")
        _check(
            0.0 <= self.turn_fraction <= 1.0,
            "paths.turn_fraction",
            f"must be in [0, 1], got {self.turn_fraction}",
        )
        _check_range("paths.view_distance_mm", self.view_distance_mm, 0.5, 200.0)
        _check(
            self.viewpoint_spread_mm >= 0 and self.aim_jitter_mm >= 0,
            "paths.*_mm",
            "spreads must be >= 0",
        )
        _check(
            0.0 <= self.roll_deg <= 180.0,
            "paths.roll_deg",
            f"must be in [0, 180], got {self.roll_deg}",
        )
        _check(
            float(np.linalg.norm(self.up_hint)) > 0, "paths.up_hint", "must be a non-zero vector"
        )


@dataclass(frozen=True)
class ToolsConfig:
    """Rigid instruments in view (``sim/tools.py``): forceps, suction cannula, microdebrider.

    In intraoperative sequences only (the preoperative sweep and the evaluation poses stay
    tool-free). A tool episode holds one instrument beside the scope (both pass the
    nostril) on an axis that enters the view from its edge; the tool advances along that
    axis into view, works, and withdraws. Every frame's tool keeps ``clearance_mm`` from tissue and from the
    scope (``sim.collision`` distances), else the episode is redrawn."""

    enabled: bool = False
    """Put instruments in view (``sim render --tools``)."""
    fraction: float = 0.3
    """Fraction of each intraoperative sequence's frames that lie in a tool episode."""
    kinds: tuple[ToolKind, ...] = ("forceps", "suction", "microdebrider")
    """Instruments drawn from, one per episode."""
    seed: int = 0
    """Mixed with each sequence's seed for the tool draws (same seed, same tools)."""
    episode_frames: tuple[int, int] = (12, 30)
    """[min, max] frames of one tool episode."""
    tip_depth_mm: Range = (5.0, 12.0)
    """z-depth of the tool tip in the camera when fully in, mm (kept in front of tissue)."""
    travel_mm: float = 14.0
    """How far the tool advances along its axis while entering (and withdrawing), mm."""
    clearance_mm: float = 0.3
    """Smallest distance of any point of the tool from tissue, mm."""
    shaft_length_mm: float = 20.0
    """Modelled length of the instrument from its tip, mm (the rest is behind the scope)."""
    forceps_jaw_width_mm: Range = (3.0, 5.0)
    """Through-cutting/Blakesley forceps: jaw width, mm."""
    forceps_shaft_mm: Range = (2.0, 3.0)
    """Forceps shaft diameter, mm."""
    suction_diameter_mm: Range = (2.0, 4.0)
    """Suction cannula outer diameter, mm."""
    microdebrider_diameter_mm: Range = (3.0, 4.0)
    """Microdebrider tip diameter, mm."""
    material: str = "Cr"
    """Mitsuba ``roughconductor`` material (complex IOR) of the metal."""
    roughness: float = 0.2
    """GGX alpha of the metal (low = sharp highlights)."""
    diffuse: float = 0.3
    """Weight of a grey diffuse lobe blended with the metal (brushed steel; 0 = mirror-like)."""
    model_file: str | None = None
    """Optional closed tool mesh (PLY/STL/OBJ, mm; tip at the origin, shaft along -z)
    used instead of the built-in kinds."""
    max_tries: int = 200
    """Attempts at drawing a tool episode that keeps clear of tissue before giving up."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="tools")
        _check(
            0.0 <= self.fraction <= 1.0, "tools.fraction", f"must be in [0, 1], got {self.fraction}"
        )
        _check(len(self.kinds) >= 1, "tools.kinds", "name at least one instrument")
        _check(self.seed >= 0, "tools.seed", f"must be >= 0, got {self.seed}")
        a, b = self.episode_frames
        _check(1 <= a <= b, "tools.episode_frames", f"expected 1 <= min <= max, got {[a, b]}")
        _check_range("tools.tip_depth_mm", self.tip_depth_mm, 1.0, 100.0)
        _check(
            0.0 < self.travel_mm <= 100.0,
            "tools.travel_mm",
            f"must be in (0, 100] mm, got {self.travel_mm}",
        )
        _check(
            0.0 <= self.clearance_mm <= 5.0,
            "tools.clearance_mm",
            f"must be in [0, 5] mm, got {self.clearance_mm}",
        )
        _check(
            5.0 <= self.shaft_length_mm <= 300.0,
            "tools.shaft_length_mm",
            f"must be in [5, 300] mm, got {self.shaft_length_mm}",
        )
        _check_range("tools.forceps_jaw_width_mm", self.forceps_jaw_width_mm, 1.0, 8.0)
        _check_range("tools.forceps_shaft_mm", self.forceps_shaft_mm, 1.0, 6.0)
        _check_range("tools.suction_diameter_mm", self.suction_diameter_mm, 1.0, 6.0)
        _check_range("tools.microdebrider_diameter_mm", self.microdebrider_diameter_mm, 1.0, 6.0)
        _check(
            0.01 <= self.roughness <= 1.0,
            "tools.roughness",
            f"must be in [0.01, 1], got {self.roughness}",
        )
        _check(
            0.0 <= self.diffuse <= 1.0, "tools.diffuse", f"must be in [0, 1], got {self.diffuse}"
        )
        _check(self.max_tries >= 1, "tools.max_tries", f"must be >= 1, got {self.max_tries}")


@dataclass(frozen=True)
class SmokeConfig:
    """Cautery smoke: a screen-space participating-medium approximation (``sim/effects.py``).

    Homogeneous extinction ``density_per_mm`` modulated by seeded smooth noise over the
    image (patches); light crosses the smoke twice (tip -> tissue -> lens, the light sits
    at the lens), so the tissue is attenuated by ``exp(-2 sigma z)`` and a veil of
    ``albedo`` x the frame's mean radiance fills in ``1 - exp(-2 sigma z)``."""

    density_per_mm: float = 0.0
    """Extinction coefficient, 1/mm (0 = off; 0.05 = light haze, 0.3 = dense smoke)."""
    albedo: float = 0.9
    """Veil brightness relative to the frame's mean tissue radiance."""
    patchiness: float = 0.6
    """Relative spatial variation of the density (0 = uniform)."""
    scale_frac: float = 0.3
    """Feature size of the smoke patches, fraction of the image width."""
    color_rgb: tuple[float, float, float] = (0.95, 0.93, 0.9)
    """Tint of the scattered light, linear RGB."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="smoke")
        _check(
            0.0 <= self.density_per_mm <= MAX_SMOKE_DENSITY_PER_MM,
            "smoke.density_per_mm",
            f"must be in [0, {MAX_SMOKE_DENSITY_PER_MM}] per mm, got {self.density_per_mm}",
        )
        _check(0.0 <= self.albedo <= 4.0, "smoke.albedo", f"must be in [0, 4], got {self.albedo}")
        _check(
            0.0 <= self.patchiness <= 1.0,
            "smoke.patchiness",
            f"must be in [0, 1], got {self.patchiness}",
        )
        _check(
            0.01 <= self.scale_frac <= 4.0,
            "smoke.scale_frac",
            f"must be in [0.01, 4], got {self.scale_frac}",
        )
        _check(
            all(0.0 <= x <= 1.0 for x in self.color_rgb),
            "smoke.color_rgb",
            f"expected 3 values in [0, 1], got {list(self.color_rgb)}",
        )


@dataclass(frozen=True)
class BlurConfig:
    """Motion blur from the camera's own motion: the average of sub-frame renders."""

    shutter: float = 0.0
    """Fraction of the motion from the previous frame's pose to this one that the exposure
    integrates (0 = off, 1 = the whole interval)."""
    subframes: int = 4
    """Sub-frame renders averaged when ``shutter`` > 0 (each with the full ``spp``)."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="blur")
        _check(0.0 <= self.shutter <= 1.0, "blur.shutter", f"must be in [0, 1], got {self.shutter}")
        _check(
            2 <= self.subframes <= 64, "blur.subframes", f"must be in [2, 64], got {self.subframes}"
        )


@dataclass(frozen=True)
class LensConfig:
    """Occasional lens smear (blood or mucus on the distal window): a soft blurred veil."""

    smear_probability: float = 0.0
    """Chance per frame that a smear starts (0 = off); it stays ``smear_frames`` frames."""
    smear_strength: float = 0.7
    """Opacity of the smear at its centre (0 = off)."""
    smear_frames: int = 20
    """Frames a smear stays before the surgeon cleans the lens."""
    smear_blur_px: float = 6.0
    """Blur radius (Gaussian sigma) under the smear, in pixels of a 320-pixel-wide image."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="lens")
        _check(
            0.0 <= self.smear_probability <= 1.0,
            "lens.smear_probability",
            f"must be in [0, 1], got {self.smear_probability}",
        )
        _check(
            0.0 <= self.smear_strength <= 1.0,
            "lens.smear_strength",
            f"must be in [0, 1], got {self.smear_strength}",
        )
        _check(
            self.smear_frames >= 1, "lens.smear_frames", f"must be >= 1, got {self.smear_frames}"
        )
        _check(
            0.0 < self.smear_blur_px <= 50.0,
            "lens.smear_blur_px",
            f"must be in (0, 50], got {self.smear_blur_px}",
        )


@dataclass(frozen=True)
class SimConfig:
    """Everything the renderer needs besides the phantom; ``sim render --config`` loads it."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    """Endoscope camera."""
    light: LightConfig = field(default_factory=LightConfig)
    """Tip light."""
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    """Tissue appearance."""
    cut: CutConfig = field(default_factory=CutConfig)
    """Appearance of the faces a cut created."""
    imaging: ImagingConfig = field(default_factory=ImagingConfig)
    """Sensor model and sampling."""
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    """Appearance randomisation ranges (training data)."""
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    """Tracked-pose noise."""
    paths: PathConfig = field(default_factory=PathConfig)
    """Camera paths."""
    tools: ToolsConfig = field(default_factory=ToolsConfig)
    """Instruments in view."""
    smoke: SmokeConfig = field(default_factory=SmokeConfig)
    """Cautery smoke."""
    blur: BlurConfig = field(default_factory=BlurConfig)
    """Motion blur."""
    lens: LensConfig = field(default_factory=LensConfig)
    """Lens smear."""
    seed: int = 0
    """Master seed: paths, texture, tracking noise and sensor noise derive from it."""
    depth_only: bool = False
    """Render depth (and masks) only, no RGB."""
    variant: Literal["auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"] = "auto"
    """Mitsuba variant; ``auto`` probes cuda, then llvm, then falls back to scalar (warned)."""

    def __post_init__(self) -> None:
        check_fields(
            self, error=ConfigError, section=""
        )  # also checks ``variant`` against its Literal
        _check(self.seed >= 0, "seed", f"must be an integer >= 0, got {self.seed!r}")


def config_to_dict(cfg: SimConfig) -> dict[str, Any]:
    """Plain nested dict (JSON/YAML-ready) of a configuration."""
    return to_plain(cfg)


def config_from_dict(data: dict[str, Any]) -> SimConfig:
    """Build a :class:`SimConfig` from a nested mapping; unknown keys raise ConfigError."""
    return config_from_dict_of(SimConfig, data, "", ConfigError)


def load_config(path: str | Path | None) -> SimConfig:
    """Read a YAML configuration file (``None`` = defaults); raises :class:`ConfigError`."""
    if path is None:
        return SimConfig()
    return load_config_file(SimConfig, path, ConfigError)


def replace_in(cfg: SimConfig, **changes: Any) -> SimConfig:
    """Copy of ``cfg`` with dotted-path changes, e.g. ``replace_in(cfg, **{"camera.width": 64})``."""
    return replace_dotted(cfg, ConfigError, **changes)
