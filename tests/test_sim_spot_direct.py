"""The fast spot-light direct integrator against Mitsuba's ``direct`` integrator and geometry."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
import trimesh

from chisel.core.geometry import Camera, look_at, make_transform
from chisel.core.mitsuba_variant import load_mitsuba
from chisel.core.raycast import MeshRaycaster
from sim.appearance import TextureVolume, texture_volume
from sim.collision import TissueDistance
from sim.config import ImagingConfig, SimConfig, replace_in
from sim.imaging import sensor_image
from sim.render import MeshRenderer, _frame_seed, _noise_key
from sim.spot_direct import PackedTexture, pixel_ray_frames, principled_eval
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


def _jit_mitsuba():
    mi, variant = load_mitsuba("auto")
    if variant == "scalar_rgb":
        pytest.skip("the inline BSDF, texture and sensor need a JIT variant")
    import drjit as dr

    return mi, dr


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.mark.parametrize(("roughness", "specular"), [(0.3, 0.5), (0.08, 0.9), (0.7, 0.2)])
def test_inline_principled_matches_mitsuba_eval(roughness: float, specular: float) -> None:
    """Random normals and directions, both hemispheres: the same value as ``principled``."""
    mi, dr = _jit_mitsuba()
    rng = np.random.default_rng(4)
    n_dirs = 20_000
    normal = _unit(rng.normal(size=(n_dirs, 3)))
    wi = _unit(rng.normal(size=(n_dirs, 3)))
    wo = _unit(rng.normal(size=(n_dirs, 3)))
    wi[:50] = normal[:50]  # normal incidence and exact mirror configurations
    wo[50:100] = 2 * np.sum(wi[50:100] * normal[50:100], -1, keepdims=True) * normal[50:100]
    wo[50:100] -= wi[50:100]
    base = rng.uniform(0.02, 0.95, size=(n_dirs, 3))

    def v3(a: np.ndarray, cls=mi.Vector3f):
        return cls(np.ascontiguousarray(a.T, dtype=np.float32))

    bsdf = mi.load_dict(
        {
            "type": "principled",
            "base_color": {"type": "volume", "volume": {"type": "constvolume"}},
            "roughness": roughness,
            "specular": specular,
        }
    )
    # Mitsuba's own eval, in its local shading frame, with a per-lane base colour.
    ref = []
    for k in range(3):
        b = np.zeros_like(base)
        b[:, k] = 1.0
        si = dr.zeros(mi.SurfaceInteraction3f, n_dirs)
        si.sh_frame = mi.Frame3f(v3(normal))
        si.wi = si.sh_frame.to_local(v3(wi))
        f = bsdf.eval(mi.BSDFContext(), si, si.sh_frame.to_local(v3(wo)))
        ref.append(np.asarray(f)[k] if np.asarray(f).ndim == 2 else np.asarray(f))
    eta = 2.0 / (1.0 - np.sqrt(0.08 * specular)) - 1.0
    ours = np.asarray(
        principled_eval(
            dr, v3(normal), v3(wi), v3(wo), v3(np.ones_like(base), mi.Color3f), roughness, eta
        )
    )
    ref = np.asarray(ref)
    # constvolume is 1 everywhere: the reference is the BSDF for a white base colour.
    np.testing.assert_allclose(ours, ref, rtol=2e-4, atol=1e-6)
    front = (np.sum(normal * wi, -1) > 0) & (np.sum(normal * wo, -1) > 0)
    assert front.sum() > 3000 and np.all(ours[:, ~front] == 0)
    # Linear in the base colour (diffuse lobe) plus a colourless specular lobe.
    ours_b = np.asarray(
        principled_eval(dr, v3(normal), v3(wi), v3(wo), v3(base, mi.Color3f), roughness, eta)
    )
    ours_0 = np.asarray(
        principled_eval(dr, v3(normal), v3(wi), v3(wo), v3(0 * base, mi.Color3f), roughness, eta)
    )
    np.testing.assert_allclose(ours_b, ours_0 + (ours - ours_0) * base.T, rtol=1e-4, atol=1e-6)
    assert ours_0[:, front].max() > 0.1  # the specular lobe is there


def test_packed_texture_matches_mitsuba_gridvolume() -> None:
    mi, dr = _jit_mitsuba()
    box = np.array([[-3.0, 1.0, 2.0], [5.0, 7.5, 6.0]])
    cfg = replace_in(SimConfig(), **{"appearance.texture_voxel_mm": 0.4})
    tex = texture_volume(box, cfg.appearance, 3)
    assert tex.rgb.shape[0] > 4
    rng = np.random.default_rng(5)
    # Inside the box and up to a voxel beyond it (clamped border).
    pts = rng.uniform(tex.box_mm[0] - 0.5, tex.box_mm[1] + 0.5, size=(50_000, 3))
    p = mi.Point3f(np.ascontiguousarray(pts.T, dtype=np.float32))
    b = tex.box_mm
    ref_tex = mi.load_dict(
        {
            "type": "volume",
            "volume": {
                "type": "gridvolume",
                "grid": mi.VolumeGrid(np.ascontiguousarray(tex.rgb)),
                "to_world": mi.ScalarTransform4f(make_transform(np.diag(b[1] - b[0]), b[0])),
            },
        }
    )
    si = dr.zeros(mi.SurfaceInteraction3f, len(pts))
    si.p = p
    ref = np.asarray(ref_tex.eval(si))
    ours = np.asarray(PackedTexture(mi, tex).eval(p))
    np.testing.assert_allclose(ours, ref, atol=2e-5)
    assert ref.std() > 0.01


def test_packed_texels_are_the_10_bit_levels_and_off_grid_values_are_refused() -> None:
    box = np.array([[0.0, 0.0, 0.0], [4.0, 3.0, 2.0]])
    cfg = replace_in(SimConfig(), **{"appearance.texture_voxel_mm": 0.5})
    tex = texture_volume(box, cfg.appearance, 1)
    # Independent of the float32 packing: the levels in float64, shifted by hand.
    k = np.round(tex.rgb.astype(np.float64) * 1023).astype(np.int64)
    words = tex.packed_10bit.astype(np.int64)
    np.testing.assert_array_equal(words & 1023, k[..., 0])
    np.testing.assert_array_equal((words >> 10) & 1023, k[..., 1])
    np.testing.assert_array_equal(words >> 20, k[..., 2])
    assert tex.packed_10bit is tex.packed_10bit  # packed once per volume
    # A volume built from the same values packs the same words.
    np.testing.assert_array_equal(TextureVolume(tex.rgb, tex.box_mm).packed_10bit, words)
    rgb = tex.rgb.copy()
    rgb[0, 0, 0, 1] += 0.3 / 1023
    with pytest.raises(ValueError, match="multiples of 1/1023"):
        _ = TextureVolume(rgb, tex.box_mm).packed_10bit
    rgb = tex.rgb.copy()
    rgb[1, 0, 0, 2] = 1.0 + 1.0 / 1023
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        _ = TextureVolume(rgb, tex.box_mm).packed_10bit


def test_render_depth_from_the_colour_launch_is_exact() -> None:
    """``render`` traces depth with colour in one launch: same as ``render_depth``, Open3D;
    its RGB is the drjit sensor's, placed on the used pixels."""
    mesh = toy_meshes(1)[1]
    r = _renderer(mesh, **{"imaging.spp": 4})
    T = look_at([34.0, 1.0, 0.5], [47.0, -1.5, 0.0], [0, 0, 1])
    frame = r.render(T, index=2, seed=9)
    np.testing.assert_array_equal(frame.depth_mm, r.render_depth(T)[0])
    np.testing.assert_array_equal(frame.valid, np.isfinite(frame.depth_mm))
    ref = MeshRaycaster.from_trimesh(mesh).render_depth(r.camera, T)
    both = np.isfinite(ref) & np.isfinite(frame.depth_mm)
    assert both.mean() > 0.9
    assert np.median(np.abs(frame.depth_mm[both] - ref[both])) <= 0.01
    # The 8-bit RGB packed into one word and scattered in drjit: the sensor's values of
    # the used pixels, channel by channel, and 0 outside the field stop.
    rad = r._direct.radiance(T, seed=_frame_seed(9, 2))
    q = r._direct.sensor(rad, r._gain_used, r.cfg.imaging, _noise_key(9, 2))
    expected = np.zeros(frame.rgb.shape, np.uint8)
    expected[r.field_stop] = np.asarray(q, dtype=np.uint32).T
    np.testing.assert_array_equal(frame.rgb, expected)
    assert frame.rgb.flags.c_contiguous and frame.rgb[r.field_stop].mean() > 20
    again = r.render(T, index=2, seed=9)
    np.testing.assert_array_equal(again.rgb, frame.rgb)
    assert not np.array_equal(r.render(T, index=3, seed=9).rgb, frame.rgb)


