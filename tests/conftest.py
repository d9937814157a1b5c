"""Shared fixtures."""

from __future__ import annotations

import pytest

from sim.config import SimConfig, replace_in


@pytest.fixture
def tiny_sim_config() -> SimConfig:
    """A simulator configuration that renders in moments: 32x24, 1 spp, 2-frame paths."""
    return replace_in(
        SimConfig(),
        **{
            "camera.width": 32,
            "camera.height": 24,
            "imaging.spp": 1,
            "paths.preop_frames": 2,
            "paths.intraop_frames": 2,
        },
    )
