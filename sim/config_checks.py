"""The small checks every section of the simulator's configuration shares.

Each field's kind (a number, a list of two numbers, one of a few names) is checked by
:func:`chisel.core.config.check_fields`, first thing in every ``__post_init__``; these
helpers only add the ranges and relations the annotations cannot say.
"""

from __future__ import annotations

import math

from sim.errors import ConfigError

Range = tuple[float, float]
"""A ``[min, max]`` pair of finite numbers (its kind is checked by ``check_fields``)."""


def check(cond: bool, name: str, problem: str) -> None:
    """Raise :class:`ConfigError` naming the dotted key ``name`` unless ``cond`` holds."""
    if not cond:
        raise ConfigError(name, problem)


def check_range(name: str, r: Range, lo: float = -math.inf, hi: float = math.inf) -> None:
    """``r`` must satisfy ``lo <= min <= max <= hi``."""
    check(lo <= r[0] <= r[1] <= hi, name, f"expected {lo} <= min <= max <= {hi}, got {list(r)}")
