"""Procedural tissue appearance: a seeded 3D colour texture and randomised looks.

The mucosa colour is a 3D texture (a Mitsuba ``volume`` texture over a grid that covers
the phantom), so it needs no UV map and is identical on the tissue that stays the same
from one surgical step to the next (same box, same seed). It combines:

- low-frequency colour variation (multi-octave smooth noise, slightly redder/paler);
- a vessel network: the zero set of a smooth 3D noise field cuts the tissue surface in
  curves; ``exp(-(n / width)^2)`` turns the field into thin dark-red lines, plus a finer,
  fainter second network (capillaries).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from chisel.core.geometry import vec3
from sim.config import AppearanceConfig, SimConfig

TEXEL_LEVELS = 1023
"""Texel values are quantised to ``k / 1023`` (10 bits per channel): the renderer packs a
texel into one 32-bit word (``sim.spot_direct.PackedTexture``), a quarter of the memory
traffic of 4 floats, and Mitsuba's reference texture then reads exactly the same values.
The step, 0.001 in linear albedo, moves an 8-bit pixel by at most about 0.2 of a level
(trilinear filtering interpolates between texels, so it makes no bands)."""


@dataclasses.dataclass(frozen=True)
class TextureVolume:
    """A baked colour volume over an axis-aligned world box."""

    rgb: np.ndarray
    """(nz, ny, nx, 3) float32 linear RGB in [0, 1]; index [k, j, i] = voxel (x_i, y_j, z_k).
    Baked values are multiples of 1 / :data:`TEXEL_LEVELS` (10 bits per channel)."""
    box_mm: np.ndarray
    """(2, 3) float64 [[xmin, ymin, zmin], [xmax, ymax, zmax]] the grid spans, mm."""

    @functools.cached_property
    def packed_10bit(self) -> np.ndarray:
        """(nz, ny, nx) uint32 texels packed 10:10:10 (red in the low bits), computed once
        per volume: a phantom's renderers (one per surgical step) share its volumes, and
        checking and packing ~6 M texels costs ~0.15 s. Raises ValueError when a value is
        outside [0, 1] or not a multiple of 1 / :data:`TEXEL_LEVELS`."""
        rgb = np.asarray(self.rgb, dtype=np.float32)
        # float32 is exact enough: k / 1023 in float32 times 1023 is within 1e-4 of k.
        levels = np.rint(rgb * np.float32(TEXEL_LEVELS))
        if levels.min(initial=0) < 0 or levels.max(initial=0) > TEXEL_LEVELS:
            raise ValueError("TextureVolume: texel values must lie in [0, 1]")
        if np.abs(levels * np.float32(1.0 / TEXEL_LEVELS) - rgb).max(initial=0) > 1e-6:
            raise ValueError(
                f"TextureVolume: texel values must be multiples of 1/{TEXEL_LEVELS} "
                "(bake with sim.appearance.texture_volume)"
            )
        q = levels.astype(np.uint32)
        words = q[..., 0] | (q[..., 1] << 10) | (q[..., 2] << 20)
        words.flags.writeable = False
        return words

    @property
    def voxel_mm(self) -> np.ndarray:
        """(3,) float64 voxel size along x, y, z, mm."""
        shape_xyz = np.array(self.rgb.shape[2::-1], dtype=np.float64)
        return (self.box_mm[1] - self.box_mm[0]) / shape_xyz


def _bspline_matrix(n_out: int, step: float) -> tuple[np.ndarray, int]:
    """(n_out, n_lat) cubic B-spline weights sampling a lattice of spacing ``step`` voxels."""
    t = np.arange(n_out, dtype=np.float64) / step + 1.0
    i = np.floor(t).astype(int)
    f = t - i
    w = (
        np.stack(
            [(1 - f) ** 3, 3 * f**3 - 6 * f**2 + 4, -3 * f**3 + 3 * f**2 + 3 * f + 1, f**3], axis=1
        )
        / 6.0
    )
    n_lat = int(i.max()) + 3
    M = np.zeros((n_out, n_lat), dtype=np.float32)
    rows = np.repeat(np.arange(n_out), 4)
    cols = (i[:, None] + np.arange(-1, 3)[None, :]).ravel()
    np.add.at(M, (rows, cols), w.ravel())
    return M, n_lat


def _smooth_noise(
    rng: np.random.Generator, shape: tuple[int, int, int], voxel_mm: float, scale_mm: float
) -> np.ndarray:
    """Zero-mean, unit-std smooth noise on a grid of ``shape`` (z, y, x), features ~scale_mm.

    A random lattice with spacing ``scale_mm`` is sampled with a cubic B-spline (C2, so
    iso-lines are smooth curves), separably: three small matrix products.
    """
    step = max(scale_mm / voxel_mm, 1.0)
    mats = [_bspline_matrix(n, step) for n in shape]
    lattice = rng.normal(size=tuple(m[1] for m in mats)).astype(np.float32)
    out = lattice @ mats[2][0].T  # (Lz, Ly, nx)
    out = mats[1][0] @ out  # (Lz, ny, nx)
    out = (mats[0][0] @ out.reshape(out.shape[0], -1)).reshape(shape)
    out -= out.mean()
    out /= max(float(out.std()), 1e-6)
    return out.astype(np.float32, copy=False)


def texture_volume(box_mm: np.ndarray, cfg: AppearanceConfig, seed: int) -> TextureVolume:
    """Bake the mucosa colour over ``box_mm`` ((2, 3) float, mm) with a seeded pattern.

    The voxel size is ``cfg.texture_voxel_mm``, coarsened so the grid stays within
    ``cfg.max_texture_voxels``; values are quantised to 10 bits (:data:`TEXEL_LEVELS`).
    Same box, config and seed -> same bytes.
    """
    box = np.asarray(box_mm, dtype=np.float64)
    extent = np.maximum(box[1] - box[0], 1e-3)
    voxel = max(cfg.texture_voxel_mm, float((np.prod(extent) / cfg.max_texture_voxels) ** (1 / 3)))
    nxyz = np.maximum(np.ceil(extent / voxel).astype(int), 2)
    shape = (int(nxyz[2]), int(nxyz[1]), int(nxyz[0]))
    box = np.stack([box[0], box[0] + nxyz * voxel])
    rng = np.random.default_rng([int(seed), 7])
    var1 = _smooth_noise(rng, shape, voxel, cfg.variation_scale_mm)
    var2 = _smooth_noise(rng, shape, voxel, cfg.variation_scale_mm * 3.0)
    ves1 = _smooth_noise(rng, shape, voxel, cfg.vessel_scale_mm)
    ves2 = _smooth_noise(rng, shape, voxel, cfg.vessel_scale_mm * 0.45)
    base = np.asarray(cfg.albedo_rgb, dtype=np.float32)
    vessel_rgb = np.asarray(cfg.vessel_rgb, dtype=np.float32)
    # One contiguous plane per channel, operations in place (a bake is ~6 M texels, and
    # temporaries of the interleaved (..., 3) array cost more than the arithmetic); each
    # texel gets the same float32 operations in the same order as written out here:
    #   bright = 1 + 0.6 c var1, red = 0.4 c var2 (brightness and redness vary);
    #   rgb = base * bright * (1 + 0.5 red, 1 - red, 1 - red);
    #   vessels = max(exp(-(ves1 / w)^2), 0.5 exp(-(ves2 / 0.6 w)^2)), weight = s vessels;
    #   rgb = (1 - weight) rgb + weight vessel_rgb, quantised to 10 bits.
    bright = var1
    bright *= cfg.color_variation * 0.6
    bright += 1.0
    red = var2
    red *= cfg.color_variation * 0.4
    w = cfg.vessel_width
    weight = ves1
    weight /= w
    np.square(weight, out=weight)
    np.negative(weight, out=weight)
    np.exp(weight, out=weight)
    fine = ves2
    fine /= 0.6 * w
    np.square(fine, out=fine)
    np.negative(fine, out=fine)
    np.exp(fine, out=fine)
    fine *= 0.5
    np.maximum(weight, fine, out=weight)
    weight *= cfg.vessel_strength
    keep = np.subtract(1.0, weight, dtype=np.float32)
    rgb = np.empty(shape + (3,), dtype=np.float32)
    plane = np.empty(shape, dtype=np.float32)
    tint = np.empty(shape, dtype=np.float32)
    words = np.zeros(shape, dtype=np.uint32)
    for c in range(3):
        np.multiply(bright, base[c], out=plane)
        if c == 0:
            np.multiply(red, 0.5, out=tint)
            tint += 1.0
        else:
            np.subtract(1.0, red, out=tint)
        plane *= tint
        plane *= keep
        np.multiply(weight, vessel_rgb[c], out=tint)
        plane += tint
        np.clip(plane, 0.0, 1.0, out=plane)
        plane *= TEXEL_LEVELS
        np.round(plane, out=plane)
        words |= plane.astype(np.uint32) << np.uint32(10 * c)
        plane /= TEXEL_LEVELS
        rgb[..., c] = plane
    volume = TextureVolume(rgb, box)
    # The levels are at hand: the packed texels (TextureVolume.packed_10bit, whose checks
    # of a volume from elsewhere cost ~0.4 s per bake) are stored as that property's value.
    words.flags.writeable = False
    volume.__dict__["packed_10bit"] = words
    return volume


def cut_texture_volume(box_mm: np.ndarray, cfg: SimConfig, seed: int) -> TextureVolume:
    """The base colour of cut faces (``cfg.cut``): raw tissue with blood blotches, baked
    like :func:`texture_volume` over the same box (wide, dense "vessels" of blood colour
    make the blotches); its own seed stream, so the mucosa's texture is unchanged."""
    c = cfg.cut
    look = dataclasses.replace(
        cfg.appearance,
        albedo_rgb=c.albedo_rgb,
        color_variation=0.3,
        variation_scale_mm=2.0,
        vessel_strength=c.blood_strength,
        vessel_scale_mm=c.blood_scale_mm,
        vessel_width=0.45,
        vessel_rgb=c.blood_rgb,
    )
    return texture_volume(box_mm, look, int(seed) + 104_729)


