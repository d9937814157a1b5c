"""Simulator configuration: :class:`SimConfig`, loadable from YAML.

A YAML file mirrors :class:`SimConfig`: one mapping per section (``camera``, ``light``,
``appearance``, ``cut``, ``blood``, ``imaging``, ``randomization``, ``tracking``, ``paths``, ``tools``,
``smoke``, ``blur``, ``lens``) plus ``seed``.
Missing keys keep their defaults; unknown keys are refused (:class:`ConfigError`), so a
typo never passes silently. ``config/sim_default.yaml`` lists every key with its default.

The sections are small frozen dataclasses, each checked in its ``__post_init__``, kept
beside the sections they belong with; all are importable from here:

* ``sim/config_scope.py``: the endoscope (``camera``, ``light``, ``imaging``);
* ``sim/config_tissue.py``: the tissue's look (``appearance``, ``cut``, ``blood``,
  ``randomization``);
* ``sim/config_paths.py``: the camera's motion (``paths``, ``tracking``);
* ``sim/config_effects.py``: what comes between lens and tissue (``tools``, ``smoke``,
  ``blur``, ``lens``).

Loading, checking kinds and writing out are :mod:`chisel.core.config`'s, shared with the
updater's configuration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from chisel.core.config import check_fields, load_config_file, to_plain
from chisel.core.config import config_from_dict as config_from_dict_of
from chisel.core.config import replace_in as replace_dotted
from sim.config_checks import Range, check
from sim.config_effects import (
    MAX_SMOKE_DENSITY_PER_MM,
    BlurConfig,
    LensConfig,
    SmokeConfig,
    ToolKind,
    ToolsConfig,
)
from sim.config_paths import MAX_FRAMES, MIN_CLEARANCE_MM, PathConfig, TrackingConfig
from sim.config_scope import MAX_IMAGE_SIDE, CameraConfig, ImagingConfig, LightConfig
from sim.config_tissue import AppearanceConfig, BloodConfig, CutConfig, RandomizationConfig
from sim.errors import ConfigError

__all__ = [
    "MAX_FRAMES",
    "MAX_IMAGE_SIDE",
    "MAX_SMOKE_DENSITY_PER_MM",
    "MIN_CLEARANCE_MM",
    "AppearanceConfig",
    "BloodConfig",
    "BlurConfig",
    "CameraConfig",
    "ConfigError",
    "CutConfig",
    "ImagingConfig",
    "LensConfig",
    "LightConfig",
    "PathConfig",
    "RandomizationConfig",
    "Range",
    "SimConfig",
    "SmokeConfig",
    "ToolKind",
    "ToolsConfig",
    "TrackingConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "replace_in",
]


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
    blood: BloodConfig = field(default_factory=BloodConfig)
    """Blood film trickling below fresh cuts."""
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
        check_fields(self, error=ConfigError, section="")  # also ``variant`` against its Literal
        check(self.seed >= 0, "seed", f"must be an integer >= 0, got {self.seed!r}")


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