def test_sensor_in_drjit_matches_the_numpy_sensor_model() -> None:
    """Same tone curve without noise; same noise statistics (not the same draws) with it."""
    mesh = toy_meshes(1)[1]
    r = _renderer(mesh)
    mi = r.mi
    stop = r.field_stop
    gain = r._gain
    rng = np.random.default_rng(6)
    rad = np.zeros(stop.shape + (3,), np.float32)
    rad[stop] = rng.uniform(0.0, 0.4, size=(int(stop.sum()), 3))
    rad_dr = mi.Color3f(np.ascontiguousarray(rad[stop].T))

    def jit(cfg: ImagingConfig, key: int) -> np.ndarray:
        q = np.asarray(r._direct.sensor(rad_dr, r._gain_used, cfg, key), dtype=np.uint32).T
        out = np.zeros(stop.shape + (3,), np.uint8)
        out[stop] = q
        return out

    quiet = replace_in(SimConfig(), **{"imaging.shot_noise": 0.0, "imaging.read_noise": 0.0})
    for ae in (True, False):
        cfg = dataclasses.replace(quiet.imaging, auto_exposure=ae, exposure=1.7)
        ref = sensor_image(rad, gain, cfg, np.random.default_rng(0))
        ours = jit(cfg, 1)
        # float32 rounding of the exposure mean and of the gamma curve: at most one level
        assert np.abs(ours.astype(int) - ref).max() <= 1
        assert (ours != ref).mean() < 0.01
        assert ours[~stop].max() == 0
    noisy = dataclasses.replace(quiet.imaging, shot_noise=0.01, read_noise=0.01)
    flat = np.zeros(stop.shape + (3,), np.float32)
    flat[stop] = 0.05
    rad_dr = mi.Color3f(np.ascontiguousarray(flat[stop].T))
    gain1 = np.where(stop, 1.0, 0.0).astype(np.float32)
    r._gain_used, saved = mi.Float(gain1[stop]), r._gain_used
    try:
        ours = jit(noisy, 7)[stop].astype(float)
        np.testing.assert_array_equal(jit(noisy, 7)[stop], ours)
        assert not np.array_equal(jit(noisy, 8)[stop], ours)
    finally:
        r._gain_used = saved
    ref = sensor_image(flat, gain1, noisy, np.random.default_rng(1))[stop].astype(float)
    assert ours.mean() == pytest.approx(ref.mean(), abs=0.3)
    assert ours.std() == pytest.approx(ref.std(), rel=0.05)
    assert ours.std() > 3.0
    # No correlation between channels or neighbouring pixels (independent draws).
    c = np.corrcoef(np.stack([ours[:-1, 0], ours[1:, 0], ours[:-1, 1]]))
    assert np.abs(c[np.triu_indices(3, 1)]).max() < 0.05


