"""The airway as an implicit field: the space between septum, lateral wall, floor and roof.

:class:`AirwayField` is positive in air and close to the signed distance to the airway
wall near it (mm, world frame of ``docs/phantoms.md``). The three turbinates are carved
out of it by smooth subtraction, and a smooth, seeded low-frequency undulation moves the
walls. :func:`phantoms.anatomy.build_anatomy` meshes it (marching cubes) and takes the
air cells' walls out of it.
"""

from __future__ import annotations

import math

import numpy as np


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth minimum (polynomial, blend radius ``k`` mm): smooth intersection of fields."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def _ellipsoid(px, py, pz, center, axes) -> np.ndarray:
    """Approximate signed distance, positive inside an ellipsoid (Quilez' bound), mm."""
    x = (px - center[0]) / axes[0]
    y = (py - center[1]) / axes[1]
    z = (pz - center[2]) / axes[2]
    k0 = np.sqrt(x * x + y * y + z * z)
    k1 = np.sqrt((x / axes[0]) ** 2 + (y / axes[1]) ** 2 + (z / axes[2]) ** 2)
    return -k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


class AirwayField:
    """The airway as an implicit field ``f(x, y, z)`` in mm, positive in air.

    The zero level set is the airway wall; ``|grad f|`` is close to 1 near it, so ``f``
    approximates the signed distance to the wall.
    """

    def __init__(self, p: dict[str, float], seed: int) -> None:
        self.p = p
        L, H = p["airway_length_mm"], p["airway_height_mm"]
        self.L, self.H = L, H
        self.dev_max = max(p["septum_deviation_mm"], 0.0)
        # inferior turbinate: medial face at the common meatus, lateral face at the meatus
        it_med = self.dev_max + p["it_septum_gap_mm"]
        it_lat = p["floor_width_mm"] - p["inferior_meatus_mm"]
        it_ax = max((it_lat - it_med) / 2.0, 1.5)
        self.it_center = (
            it_med + it_ax,
            p["it_start_mm"] + p["it_length_mm"] / 2,
            p["it_center_z_mm"],
        )
        self.it_axes = (it_ax, p["it_length_mm"] / 2, p["it_height_mm"] / 2)
        # attachment of the inferior turbinate to the lateral wall, above its meatus
        att_x0 = self.it_center[0]
        att_x1 = p["floor_width_mm"] + 1.5
        self.it_att_center = (
            (att_x0 + att_x1) / 2,
            self.it_center[1],
            p["it_center_z_mm"] + 0.3 * p["it_height_mm"],
        )
        self.it_att_axes = (
            (att_x1 - att_x0) / 2 + 0.5,
            0.42 * p["it_length_mm"],
            0.28 * p["it_height_mm"],
        )
        self.it_top = p["it_center_z_mm"] + p["it_height_mm"] / 2
        # middle turbinate: a hanging plate with a root up to the roof
        mt_x = self.dev_max + p["mt_septum_gap_mm"] + p["mt_thickness_mm"] / 2
        mt_y0 = p["mt_start_frac"] * L
        mt_z0 = p["mt_bottom_frac"] * H
        self.mt_start = mt_y0
        self.mt_center = (mt_x, mt_y0 + p["mt_length_mm"] / 2, mt_z0 + p["mt_height_mm"] / 2)
        self.mt_axes = (p["mt_thickness_mm"] / 2, p["mt_length_mm"] / 2, p["mt_height_mm"] / 2)
        root_z = (self.mt_center[2] + H + 4.0) / 2
        self.mt_root_center = (mt_x, self.mt_center[1] + 2.0, root_z)
        self.mt_root_axes = (0.4 * p["mt_thickness_mm"], 0.42 * p["mt_length_mm"], H + 4.0 - root_z)
        # lateral wall: floor width below the inferior turbinate's top, the middle meatus
        # above it, tapering to the olfactory cleft under the roof
        self.x_mid = mt_x + p["mt_thickness_mm"] / 2 + p["middle_meatus_mm"]
        self.x_low = p["floor_width_mm"]
        # superior turbinate: small, high and posterior on the lateral wall
        st_z = 0.8 * H
        st_y0 = 0.6 * L
        self.st_center = (
            self.lateral_x(np.array(st_y0 + 10.0), np.array(st_z)).item() - 0.6,
            st_y0 + p["st_length_mm"] / 2,
            st_z,
        )
        self.st_axes = (2.0, p["st_length_mm"] / 2, 2.4)
        # smooth undulation of the walls: three plane waves, 12-25 mm wavelength
        rng = np.random.default_rng([int(seed), 0xA1])
        dirs = rng.normal(size=(3, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        wavelengths = rng.uniform(12.0, 25.0, size=3)
        self.wave_k = dirs * (2.0 * math.pi / wavelengths)[:, None]
        self.wave_phase = rng.uniform(0.0, 2.0 * math.pi, size=3)

    # -- profiles ----------------------------------------------------------------
    def septum_x(self, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        p = self.p
        yd = p["septum_deviation_y_frac"] * self.L
        zd = p["septum_deviation_z_frac"] * self.H
        return p["septum_deviation_mm"] * np.exp(
            -(((y - yd) / (0.2 * self.L)) ** 2) - ((z - zd) / (0.18 * self.H)) ** 2
        )

    def roof_z(self, y: np.ndarray) -> np.ndarray:
        L, H = self.L, self.H
        vh = self.p["vestibule_height_mm"]
        rise = _smoothstep(0.0, 0.3 * L, y)
        fall = _smoothstep(0.7 * L, L, y)
        return vh + (H - vh) * rise - 0.3 * H * fall

    def lateral_x(self, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        base = self.x_low + (self.x_mid - self.x_low) * _smoothstep(
            self.it_top - 1.0, self.it_top + 3.0, z
        )
        zr = self.roof_z(y)
        z2 = 0.72 * zr
        u = np.clip((z - z2) / np.maximum(zr - z2, 1e-6), 0.0, 1.0)
        x = base + (self.p["roof_width_mm"] - base) * u**1.3
        return x * (0.85 + 0.15 * _smoothstep(0.0, 15.0, y))

    # -- the field ---------------------------------------------------------------
    def __call__(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        k = 1.5
        f = x - self.septum_x(y, z)
        f = _smin(f, self.lateral_x(y, z) - x, k)
        floor = 2.0 * (1.0 - _smoothstep(0.0, 10.0, y))  # nostril sill
        f = _smin(f, z - floor, 2.0)
        f = _smin(f, self.roof_z(y) - z, k)
        f = _smin(f, self.L - y, 3.0)
        wave = np.zeros_like(f)
        for kv, ph in zip(self.wave_k, self.wave_phase, strict=True):
            wave += np.sin(kv[0] * x + kv[1] * y + kv[2] * z + ph)
        f = f + self.p["wobble_mm"] * wave / 3.0
        # turbinates are tissue: smooth subtraction
        for center, axes in (
            (self.it_center, self.it_axes),
            (self.it_att_center, self.it_att_axes),
            (self.mt_center, self.mt_axes),
            (self.mt_root_center, self.mt_root_axes),
            (self.st_center, self.st_axes),
        ):
            f = _smin(f, -_ellipsoid(x, y, z, center, axes), k)
        return f

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box that contains the airway's part inside the block, mm."""
        lo = np.array([-1.5 - 1.0, -3.0, -1.0])
        hi = np.array([max(self.x_low, self.x_mid) + 2.0, self.L + 1.0, self.H + 1.0])
        lo[0] = min(lo[0], -abs(self.p["septum_deviation_mm"]) - 2.0)
        return lo, hi
