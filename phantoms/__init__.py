"""Procedural nasal-sinus phantoms: tissue meshes, surgical bites, CT volumes.

Public API (see ``docs/phantoms.md``):

* :class:`PhantomConfig`, :func:`sample_params`, :data:`PARAM_RANGES`, :data:`TARGETS`
* :func:`build_phantom` (pure, in memory), :func:`write_phantom`, :func:`generate`
* :func:`plan_bites`, :func:`apply_bites`, :class:`Bite`
* :data:`PROCEDURES`, :func:`plan_procedure`, :func:`cut_steps` (uncinectomy,
  ethmoidectomy, bites; ragged cutters, cut-face labels)
* :func:`repair_surface`, :func:`tetrahedralize`, :func:`load_tissue`
* errors in :mod:`phantoms.errors` (all subclass :class:`PhantomError`, a ``ValueError``)

``phantoms`` imports neither ``chisel`` nor ``sim``.
"""

from phantoms.bites import Bite, apply_bites, cutter_manifold, plan_bites
from phantoms.errors import (
    AnatomyError,
    BiteMissError,
    NotManifoldError,
    OutputError,
    ParameterRangeError,
    PhantomError,
    ProcedureError,
    UnknownParameterError,
    UnknownProcedureError,
    UnknownTargetError,
)
from phantoms.generate import Phantom, build_phantom, generate, manifest, write_phantom
from phantoms.params import PARAM_RANGES, TARGETS, PhantomConfig, sample_params
from phantoms.procedures import PROCEDURES, STEP_RANGES, cut_steps, plan_procedure
from phantoms.surface import load_tissue
from phantoms.tet import repair_surface, tetrahedralize

__all__ = [
    "PARAM_RANGES",
    "PROCEDURES",
    "STEP_RANGES",
    "TARGETS",
    "AnatomyError",
    "Bite",
    "BiteMissError",
    "NotManifoldError",
    "OutputError",
    "ParameterRangeError",
    "Phantom",
    "PhantomConfig",
    "PhantomError",
    "ProcedureError",
    "UnknownParameterError",
    "UnknownProcedureError",
    "UnknownTargetError",
    "apply_bites",
    "build_phantom",
    "cut_steps",
    "cutter_manifold",
    "generate",
    "load_tissue",
    "manifest",
    "plan_bites",
    "plan_procedure",
    "repair_surface",
    "sample_params",
    "tetrahedralize",
    "write_phantom",
]