def test_sample_rays_fall_in_their_strata_and_primary_hits_match_open3d() -> None:
    """The rays behind every colour sample: inside their pixel's stratum (under the lens
    distortion), and their first hit where Open3D's ray caster finds it."""
    mesh = toy_meshes(1)[1]
    r = _renderer(mesh)  # 64 spp: 8 x 8 strata per pixel
    S = r._direct
    T = look_at([34.0, 1.0, 0.5], [47.0, -1.5, 0.0], [0, 0, 1])
    origin, d_world = S.sample_rays(T, seed=4)
    t_mm = r.primary_hit_mm(T, seed=4).astype(np.float64).ravel()
    o = np.asarray(origin, dtype=np.float64).ravel()
    d = np.asarray(d_world, dtype=np.float64).T
    n = S.n_pixels * S.spp
    assert d.shape == (n, 3) and t_mm.shape == (n,)
    np.testing.assert_allclose(o, T[:3, 3], atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)

    uv, z = r.camera.project(d @ T[:3, :3])  # world -> camera directions
    assert (z > 0).all()
    u, v = r.camera.pixel_grid()
    pix = np.repeat(np.stack([u[r.field_stop], v[r.field_stop]], -1), S.spp, axis=0)
    offset = uv - pix  # in [-0.5, 0.5] px up to the linearised distortion
    assert np.abs(offset).max() < 0.5 + 0.01
    side = 8
    s = np.tile(np.arange(S.spp), S.n_pixels)
    stratum = np.clip(np.floor((offset + 0.5) * side), 0, side - 1)
    inside = (stratum[:, 0] == s % side) & (stratum[:, 1] == s // side)
    assert inside.mean() > 0.99, inside.mean()

    ref = TissueDistance(mesh).first_hit_mm(np.broadcast_to(o, d.shape), o + d)  # Open3D
    np.testing.assert_array_equal(np.isfinite(t_mm), np.isfinite(ref))
    hit = np.isfinite(ref)
    assert hit.mean() > 0.9
    err = np.abs(t_mm[hit] - ref[hit])
    assert np.median(err) < 1e-4 and np.quantile(err, 0.999) < 1e-3, err.max()
    depth_only = MeshRenderer(mesh, replace_in(r.cfg, depth_only=True), depth_only=True)
    with pytest.raises(ValueError, match="depth_only=True"):
        depth_only.primary_hit_mm(T)
