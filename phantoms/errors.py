"""Exceptions raised at the public entry points of the phantom generator.

Every error names the argument (or file) and the problem, with expected vs actual. All
derive from :class:`PhantomError`, itself a :class:`chisel.core.errors.InvalidInputError`
(so a ``ValueError`` and a ``ChiselError``): one family of errors for the whole project.
"""

from __future__ import annotations

from chisel.core.errors import InvalidInputError


class PhantomError(InvalidInputError):
    """Base class of every error the phantom generator raises on purpose.

    ``source`` names the argument, parameter or file; ``problem`` says what is wrong.
    """


class UnknownParameterError(PhantomError):
    """A parameter name (shape parameter, config field) that the generator does not know."""


class ParameterRangeError(PhantomError):
    """A parameter value outside its documented range (or of the wrong type)."""


class UnknownTargetError(PhantomError):
    """The requested target lamella does not exist in the phantom."""


class BiteMissError(PhantomError):
    """A bite of the surgical plan removes no tissue (the cutter lies in air)."""


class NotManifoldError(PhantomError):
    """A surface mesh is not a closed, oriented 2-manifold (repair it first)."""


class OutputError(PhantomError):
    """The output folder cannot be created or written."""


class AnatomyError(PhantomError):
    """The sampled anatomy violates a constraint (e.g. no airway path with clearance)."""


class UnknownProcedureError(PhantomError):
    """The requested surgical procedure does not exist."""


class ProcedureError(PhantomError):
    """A procedure (or plan) cannot be carried out on this phantom: no wall in reach, a
    fragment that misses the tissue or cuts beyond the procedure's structures."""
