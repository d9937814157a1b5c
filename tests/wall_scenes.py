"""Synthetic change-aware pairs: a textured wall and, optionally, a window through it.

Shared by the change-aware tests (CPU and CUDA). Only numpy, torch and ``chisel.depth``
are imported, so ``tests/test_depth_cuda.py`` runs on a machine without the renderer's
packages. The scene is drawn on a 32 x 40 lattice of "pixels" whatever the image size, so
a larger image shows the same wall at a finer sampling.
"""

from __future__ import annotations

import numpy as np
import torch

from chisel.depth.change_train import PriorSet

H, W = 32, 40


def wall_scene(
    rng: np.random.Generator, window: bool, h: int = H, w: int = W
) -> tuple[np.ndarray, ...]:
    """A tilted textured wall (the prior) and, optionally, a window through it onto a
    farther, darker wall: returns (rgb uint8, prior_mm, target_mm, window mask)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    v, u = yy * np.float32(H / h), xx * np.float32(W / w)  # the 32 x 40 lattice
    z0 = rng.uniform(10.0, 25.0)
    prior = (
        z0 + rng.uniform(-0.05, 0.05) * (u - W / 2) + rng.uniform(-0.05, 0.05) * (v - H / 2)
    ).astype(np.float32)
    target = prior.copy()
    win = np.zeros((h, w), bool)
    if window:
        wh, ww = int(rng.integers(8, 16)) * h // H, int(rng.integers(8, 18)) * w // W
        y, x = rng.integers(0, h - wh), rng.integers(0, w - ww)
        win[y : y + wh, x : x + ww] = True
        target[win] += rng.uniform(4.0, 8.0)
    phase = rng.uniform(0, 2 * np.pi)
    texture = 0.5 + 0.2 * np.sin(0.7 * u + phase) * np.cos(0.5 * v)
    shade = (z0 / target) ** 2  # an endoscope's light falls off with distance
    gray = np.clip(texture * shade, 0.0, 1.0)
    rgb = (np.stack([gray, 0.6 * gray, 0.5 * gray], axis=-1) * 255).astype(np.uint8)
    return rgb, prior, target, win


def wall_pairs(n: int, seed: int, h: int = H, w: int = W) -> PriorSet:
    """``n`` wall scenes, three of four with a window."""
    rng = np.random.default_rng(seed)
    rows = [wall_scene(rng, i % 4 != 0, h, w) for i in range(n)]
    return PriorSet(
        rgb=torch.from_numpy(np.stack([r[0] for r in rows])),
        prior_mm=torch.from_numpy(np.stack([r[1] for r in rows])),
        target_mm=torch.from_numpy(np.stack([r[2] for r in rows])),
        changed=torch.from_numpy(np.stack([r[3] for r in rows])),
        sources=[f"wall#{i}" for i in range(n)],
    )
