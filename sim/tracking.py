"""Tracked poses: what an optical navigation system reports beside the true poses.

Model (all in the camera frame, so rotations turn about the optical centre)::

    T_tracked[i] = T_true[max(i - latency, 0)] @ E_handeye @ J[i]

- ``E_handeye``: a constant hand-eye calibration error, a rotation of exactly
  ``handeye_deg`` about a random axis and a translation of exactly ``handeye_mm`` in a
  random direction;
- ``J[i]``: per-frame tracking jitter, rotation vector ~ N(0, jitter_deg^2) and translation
  ~ N(0, jitter_mm^2) per axis;
- latency: frame ``i`` reports the true pose of frame ``i - latency`` (the first pose
  repeated at the start).

All randomness comes from ``seed``; zero noise and zero latency give the true poses exactly.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from chisel.core.geometry import check_rigid, make_transform
from sim.config import TrackingConfig


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def handeye_error(cfg: TrackingConfig, seed: int) -> np.ndarray:
    """(4, 4) float64 constant hand-eye error ``E`` (camera frame), from ``seed``."""
    rng = np.random.default_rng([int(seed), 101])
    axis, direction = _unit(rng), _unit(rng)
    R = Rotation.from_rotvec(axis * math.radians(cfg.handeye_deg)).as_matrix()
    return make_transform(R, direction * cfg.handeye_mm)


def tracked_poses(
    true_poses: np.ndarray, cfg: TrackingConfig, seed: int, handeye_seed: int | None = None
) -> np.ndarray:
    """Tracked ``T_world_from_cam`` for a sequence of true ones.

    true_poses : (N, 4, 4) float64 ``T_world_from_cam``, mm. Returns (N, 4, 4) float64.
    ``seed`` draws the jitter; ``handeye_seed`` (default ``seed``) the constant hand-eye
    error, so several sequences of one session can share one calibration error.
    Raises :class:`chisel.core.errors.PoseError` on non-rigid or non-finite poses.
    """
    T = check_rigid(true_poses, "true poses").reshape(-1, 4, 4)
    n = len(T)
    idx = np.maximum(np.arange(n) - int(cfg.latency_frames), 0)
    lagged = T[idx]
    if cfg.handeye_mm == 0 and cfg.handeye_deg == 0 and cfg.jitter_mm == 0 and cfg.jitter_deg == 0:
        return lagged.copy()
    E = handeye_error(cfg, seed if handeye_seed is None else handeye_seed)
    rng = np.random.default_rng([int(seed), 102])
    rotvec = rng.normal(scale=math.radians(cfg.jitter_deg), size=(n, 3))
    trans = rng.normal(scale=cfg.jitter_mm, size=(n, 3))
    J = np.tile(np.eye(4), (n, 1, 1))
    J[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    J[:, :3, 3] = trans
    out = lagged @ E @ J
    # Re-orthonormalise: products of many rotations drift from SO(3) by float rounding.
    out[:, :3, :3] = Rotation.from_matrix(out[:, :3, :3]).as_matrix()
    return out


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame (translation mm, rotation deg) differences between two pose stacks.

    T_a, T_b : (N, 4, 4) float64. Returns two (N,) float64 arrays.
    """
    A = np.asarray(T_a, dtype=np.float64).reshape(-1, 4, 4)
    B = np.asarray(T_b, dtype=np.float64).reshape(-1, 4, 4)
    dt = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    Rd = np.swapaxes(A[:, :3, :3], 1, 2) @ B[:, :3, :3]
    c = (np.trace(Rd, axis1=1, axis2=2) - 1.0) / 2.0
    return dt, np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
