"""Configuration of the tissue's look: mucosa, cut faces, and its randomisation.

Sections ``appearance`` (:class:`AppearanceConfig`: the mucosa's BSDF and procedural
texture), ``cut`` (:class:`CutConfig`: raw, bleeding tissue on the faces a cut created),
``blood`` (:class:`BloodConfig`: a film of blood trickling downhill from fresh cuts) and
``randomization`` (:class:`RandomizationConfig`: the ranges ``sim dataset`` draws
appearance, light, sensor and effects from, once per render) of
:class:`sim.config.SimConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

from chisel.core.config import check_fields
from sim.config_checks import Range, check, check_range
from sim.config_effects import MAX_SMOKE_DENSITY_PER_MM
from sim.errors import ConfigError


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
            check(
                all(0.0 <= x <= 1.0 for x in v),
                f"appearance.{name}",
                f"expected 3 values in [0, 1], got {list(v)}",
            )
        check(
            0.0 <= self.color_variation <= 1.0,
            "appearance.color_variation",
            f"must be in [0, 1], got {self.color_variation}",
        )
        check(
            0.0 <= self.vessel_strength <= 1.0,
            "appearance.vessel_strength",
            f"must be in [0, 1], got {self.vessel_strength}",
        )
        check(
            self.variation_scale_mm > 0 and self.vessel_scale_mm > 0,
            "appearance.*_scale_mm",
            "scales must be > 0 mm",
        )
        check(
            0.0 < self.vessel_width < 1.0,
            "appearance.vessel_width",
            f"must be in (0, 1), got {self.vessel_width}",
        )
        check(
            0.0 < self.roughness <= 1.0,
            "appearance.roughness",
            f"must be in (0, 1], got {self.roughness}",
        )
        check(
            0.0 <= self.specular <= 1.0,
            "appearance.specular",
            f"must be in [0, 1], got {self.specular}",
        )
        check(
            self.texture_voxel_mm > 0,
            "appearance.texture_voxel_mm",
            f"must be > 0, got {self.texture_voxel_mm}",
        )
        check(
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
            check(
                all(0.0 <= x <= 1.0 for x in v),
                f"cut.{name}",
                f"expected 3 values in [0, 1], got {list(v)}",
            )
        check(
            0.0 <= self.blood_strength <= 1.0,
            "cut.blood_strength",
            f"must be in [0, 1], got {self.blood_strength}",
        )
        check(self.blood_scale_mm > 0, "cut.blood_scale_mm", "must be > 0 mm")


@dataclass(frozen=True)
class BloodConfig:
    """A thin film of blood trickling downhill from the faces the current step cut
    (``sim/blood.py``): a few seeded streaks following the steepest descent of gravity over
    the surface, each ``width_mm`` wide and thinning out linearly to nothing at its length.
    Off by default (the benchmark renders without it)."""

    enabled: bool = False
    """Draw blood streaks below each step's fresh cut faces (needs the phantom's labels)."""
    strength: float = 0.85
    """Film coverage where a streak leaves the cut (0 = off; same bytes as disabled)."""
    streaks: tuple[int, int] = (2, 5)
    """[min, max] streaks drawn per surgical step, from the cut's lower edge."""
    film_length_mm: Range = (3.0, 10.0)
    """[min, max] length a streak runs down the surface before it has thinned out, mm."""
    width_mm: Range = (0.6, 1.6)
    """[min, max] width of a streak, mm."""
    rgb: tuple[float, float, float] = (0.3, 0.012, 0.01)
    """Colour of the film (fresh blood), linear RGB in [0, 1]."""
    roughness: float = 0.1
    """Principled BSDF roughness of the film (smoother than mucosa: a wet, sharp highlight)."""
    specular: float = 0.5
    """Principled BSDF specular amount of the film."""
    gravity: tuple[float, float, float] = (0.0, 1.0, 0.0)
    """Direction of gravity in the phantom's world (LPS, unit length not needed); default
    +y = posterior: the patient lies supine."""

    def __post_init__(self) -> None:
        check_fields(self, error=ConfigError, section="blood")
        check(
            0.0 <= self.strength <= 1.0, "blood.strength", f"must be in [0, 1], got {self.strength}"
        )
        a, b = self.streaks
        check(0 <= a <= b <= 50, "blood.streaks", f"expected 0 <= min <= max <= 50, got {[a, b]}")
        check_range("blood.film_length_mm", self.film_length_mm, 0.1, 100.0)
        check_range("blood.width_mm", self.width_mm, 0.05, 20.0)
        check(
            all(0.0 <= x <= 1.0 for x in self.rgb),
            "blood.rgb",
            f"expected 3 values in [0, 1], got {list(self.rgb)}",
        )
        check(
            0.0 < self.roughness <= 1.0,
            "blood.roughness",
            f"must be in (0, 1], got {self.roughness}",
        )
        check(
            0.0 <= self.specular <= 1.0,
            "blood.specular",
            f"must be in [0, 1], got {self.specular}",
        )
        check(
            sum(x * x for x in self.gravity) > 1e-12,
            "blood.gravity",
            f"must be a non-zero direction, got {list(self.gravity)}",
        )


@dataclass(frozen=True)
class RandomizationConfig:
    """Ranges sampled once per render for training data (``sim dataset``); each a [min, max].

    The effect ranges (``tools_fraction``, ``smoke_*``, ``blur_*``, ``lens_*``,
    ``blood_*``) default to
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
    blood_strength: Range = (0.0, 0.0)
    """Blood film coverage (``blood.strength``; drawn only where ``blood.enabled``)."""

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
            "blood_strength": (0.0, 1.0),
        }
        for name, (lo, hi) in bounds.items():
            check_range(f"randomization.{name}", getattr(self, name), lo, hi)
