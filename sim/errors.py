"""Errors raised by the simulator's public entry points.

Every error names the file or argument and the problem (expected vs actual). They all
derive from :class:`SimError`, itself a :class:`chisel.core.errors.InvalidInputError`, so
callers can catch them as ``ValueError`` or as chisel errors. ``VariantError`` is
:class:`chisel.core.errors.VariantError` (the variant probe, shared with the updater's ray
caster, lives in :mod:`chisel.core.mitsuba_variant`).
"""

from __future__ import annotations

from chisel.core.errors import ConfigError as BaseConfigError
from chisel.core.errors import InvalidInputError
from chisel.core.errors import VariantError as VariantError  # the variant probe is chisel's


class SimError(InvalidInputError):
    """Base class of every input error the simulator raises on purpose."""


class ConfigError(SimError, BaseConfigError):
    """A configuration value (YAML key, CLI option, dataclass field) is invalid."""


class PhantomError(SimError):
    """A phantom folder or its ``phantom.json`` manifest is missing or malformed."""


class MeshError(SimError):
    """A mesh is missing, unreadable, empty or not watertight."""


class PathError(SimError):
    """A camera path cannot be built or violates the clearance from tissue."""


class PathInTissueError(PathError):
    """A camera path starts (or runs) inside the tissue solid."""
