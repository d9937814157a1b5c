"""Mitsuba camera conventions and depth against an independent ray caster (Open3D)."""

from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest
import scipy.ndimage as ndi

from chisel.core import mitsuba_variant as variant_mod
from chisel.core.errors import CameraError, PoseError
from chisel.core.geometry import Camera, look_at, transform_points
from chisel.core.raycast import MeshRaycaster
from sim.config import CameraConfig, SimConfig, replace_in
from sim.errors import ConfigError, VariantError
from sim.mitsuba_camera import (
    T_CV_FROM_MITSUBA,
    mitsuba_to_world,
    opencv_from_mitsuba_to_world,
    render_grid,
    z_depth_from_mitsuba_depth,
)
from sim.render import MeshRenderer
from sim.synthetic import toy_meshes

SMALL = {"camera.width": 64, "camera.height": 48}


@functools.cache
def _mesh():
    return toy_meshes(1)[1]


def _poses() -> list[np.ndarray]:
    # Inside the chamber (centre (38, 0, 0), radius 9), looking at the bitten wall and sideways.
    return [
        look_at([34.0, 1.0, 0.5], [47.0, -1.5, 0.0], [0, 0, 1]),
        look_at([36.0, -2.0, 2.0], [44.0, 6.0, -3.0], [0, 0, 1]),
        look_at([20.0, 0.5, -0.5], [40.0, 0.0, 0.0], [0, 1, 0]),
    ]


def _smooth_pixels(ref: np.ndarray) -> np.ndarray:
    """Valid pixels whose 5x5 neighbourhood is valid and free of depth jumps (no silhouettes)."""
    valid = np.isfinite(ref)
    filled = np.where(valid, ref, 0.0)
    span = ndi.maximum_filter(filled, size=5) - ndi.minimum_filter(
        np.where(valid, ref, 1e9), size=5
    )
    return ndi.binary_erosion(valid, iterations=2) & (span < 0.3 * filled)


def _cfg(dist: tuple | None) -> SimConfig:
    cfg = replace_in(SimConfig(depth_only=True), **SMALL)
    if dist is not None:
        cfg = replace_in(cfg, **{"camera.dist": dist})
    return cfg


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0, 0.0), (-0.18, 0.04, 0.0004, -0.0003, 0.0)])
def test_depth_matches_open3d(dist: tuple) -> None:
    cfg = _cfg(dist)
    renderer = MeshRenderer(_mesh(), cfg, depth_only=True)
    ref_caster = MeshRaycaster.from_trimesh(_mesh(), backend="open3d")
    depth = renderer.render_depth(np.stack(_poses()))
    for T, d in zip(_poses(), depth, strict=True):
        ref = ref_caster.render_depth(renderer.camera, T)
        np.testing.assert_array_equal(np.isfinite(d), np.isfinite(ref))
        smooth = _smooth_pixels(ref)
        assert smooth.mean() > 0.4
        diff = np.abs(d[smooth] - ref[smooth])
        assert np.median(diff) <= 0.01, np.median(diff)
        assert np.percentile(diff, 99) <= 0.01


@pytest.mark.parametrize("distorted", [False, True])
def test_sensor_depth_aov_matches_open3d(distorted: bool) -> None:
    """The Mitsuba *sensor* path (used by scalar_rgb and by every RGB render) is aligned.

    Undistorted: the sensor's pixel-centre rays are the camera's, so the AOV depth converted
    from near-plane ray length equals the reference. Distorted: nearest-neighbour remap of
    the undistorted grid, so only a looser bound holds (documented in docs/sim.md).
    """
    cfg = _cfg(None if distorted else (0.0,) * 5)
    renderer = MeshRenderer(_mesh(), cfg, depth_only=True)
    renderer_rgb = MeshRenderer(_mesh(), replace_in(cfg, depth_only=False), texture=_texture())
    ref_caster = MeshRaycaster.from_trimesh(_mesh(), backend="open3d")
    for T in _poses():
        d = renderer_rgb._depth_via_sensor(T)
        ref = ref_caster.render_depth(renderer.camera, T)
        smooth = _smooth_pixels(ref) & np.isfinite(d)
        diff = np.abs(d[smooth] - ref[smooth])
        assert smooth.mean() > 0.4
        if distorted:
            assert np.median(diff) <= 0.1, np.median(diff)
        else:
            assert np.median(diff) <= 0.01, np.median(diff)


@functools.cache
def _texture():
    from sim.appearance import texture_volume

    return texture_volume(
        np.array([[-1.0, -19.0, -19.0], [61.0, 19.0, 19.0]]), SimConfig().appearance, 0
    )


