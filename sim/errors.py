"""Errors raised by the simulator's public entry points.

Every error names the file or argument and the problem (expected vs actual). They all
derive from :class:`SimError`, itself a :class:`chisel.errors.InvalidInputError`, so
callers can catch them as ``ValueError`` or as chisel errors.
"""

from __future__ import annotations

from chisel.errors import InvalidInputError


class SimError(InvalidInputError):
    """Base class of every input error the simulator raises on purpose."""


class ConfigError(SimError):
    """A configuration value (YAML key, CLI option, dataclass field) is invalid."""


class PhantomError(SimError):
    """A phantom folder or its ``phantom.json`` manifest is missing or malformed."""


class MeshError(SimError):
    """A mesh is missing, unreadable, empty or not watertight."""


class PathError(SimError):
    """A camera path cannot be built or violates the clearance from tissue."""


class PathInTissueError(PathError):
    """A camera path starts (or runs) inside the tissue solid."""


class VariantError(SimError):
    """No usable Mitsuba variant, or an explicitly requested variant does not work."""
