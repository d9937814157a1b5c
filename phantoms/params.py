"""Shape parameters of a phantom and the generator's configuration.

Every shape parameter has a documented range (:data:`PARAM_RANGES`, also listed in
``docs/phantoms.md``); :func:`sample_params` draws each one uniformly inside its range
from the seed, then applies the user's overrides, which must name a known parameter and
lie inside its range. Ranges follow ``ANATOMY.md`` (adult values, one nasal side).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Literal

import numpy as np

from phantoms.errors import ParameterRangeError, UnknownParameterError, UnknownTargetError

#: name -> (low, high, description). Lengths in mm, volumes in mm^3, counts as integers.
PARAM_RANGES: dict[str, tuple[float, float, str]] = {
    # nasal airway
    "airway_length_mm": (62.0, 76.0, "nostril to choana along +y"),
    "airway_height_mm": (34.0, 44.0, "floor to roof in the middle of the cavity (+z)"),
    "floor_width_mm": (12.0, 15.0, "septum to lateral wall near the floor (+x)"),
    "roof_width_mm": (1.5, 3.0, "width of the olfactory cleft at the roof"),
    "vestibule_height_mm": (16.0, 20.0, "height of the nostril opening"),
    "septum_deviation_mm": (
        -1.0,
        2.5,
        "bulge of the septum towards the lateral wall (+ = narrower)",
    ),
    "septum_deviation_y_frac": (
        0.35,
        0.65,
        "position of the deviation along the airway (fraction of its length)",
    ),
    "septum_deviation_z_frac": (
        0.15,
        0.35,
        "height of the deviation (fraction of the airway height)",
    ),
    "wobble_mm": (0.3, 0.8, "amplitude of the smooth low-frequency undulation of the airway walls"),
    # inferior turbinate
    "it_length_mm": (40.0, 50.0, "inferior turbinate length (+y)"),
    "it_height_mm": (8.0, 11.0, "inferior turbinate height (+z)"),
    "it_start_mm": (9.0, 14.0, "anterior end of the inferior turbinate (y)"),
    "it_center_z_mm": (9.0, 11.5, "height of the inferior turbinate's axis above the floor"),
    "it_septum_gap_mm": (2.5, 4.0, "common meatus between inferior turbinate and septum"),
    "inferior_meatus_mm": (2.5, 4.0, "gap between inferior turbinate and lateral wall"),
    # middle turbinate
    "mt_length_mm": (35.0, 40.0, "middle turbinate length (+y)"),
    "mt_height_mm": (11.0, 14.0, "height of the middle turbinate's hanging plate"),
    "mt_thickness_mm": (3.0, 4.5, "medial-lateral thickness of the middle turbinate"),
    "mt_septum_gap_mm": (2.5, 3.5, "gap between middle turbinate and septum"),
    "mt_start_frac": (
        0.34,
        0.40,
        "anterior end of the middle turbinate (fraction of the airway length)",
    ),
    "mt_bottom_frac": (
        0.46,
        0.52,
        "lower edge of the middle turbinate (fraction of the airway height)",
    ),
    "middle_meatus_mm": (3.5, 5.0, "gap between middle turbinate and lateral wall"),
    # superior turbinate
    "st_length_mm": (15.0, 20.0, "superior turbinate length (+y)"),
    # uncinate process (wall of the infundibulum)
    "uncinate_thickness_mm": (0.7, 1.5, "uncinate process thickness (bony lamella)"),
    "uncinate_radius_mm": (7.5, 9.5, "curvature radius of the uncinate (= infundibulum radius)"),
    "uncinate_bulge_mm": (3.0, 4.0, "protrusion of the uncinate medially from the lateral wall"),
    "uncinate_y_offset_mm": (
        -8.0,
        -3.0,
        "uncinate centre along +y relative to the middle turbinate's anterior end",
    ),
    "uncinate_z_frac": (0.48, 0.54, "uncinate centre height (fraction of the airway height)"),
    # ethmoid bulla
    "bulla_radius_mm": (4.5, 6.0, "ethmoid bulla air-cell radius (~10 mm across)"),
    "bulla_wall_mm": (0.5, 1.2, "ethmoid bulla wall thickness"),
    "bulla_bulge_mm": (1.5, 2.5, "protrusion of the bulla into the middle meatus"),
    "bulla_z_frac": (0.58, 0.64, "bulla centre height (fraction of the airway height)"),
    # basal lamella (anterior wall of the posterior ethmoid cell)
    "basal_lamella_mm": (0.8, 2.0, "basal lamella thickness"),
    "posterior_ethmoid_radius_mm": (5.0, 7.0, "posterior ethmoid air-cell radius"),
    "basal_bulge_mm": (1.5, 2.5, "protrusion of the basal lamella into the middle meatus"),
    # maxillary sinus and further ethmoid cells
    "maxillary_volume_mm3": (11000.0, 16000.0, "maxillary sinus volume"),
    "maxillary_wall_mm": (
        1.5,
        2.5,
        "thinnest tissue between the maxillary sinus and the nasal airway",
    ),
    "ostium_radius_mm": (1.2, 2.2, "maxillary ostium radius (joins the sinus to the infundibulum)"),
    "ethmoid_cells": (2, 5, "number of further (closed) ethmoid air cells"),
    "ethmoid_cell_wall_mm": (0.4, 1.0, "wall thickness of the further ethmoid cells"),
}

INTEGER_PARAMS = frozenset({"ethmoid_cells"})

TARGETS: tuple[str, ...] = ("uncinate", "bulla", "basal_lamella")
"""Lamellae a bite plan can target; each is the airway-facing wall of one air cell."""


def sample_params(
    seed: int, overrides: dict[str, float] | None = None, draw: int = 0
) -> dict[str, float]:
    """Draw every shape parameter uniformly inside its range, then apply ``overrides``.

    Parameters
    ----------
    seed : int
        Seed of ``numpy.random.default_rng``; parameters are drawn in the order of
        :data:`PARAM_RANGES`, so a seed always gives the same anatomy.
    overrides : dict, optional
        ``{name: value}``; each name must be in :data:`PARAM_RANGES` and each value
        inside its range.
    draw : int, optional
        Which of the seed's independent draws (0, the default, is the seed's first; the
        generator takes the next when an anatomy has no airway for the endoscope).

    Returns
    -------
    dict of str -> float (int for :data:`INTEGER_PARAMS`), in the order of the ranges.
    """
    check_seed(seed)
    if int(draw) < 0:
        raise ValueError(f"draw must be >= 0, got {draw}")
    rng = np.random.default_rng([int(seed), 0x5A1] + ([int(draw)] if draw else []))
    params: dict[str, float] = {}
    for name, (lo, hi, _) in PARAM_RANGES.items():
        if name in INTEGER_PARAMS:
            params[name] = int(rng.integers(int(lo), int(hi) + 1))
        else:
            params[name] = float(lo + (hi - lo) * rng.random())
    for name, value in (overrides or {}).items():
        params[name] = check_param(name, value)
    return params


def check_param(name: str, value: object) -> float:
    """Return ``value`` as the parameter's type if ``name`` is known and in range, else raise."""
    if name not in PARAM_RANGES:
        raise UnknownParameterError(
            f"param {name!r}",
            f"unknown shape parameter; expected one of {', '.join(PARAM_RANGES)}",
        )
    lo, hi, _ = PARAM_RANGES[name]
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ParameterRangeError(
            f"param {name!r}", f"expected a number in [{lo}, {hi}], got {value!r}"
        ) from None
    if not math.isfinite(number) or not lo <= number <= hi:
        raise ParameterRangeError(
            f"param {name!r}", f"expected a value in [{lo}, {hi}], got {value!r}"
        )
    if name in INTEGER_PARAMS:
        if number != int(number):
            raise ParameterRangeError(
                f"param {name!r}", f"expected an integer in [{lo:g}, {hi:g}], got {value!r}"
            )
        return int(number)
    return number


