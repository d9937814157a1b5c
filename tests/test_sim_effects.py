"""Smoke, motion blur and lens smear: analytic checks, seeds, zero strength = off (bytes),
bad strengths refused naming the key with nothing written."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from chisel.core.geometry import look_at
from chisel.io.sequence import Sequence
from sim.appearance import randomize, texture_volume
from sim.cli import main
from sim.config import (
    BlurConfig,
    LensConfig,
    RandomizationConfig,
    SimConfig,
    SmokeConfig,
    replace_in,
)
from sim.effects import (
    FrameEffects,
    apply_smoke,
    blur_poses,
    smear_mask,
    smear_schedule,
    smoke_density,
)
from sim.errors import ConfigError
from sim.pipeline import render_phantom
from sim.render import MeshRenderer
from sim.synthetic import CHAMBER_CENTER_MM, write_toy_phantom

TINY = {
    "camera.width": 48,
    "camera.height": 40,
    "imaging.spp": 1,
    "appearance.texture_voxel_mm": 1.0,
    "paths.preop_frames": 2,
    "paths.intraop_frames": 3,
    "paths.eval_poses": 1,
}


def test_smoke_is_the_two_way_attenuation_plus_veil() -> None:
    cfg = SmokeConfig(density_per_mm=0.05, patchiness=0.0, albedo=0.5, color_rgb=(1.0, 1.0, 1.0))
    rad = np.zeros((4, 4, 3), np.float32)
    rad[1:3, 1:3] = [[[0.2, 0.1, 0.05]]]
    rad[0, 0] = [0.1, 0.1, 0.1]
    depth = np.full((4, 4), 10.0, np.float32)
    depth[1, 1] = 20.0
    sigma = smoke_density((4, 4), cfg, seed=0)
    assert np.allclose(sigma, 0.05)  # no patches
    out = apply_smoke(rad, depth, sigma, cfg)
    inside = np.any(rad > 0, axis=-1)
    mean = rad[inside].mean()
    for (v, u), z in (((1, 2), 10.0), ((1, 1), 20.0)):
        t = np.exp(-2 * 0.05 * z)
        assert np.allclose(out[v, u], rad[v, u] * t + 0.5 * mean * (1 - t), rtol=1e-5)
    assert np.all(out[~inside] == 0)  # outside the field stop stays black
    # Patches vary the density, seeded.
    patchy = dataclasses.replace(cfg, patchiness=0.8)
    a, b = smoke_density((40, 48), patchy, 3), smoke_density((40, 48), patchy, 3)
    assert np.array_equal(a, b) and a.std() > 0.01 and a.min() >= 0
    assert not np.array_equal(a, smoke_density((40, 48), patchy, 4))


def test_blur_poses_interpolate_back_towards_the_previous_frame() -> None:
    T = look_at(np.zeros(3), np.array([0.0, 0.0, 10.0]), np.array([0.0, -1.0, 0.0]))
    prev = T.copy()
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    prev[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    prev[:3, 3] = [2.0, 0.0, 0.0]
    p = blur_poses(prev, T, shutter=0.5, n=3)
    assert np.allclose(p[0], T)
    assert np.allclose(p[2][:3, 3], [1.0, 0.0, 0.0])  # half way
    angle = np.degrees(np.arccos((np.trace(T[:3, :3].T @ p[2][:3, :3]) - 1) / 2))
    assert angle == pytest.approx(10.0, abs=1e-6)


def test_smear_schedule_and_mask_are_seeded() -> None:
    cfg = LensConfig(smear_probability=0.2, smear_frames=5)
    a, b = smear_schedule(60, cfg, 1), smear_schedule(60, cfg, 1)
    assert np.array_equal(a, b) and (a >= 0).any() and (a < 0).any()
    for v in np.unique(a[a >= 0]):  # each smear: one contiguous run of smear_frames
        idx = np.flatnonzero(a == v)
        assert np.all(np.diff(idx) == 1) and (len(idx) == 5 or idx[-1] == 59)
    assert (smear_schedule(60, dataclasses.replace(cfg, smear_strength=0.0), 1) < 0).all()
    m = smear_mask((40, 48), 0.7, 9)
    assert m.max() == pytest.approx(0.7, abs=0.05) and m.min() == 0.0
    assert np.array_equal(m, smear_mask((40, 48), 0.7, 9))


@pytest.fixture(scope="module")
def renderer() -> tuple[MeshRenderer, np.ndarray, np.ndarray]:
    from sim.synthetic import toy_meshes  # noqa: PLC0415

    mesh = toy_meshes(0)[0]
    cfg = replace_in(SimConfig(), **TINY)
    tex = texture_volume(np.stack([mesh.bounds[0] - 1, mesh.bounds[1] + 1]), cfg.appearance, 0)
    r = MeshRenderer(mesh, cfg, tex)
    up = np.array([0.0, 0.0, 1.0])
    T = look_at(CHAMBER_CENTER_MM - [4.0, 0, 0], CHAMBER_CENTER_MM + [9.0, 0, 0], up)
    T_prev = look_at(CHAMBER_CENTER_MM - [6.0, 1.0, 0], CHAMBER_CENTER_MM + [9.0, 2.0, 0], up)
    return r, T, T_prev


def _fx(cfg: SimConfig, T_prev: np.ndarray | None, smear: np.ndarray | None) -> FrameEffects:
    return FrameEffects(cfg.smoke, 5, cfg.blur, T_prev, smear, 6.0)


def test_each_effect_at_zero_strength_gives_the_bytes_of_off(renderer) -> None:
    r, T, T_prev = renderer
    off = r.render(T, index=2, seed=7).rgb
    cfg = r.cfg
    zero = [
        _fx(replace_in(cfg, **{"smoke.density_per_mm": 0.0, "smoke.albedo": 2.0}), None, None),
        _fx(replace_in(cfg, **{"blur.shutter": 0.0, "blur.subframes": 8}), T_prev, None),
        _fx(cfg, T_prev, None),
    ]
    for fx in zero:
        assert not fx.active
        assert np.array_equal(r.render(T, index=2, seed=7, effects=fx).rgb, off)
    # Smear at zero strength: no smeared frame is ever scheduled.
    assert (smear_schedule(50, LensConfig(smear_probability=1.0, smear_strength=0.0), 3) < 0).all()
    # And each switched on changes the frame (so the comparison above can fail).
    on = [
        _fx(replace_in(cfg, **{"smoke.density_per_mm": 0.1}), None, None),
        _fx(replace_in(cfg, **{"blur.shutter": 1.0}), T_prev, None),
        _fx(cfg, None, smear_mask(r.camera.shape, 0.8, 2)),
    ]
    for fx in on:
        assert fx.active
        f = r.render(T, index=2, seed=7, effects=fx)
        assert not np.array_equal(f.rgb, off)
        assert np.array_equal(f.rgb, r.render(T, index=2, seed=7, effects=fx).rgb)  # seeded
        # Ground-truth depth is the frame's own, unaffected.
        assert np.array_equal(f.depth_mm, r.render(T, index=2, seed=7).depth_mm, equal_nan=True)


def test_smoke_lowers_contrast_more_with_depth(renderer) -> None:
    r, T, _ = renderer
    fx = _fx(
        replace_in(r.cfg, **{"smoke.density_per_mm": 0.08, "smoke.patchiness": 0.0}), None, None
    )
    clean = r.render(T, index=1, seed=2).rgb.astype(float)
    smoky = r.render(T, index=1, seed=2, effects=fx).rgb.astype(float)
    assert smoky[r.field_stop].std() < clean[r.field_stop].std()


def test_pipeline_zero_strength_equals_off_and_bad_strengths_are_refused(tmp_path: Path) -> None:
    phantom = write_toy_phantom(tmp_path / "p", n_bites=1)
    base = replace_in(SimConfig(), **TINY)
    zero = replace_in(
        base,
        **{"smoke.density_per_mm": 0.0, "blur.shutter": 0.0, "lens.smear_probability": 0.0},
    )
    zero = replace_in(zero, **{"lens.smear_probability": 0.9, "lens.smear_strength": 0.0})
    render_phantom(phantom, tmp_path / "a", base, progress=False)
    render_phantom(phantom, tmp_path / "b", zero, progress=False)
    a, b = Sequence(tmp_path / "a/step_01"), Sequence(tmp_path / "b/step_01")
    for i in range(len(a)):
        assert np.array_equal(a.rgb(i), b.rgb(i))
    # Out of range: the key is named, nothing is written.
    for key, value in (
        ("smoke.density_per_mm", 3.0),
        ("blur.shutter", 1.5),
        ("lens.smear_strength", -0.1),
        ("randomization.smoke_density_per_mm", [0.0, 5.0]),
    ):
        section, name = key.split(".")
        cfgfile = tmp_path / "bad.yaml"
        cfgfile.write_text(yaml.safe_dump({section: {name: value}}))
        out = tmp_path / f"bad_{section}"
        rc = main(
            ["render", "--phantom", str(phantom), "--out", str(out), "--config", str(cfgfile)]
        )
        assert rc == 1 and not out.exists()
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            replace_in(SimConfig(), **{key: value})


def test_randomization_draws_effect_strengths_in_range() -> None:
    r = RandomizationConfig(smoke_density_per_mm=(0.01, 0.1), blur_shutter=(0.2, 0.6))
    cfg = replace_in(SimConfig(), randomization=r)
    drawn = [randomize(cfg, s) for s in range(5)]
    assert all(0.01 <= d.smoke.density_per_mm <= 0.1 for d in drawn)
    assert all(0.2 <= d.blur.shutter <= 0.6 for d in drawn)
    assert len({d.smoke.density_per_mm for d in drawn}) == 5
    # [0, 0] keeps the section's own value; earlier draws unchanged by the new ranges.
    own = replace_in(SimConfig(), **{"smoke.density_per_mm": 0.04})
    assert randomize(own, 1).smoke.density_per_mm == 0.04
    assert randomize(own, 1).appearance == randomize(SimConfig(), 1).appearance
    assert BlurConfig().shutter == 0.0 and SmokeConfig().density_per_mm == 0.0