@pytest.mark.parametrize("distorted", [False, True])
def test_projected_pixel_is_where_mitsuba_ray_hits(distorted: bool) -> None:
    """A pixel's Mitsuba sensor ray hits a point that K, dist and the pose project back onto it."""
    cfg = _cfg(None if distorted else (0.0,) * 5)
    r = MeshRenderer(_mesh(), replace_in(cfg, depth_only=False), texture=_texture())
    mi = r.mi
    sensor = r.scene.sensors()[0]
    grid = r.grid
    T = _poses()[0]
    r.params["sensor.to_world"] = mi.ScalarTransform4f(mitsuba_to_world(T))
    r.params.update()
    cam = r.camera
    rng = np.random.default_rng(0)
    uv = np.stack(
        [rng.uniform(0, cam.width - 1, 20).round(), rng.uniform(0, cam.height - 1, 20).round()], 1
    )
    for u, v in uv.astype(int):
        gx = grid.map_x[v, u] if distorted else u
        gy = grid.map_y[v, u] if distorted else v
        pos = mi.Point2f(float((gx + 0.5) / grid.width), float((gy + 0.5) / grid.height))
        ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
        si = r.scene.ray_intersect(ray)
        hit = np.array(si.p, dtype=np.float64).ravel()
        p_cam = transform_points(np.linalg.inv(T), hit[None])
        proj, z = cam.project(p_cam)
        assert z[0] > 0
        np.testing.assert_allclose(proj[0], [u, v], atol=2e-3)


def test_mitsuba_pose_conversion_round_trip_and_axes() -> None:
    T = look_at([1.0, 2.0, 3.0], [4.0, -2.0, 8.0], [0, 0, 1])
    T_mi = mitsuba_to_world(T)
    np.testing.assert_allclose(opencv_from_mitsuba_to_world(T_mi), T, atol=1e-12)
    # Mitsuba +x is our -x (left), +y is our -y (up), +z is shared (forward).
    np.testing.assert_allclose(T_mi[:3, 0], -T[:3, 0])
    np.testing.assert_allclose(T_mi[:3, 1], -T[:3, 1])
    np.testing.assert_allclose(T_mi[:3, 2], T[:3, 2])
    np.testing.assert_array_equal(T_CV_FROM_MITSUBA @ T_CV_FROM_MITSUBA, np.eye(4))
    with pytest.raises(PoseError):
        mitsuba_to_world(np.full((4, 4), np.nan))
    bad = T.copy()
    bad[:3, :3] *= 1.5
    with pytest.raises(PoseError):
        mitsuba_to_world(bad)


def test_near_plane_depth_conversion_is_z_depth() -> None:
    cam = Camera.from_fov(40, 30, 80)
    grid = render_grid(cam)
    assert grid.identity
    rays = grid.rays_cam()
    z_true = 12.0
    near = 0.05
    # A fronto-parallel plane at z = 12: ray length from the origin = 12 |r|; from the near plane
    # subtract near / d_z = near |r|.
    t_aov = (z_true - near) * np.linalg.norm(rays, axis=-1)
    t_aov[0, 0] = 0.0  # a miss
    z = z_depth_from_mitsuba_depth(t_aov, grid, near)
    assert np.isnan(z[0, 0])
    np.testing.assert_allclose(z[np.isfinite(z)], z_true, atol=1e-5)


def test_render_grid_covers_distorted_rays_and_refuses_extreme() -> None:
    cam = CameraConfig(width=64, height=48).camera()
    grid = render_grid(cam)
    assert not grid.identity
    assert grid.map_x.min() >= 0 and grid.map_x.max() <= grid.width - 1
    assert grid.map_y.min() >= 0 and grid.map_y.max() <= grid.height - 1
    folding = Camera(64, 48, cam.K, np.array([-0.5, 0.0, 0.0, 0.0, 0.0]))
    with pytest.raises(CameraError, match="folds over"):
        render_grid(folding)
    wide = Camera(64, 48, cam.K, np.array([-0.3, 0.05, 0.0, 0.0, 0.0]))
    with pytest.raises(CameraError, match="undistorted grid"):
        render_grid(wide)
    render_grid(wide, max_upscale=6.0)


def test_intrinsics_that_do_not_match_image_size_are_refused() -> None:
    K = ((300.0, 0.0, 159.5), (0.0, 300.0, 127.5), (0.0, 0.0, 1.0))
    CameraConfig(width=320, height=256, K=K)  # fine
    with pytest.raises(ConfigError, match="do not match the image size"):
        CameraConfig(width=64, height=48, K=K)
    with pytest.raises(ConfigError, match="8x8"):
        CameraConfig(width=4, height=48)


def test_variant_probe_and_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    assert variant_mod.choose_variant("auto") in ("cuda_ad_rgb", "llvm_ad_rgb")
    ok, detail = variant_mod.probe_variant("llvm_ad_rgb")
    assert ok, detail
    with pytest.raises(VariantError):
        variant_mod.probe_variant("no_such_variant")
    # A failing JIT variant: auto falls back to scalar_rgb with a warning; explicit -> error.
    real = variant_mod.probe_variant

    def fake(v: str, timeout_s: float = 180.0) -> tuple[bool, str]:
        return (False, "LLVM ERROR: simulated") if v != "scalar_rgb" else real(v)

    monkeypatch.setattr(variant_mod, "probe_variant", fake)
    monkeypatch.delenv("SIM_MITSUBA_VARIANT", raising=False)
    variant_mod.choose_variant.cache_clear()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert variant_mod.choose_variant("auto") == "scalar_rgb"
        assert any("scalar_rgb" in str(w.message) for w in caught)
        with pytest.raises(VariantError, match="simulated"):
            variant_mod.choose_variant("llvm_ad_rgb")
    finally:
        variant_mod.choose_variant.cache_clear()
    assert variant_mod.configure_llvm_env() is None or "LLVM" in variant_mod.configure_llvm_env()
