"""The fast spot-light direct integrator against Mitsuba's ``direct`` integrator and geometry."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh

from chisel.geometry import Camera, look_at
from sim.appearance import texture_volume
from sim.config import SimConfig, replace_in
from sim.render import MeshRenderer
from sim.spot_direct import pixel_ray_frames
from sim.synthetic import toy_meshes

SMALL = {"camera.width": 64, "camera.height": 48, "imaging.spp": 64}
T_LOOK_Z = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0])


@functools.cache
def _shadow_scene() -> trimesh.Trimesh:
    """A wall (front face at z = 21 mm) and a 4 mm cube floating in front of it at z = 12."""
    wall = trimesh.creation.box(extents=(80.0, 80.0, 2.0))
    wall.apply_translation([0.0, 0.0, 22.0])
    cube = trimesh.creation.box(extents=(4.0, 4.0, 4.0))
    cube.apply_translation([0.0, 0.0, 12.0])
    # Subdivided so the averaged vertex normals stay close to the face normals.
    mesh = trimesh.util.concatenate([wall.subdivide_to_size(2.0), cube.subdivide_to_size(0.5)])
    mesh.merge_vertices()
    return mesh


def _texture(mesh: trimesh.Trimesh, cfg: SimConfig):
    box = np.stack([mesh.bounds[0] - 1.0, mesh.bounds[1] + 1.0])
    return texture_volume(box, cfg.appearance, 0)


def _renderer(mesh: trimesh.Trimesh, **over) -> MeshRenderer:
    cfg = replace_in(SimConfig(), **{**SMALL, **over})
    r = MeshRenderer(mesh, cfg, _texture(mesh, cfg))
    if not r.jit:
        pytest.skip("the fast integrator needs a JIT variant")
    return r


def test_pixel_ray_frames_follow_the_distortion_within_a_pixel() -> None:
    cam = Camera.from_fov(64, 48, 85.0, (2.5, -1.5), np.array([-0.18, 0.04, 4e-4, -3e-4, 0.0]))
    used = np.zeros(cam.shape, bool)
    used[::7, ::5] = True
    ray, d_du, d_dv = pixel_ray_frames(cam, used)
    u, v = cam.pixel_grid()
    u, v = u[used], v[used]
    np.testing.assert_allclose(ray, cam.rays_cam()[used], atol=1e-9)
    for a, b in [(0.5, 0.5), (-0.5, 0.25), (0.0, -0.5), (0.37, -0.41)]:
        uv, z = cam.project(ray + a * d_du + b * d_dv)
        assert (z > 0).all()
        err = np.hypot(uv[:, 0] - (u + a), uv[:, 1] - (v + b))
        assert err.max() < 0.01, err.max()  # second order in the offset: << one pixel
    with pytest.raises(ValueError, match="used"):
        pixel_ray_frames(cam, used[:-1])


@pytest.mark.parametrize("offset", [(0.0, 1.9, 0.0), (0.0, 0.0, 0.0)])
def test_matches_mitsuba_direct_and_shadows_follow_the_light_offset(offset: tuple) -> None:
    """Same image as Mitsuba's ``direct`` (64 spp, no distortion); shadows only if offset."""
    r = _renderer(_shadow_scene(), **{"camera.dist": (0.0,) * 5, "light.offset_mm": offset})
    assert r._direct is not None and r._direct.shadows == any(offset)
    stop = r.field_stop
    fast = r.render_radiance(T_LOOK_Z, seed=3)
    ref = r.render_radiance_reference(T_LOOK_Z, seed=3)
    assert np.all(fast[~stop] == 0)
    lum_f, lum_r = fast[stop].mean(-1), ref[stop].mean(-1)
    # Measured: 1e-5 relative in the mean, 0.15 % mean |difference| (sampling noise);
    # dropping the shadow rays alone would give 2 % in both.
    assert lum_f.mean() == pytest.approx(lum_r.mean(), rel=0.005)
    assert np.abs(lum_f - lum_r).mean() < 0.01 * lum_r.mean()
    # Shadowed wall: hit at the wall's depth, yet (almost) no light. The depth is exact.
    depth = r.render_depth(T_LOOK_Z)[0]
    wall = stop & (np.abs(depth - 21.0) < 0.05)
    lit = np.median(fast[wall].mean(-1))
    dark_f = wall & (fast.mean(-1) < 0.05 * lit)
    dark_r = wall & (ref.mean(-1) < 0.05 * lit)
    if any(offset):
        assert dark_f.sum() >= 15
        assert (dark_f & dark_r).sum() >= 0.7 * max(dark_f.sum(), dark_r.sum())
    else:
        assert dark_f.sum() == 0 and dark_r.sum() == 0


def test_matches_mitsuba_direct_under_distortion_on_the_toy_phantom() -> None:
    mesh = toy_meshes(1)[1]
    r = _renderer(mesh)
    T = look_at([34.0, 1.0, 0.5], [47.0, -1.5, 0.0], [0, 0, 1])
    stop = r.field_stop
    fast = r.render_radiance(T, seed=1)[stop].mean(-1)
    ref = r.render_radiance_reference(T, seed=1)[stop].mean(-1)
    # Measured: 1e-4 relative in the mean, 0.6 % mean |difference| (noise and the
    # reference's bilinear remap).
    assert fast.mean() == pytest.approx(ref.mean(), rel=0.005)
    assert np.abs(fast - ref).mean() < 0.02 * ref.mean()
    # Same seed -> same values; another seed -> other noise.
    np.testing.assert_array_equal(r.render_radiance(T, seed=1)[stop].mean(-1), fast)
    assert not np.array_equal(r.render_radiance(T, seed=2)[stop].mean(-1), fast)
