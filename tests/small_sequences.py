"""A three-frame synthetic sequence folder with every optional part (RGB, depth, masks,
true poses, a camera mask), shared by the tests that break one part of it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from chisel.core.geometry import Camera, look_at
from chisel.io.sequence import Frame, write_sequence

CAM = Camera.from_fov(32, 24, 80)


def write_small_sequence(path: Path, seed: int = 0) -> Path:
    """Three frames side by side along x, looking down +z; random images seeded by ``seed``."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(3):
        T = look_at(np.array([i, 0.0, 0.0]), np.array([i, 0.0, 30.0]), up=np.array([0.0, -1, 0]))
        frames.append(
            Frame(
                i,
                T,
                rng.integers(0, 255, (*CAM.shape, 3), dtype=np.uint8),
                rng.uniform(5, 20, CAM.shape).astype(np.float32),
                rng.random(CAM.shape) > 0.2,
                T,
            )
        )
    circle = np.ones(CAM.shape, bool)
    circle[0] = False
    return write_sequence(path, CAM, frames, camera_mask=circle)