def randomize(cfg: SimConfig, seed: int) -> SimConfig:
    """Copy of ``cfg`` with appearance, light and sensor drawn from ``cfg.randomization``.

    Used for training data (one draw per sequence). Same seed -> same draw.
    """
    r = cfg.randomization
    rng = np.random.default_rng([int(seed), 11])

    def u(rr: tuple[float, float]) -> float:
        return float(rng.uniform(rr[0], rr[1]))

    scale, hue = u(r.albedo_scale), u(r.hue_shift)
    a0 = np.asarray(cfg.appearance.albedo_rgb) * scale
    albedo = np.clip(a0 * np.array([1.0 + hue, 1.0 - hue, 1.0 - hue]), 0.02, 0.98)
    appearance = dataclasses.replace(
        cfg.appearance,
        albedo_rgb=vec3(albedo),
        vessel_strength=u(r.vessel_strength),
        roughness=u(r.roughness),
        specular=u(r.specular),
    )
    light = dataclasses.replace(cfg.light, intensity=cfg.light.intensity * u(r.light_scale))
    imaging = dataclasses.replace(
        cfg.imaging, exposure=u(r.exposure), shot_noise=u(r.shot_noise), read_noise=u(r.read_noise)
    )

    # Drawn after the earlier values so that those stay what they were before these ranges
    # existed. A [0, 0] range (the default) keeps the section's own value.
    def u_or(rr: tuple[float, float], own: float) -> float:
        x = u(rr)
        return own if rr[1] <= 0 else x

    tools = dataclasses.replace(cfg.tools, fraction=u_or(r.tools_fraction, cfg.tools.fraction))
    smoke = dataclasses.replace(
        cfg.smoke, density_per_mm=u_or(r.smoke_density_per_mm, cfg.smoke.density_per_mm)
    )
    blur = dataclasses.replace(cfg.blur, shutter=u_or(r.blur_shutter, cfg.blur.shutter))
    lens = dataclasses.replace(
        cfg.lens,
        smear_probability=u_or(r.lens_smear_probability, cfg.lens.smear_probability),
    )
    blood = dataclasses.replace(cfg.blood, strength=u_or(r.blood_strength, cfg.blood.strength))
    return dataclasses.replace(
        cfg,
        appearance=appearance,
        blood=blood,
        light=light,
        imaging=imaging,
        tools=tools,
        smoke=smoke,
        blur=blur,
        lens=lens,
    )
