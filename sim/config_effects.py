"""Configuration of what comes between the lens and the tissue: tools, smoke, blur, smear.

Sections ``tools`` (:class:`ToolsConfig`: instruments in view; ``sim/tools.py``) and
``smoke``, ``blur``, ``lens`` (:class:`SmokeConfig`, :class:`BlurConfig`,
:class:`LensConfig`: cautery smoke, motion blur, lens smear; ``sim/effects.py``) of
:class:`sim.config.SimConfig`. All are off by default.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from chisel.core.config import check_fields
from sim.config_checks import Range, check, check_range
from sim.errors import ConfigError

ToolKind = Literal["forceps", "suction", "microdebrider"]
MAX_SMOKE_DENSITY_PER_MM = 1.0
"""Densest smoke accepted, 1/mm: beyond it a 1 mm layer hides the tissue."""
CONDUCTOR_MATERIALS = (
    "none",
    *("Ag Al AlAs AlAs_palik AlSb AlSb_palik Au Be Be_palik Cr CsI CsI_palik Cu Cu2O").split(),
    *("Cu2O_palik CuO CuO_palik Cu_palik Hg HgTe HgTe_palik Hg_palik Ir Ir_palik K").split(),
    *("K_palik Li Li_palik MgO MgO_palik Mo Mo_palik Na_palik Nb Nb_palik Ni_palik Rh").split(),
    *("Rh_palik Se Se-e Se-e_palik Se_palik SiC SiC_palik SnTe SnTe_palik Ta Ta_palik").split(),
    *("Te Te-e Te-e_palik Te_palik ThF4 ThF4_palik TiC TiC_palik TiN TiN_palik TiO2").split(),
    *("TiO2-e TiO2-e_palik TiO2_palik VC VC_palik VN VN_palik V_palik W a-C d-C").split(),
    "d-C_palik",
)
"""The ``material`` names of Mitsuba's conductor plugins: its ``data/ior/<name>.eta.spd``
spectra (Mitsuba 3), and ``none`` (a perfect mirror). Any other name fails when the scene
loads ("data/ior/<name>.eta.spd does not exist"), so ``tools.material`` is checked here."""


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
    """Fraction of each intraoperative sequence's frames that lie in a tool episode. About
    two thirds of an episode's frames show the tool (it enters from behind the lens and
    withdraws there): 0.3 gave tool pixels in 20.5-21.0 % of the frames, 0.45 in 30.0 %
    (phantom seeds 0 and 1, five steps of 80 frames each)."""
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
        check(
            0.0 <= self.fraction <= 1.0, "tools.fraction", f"must be in [0, 1], got {self.fraction}"
        )
        check(len(self.kinds) >= 1, "tools.kinds", "name at least one instrument")
        check(self.seed >= 0, "tools.seed", f"must be >= 0, got {self.seed}")
        a, b = self.episode_frames
        check(1 <= a <= b, "tools.episode_frames", f"expected 1 <= min <= max, got {[a, b]}")
        check_range("tools.tip_depth_mm", self.tip_depth_mm, 1.0, 100.0)
        check(
            0.0 < self.travel_mm <= 100.0,
            "tools.travel_mm",
            f"must be in (0, 100] mm, got {self.travel_mm}",
        )
        check(
            0.0 <= self.clearance_mm <= 5.0,
            "tools.clearance_mm",
            f"must be in [0, 5] mm, got {self.clearance_mm}",
        )
        check(
            5.0 <= self.shaft_length_mm <= 300.0,
            "tools.shaft_length_mm",
            f"must be in [5, 300] mm, got {self.shaft_length_mm}",
        )
        check_range("tools.forceps_jaw_width_mm", self.forceps_jaw_width_mm, 1.0, 8.0)
        check_range("tools.forceps_shaft_mm", self.forceps_shaft_mm, 1.0, 6.0)
        check_range("tools.suction_diameter_mm", self.suction_diameter_mm, 1.0, 6.0)
        check_range("tools.microdebrider_diameter_mm", self.microdebrider_diameter_mm, 1.0, 6.0)
        check(
            0.01 <= self.roughness <= 1.0,
            "tools.roughness",
            f"must be in [0.01, 1], got {self.roughness}",
        )
        check(0.0 <= self.diffuse <= 1.0, "tools.diffuse", f"must be in [0, 1], got {self.diffuse}")
        check(self.max_tries >= 1, "tools.max_tries", f"must be >= 1, got {self.max_tries}")
        if self.material not in CONDUCTOR_MATERIALS:
            same = [m for m in CONDUCTOR_MATERIALS if m.lower() == self.material.lower()]
            hint = f" (did you mean {same[0]!r}?)" if same else ""
            raise ConfigError(
                "tools.material",
                f"expected a Mitsuba conductor material (Cr, Al, Ag, Au, Cu, W, ...: the "
                f"{len(CONDUCTOR_MATERIALS)} names of sim/config_effects.py "
                f"CONDUCTOR_MATERIALS), got {self.material[:80]!r}{hint}",
            )


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
        check(
            0.0 <= self.density_per_mm <= MAX_SMOKE_DENSITY_PER_MM,
            "smoke.density_per_mm",
            f"must be in [0, {MAX_SMOKE_DENSITY_PER_MM}] per mm, got {self.density_per_mm}",
        )
        check(0.0 <= self.albedo <= 4.0, "smoke.albedo", f"must be in [0, 4], got {self.albedo}")
        check(
            0.0 <= self.patchiness <= 1.0,
            "smoke.patchiness",
            f"must be in [0, 1], got {self.patchiness}",
        )
        check(
            0.01 <= self.scale_frac <= 4.0,
            "smoke.scale_frac",
            f"must be in [0.01, 4], got {self.scale_frac}",
        )
        check(
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
        check(0.0 <= self.shutter <= 1.0, "blur.shutter", f"must be in [0, 1], got {self.shutter}")
        check(
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
        check(
            0.0 <= self.smear_probability <= 1.0,
            "lens.smear_probability",
            f"must be in [0, 1], got {self.smear_probability}",
        )
        check(
            0.0 <= self.smear_strength <= 1.0,
            "lens.smear_strength",
            f"must be in [0, 1], got {self.smear_strength}",
        )
        check(self.smear_frames >= 1, "lens.smear_frames", f"must be >= 1, got {self.smear_frames}")
        check(
            0.0 < self.smear_blur_px <= 50.0,
            "lens.smear_blur_px",
            f"must be in (0, 50], got {self.smear_blur_px}",
        )