def check_seed(seed: object) -> int:
    """Return ``seed`` if it is a non-negative integer below 2**32, else raise."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < 2**32:
        raise ParameterRangeError("seed", f"expected an integer in [0, 2**32), got {seed!r}")
    return int(seed)


def _check_range(name: str, value: float, lo: float, hi: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float | np.number):
        raise ParameterRangeError(name, f"expected a number in [{lo}, {hi}], got {value!r}")
    if not math.isfinite(float(value)) or not lo <= float(value) <= hi:
        raise ParameterRangeError(name, f"expected a value in [{lo}, {hi}], got {value!r}")


@dataclass(frozen=True)
class PhantomConfig:
    """Everything :func:`phantoms.generate.generate_phantom` needs besides the output folder."""

    seed: int = 0
    """Seed of every random choice (anatomy, bite plan, CT noise)."""
    n_bites: int = 5
    """Number of surgical steps (fragments or bites); the range depends on the procedure
    (:data:`phantoms.procedures.STEP_RANGES`: uncinectomy 1-8, ethmoidectomy 4-12, bites 1-20)."""
    procedure: str = "uncinectomy"
    """Surgical procedure: ``uncinectomy`` (default), ``ethmoidectomy`` or ``bites``
    (the small overlapping bites on ``target``); see ``docs/phantoms.md``."""
    target: Literal["uncinate", "bulla", "basal_lamella"] = "uncinate"
    """Lamella the bites perforate; see :data:`TARGETS`."""
    bite_size_mm: tuple[float, float] = (2.0, 5.0)
    """Range of the cutter's jaw width and length, mm (forceps-sized: within 1.5-6)."""
    spacing_mm: float = 0.5
    """CT voxel spacing, mm (isotropic, 0.2-2.0)."""
    noise_hu: float = 0.0
    """Standard deviation of the seeded Gaussian CT noise, HU (0 = none, at most 300)."""
    mucosa_mm: float = 1.0
    """Soft-tissue layer under every surface; deeper tissue is bone in the CT (0.5-3 mm)."""
    roi_margin_mm: float = 3.0
    """Margin added around the removed tissue's bounding box for the change ROI, mm (0-20)."""
    mesh_edge_mm: float = 0.5
    """Target edge length of the tissue surface, mm (0.3-2.0; coarser = faster, for tests)."""
    ct: bool = True
    """Write the CT volumes (label and HU NIfTI per step). False writes the meshes and the
    manifest only: all that rendering needs, in about half the time (``sim dataset``'s
    default)."""
    tet: bool = False
    """Also export a tetrahedral mesh per step (pytetwild; slow)."""
    tet_edge_mm: float = 3.0
    """Target edge length of the tetrahedral mesh, mm (0.5-10)."""
    overrides: dict[str, float] = field(default_factory=dict)
    """Shape parameters fixed by the user, ``{name: value}`` (see :data:`PARAM_RANGES`)."""

    def __post_init__(self) -> None:
        check_seed(self.seed)
        from phantoms.procedures import check_procedure  # noqa: PLC0415 - import cycle

        check_procedure(self.procedure, self.n_bites)
        if self.target not in TARGETS:
            raise UnknownTargetError(
                "target",
                f"no lamella {self.target!r} in the phantom; expected one of {', '.join(TARGETS)}",
            )
        try:
            lo, hi = (float(v) for v in self.bite_size_mm)
        except (TypeError, ValueError):
            raise ParameterRangeError(
                "bite_size_mm", f"expected (min, max) in mm, got {self.bite_size_mm!r}"
            ) from None
        if not (1.5 <= lo <= hi <= 6.0):
            raise ParameterRangeError(
                "bite_size_mm", f"expected 1.5 <= min <= max <= 6.0 mm, got {self.bite_size_mm!r}"
            )
        _check_range("spacing_mm", self.spacing_mm, 0.2, 2.0)
        _check_range("noise_hu", self.noise_hu, 0.0, 300.0)
        _check_range("mucosa_mm", self.mucosa_mm, 0.5, 3.0)
        _check_range("roi_margin_mm", self.roi_margin_mm, 0.0, 20.0)
        _check_range("mesh_edge_mm", self.mesh_edge_mm, 0.3, 2.0)
        _check_range("tet_edge_mm", self.tet_edge_mm, 0.5, 10.0)
        for name in ("ct", "tet"):
            if not isinstance(getattr(self, name), bool):
                raise ParameterRangeError(
                    name, f"expected True or False, got {getattr(self, name)!r}"
                )
        if self.mucosa_mm < 1.5 * self.spacing_mm:
            # Bone must stay a voxel away from the surface so the -480 HU iso-surface is
            # exact (docs/phantoms.md, "CT volumes").
            raise ParameterRangeError(
                "mucosa_mm",
                f"expected at least 1.5 x spacing_mm = {1.5 * self.spacing_mm:g} mm, got {self.mucosa_mm:g}",
            )
        for name, value in self.overrides.items():
            check_param(name, value)

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))
