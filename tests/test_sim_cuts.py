"""Cut faces: the faces a cut created get the cut material, and no other face does.

Per pixel, the class of the rendered colour (mucosa or cut, from two base colours that
share no channel) is compared with the face ids of the primary hits from Open3D's ray
caster and the phantom's labels; both the fast integrator and Mitsuba's own ``direct``
over the scene's ``blendbsdf`` are checked.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from chisel.core.geometry import look_at
from sim.appearance import texture_volume
from sim.config import SimConfig, replace_in
from sim.errors import PhantomError
from sim.materials import SharedMaterials
from sim.phantom import load_mesh, load_phantom
from sim.pipeline import load_cut_faces
from sim.render import MeshRenderer
from sim.spot_direct import pixel_ray_frames
from sim.synthetic import CHAMBER_CENTER_MM, write_toy_phantom


def _face_ids(mesh, T: np.ndarray, rays_cam: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    d = rays_cam / np.linalg.norm(rays_cam, axis=1, keepdims=True)
    d = d @ T[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], axis=1).astype(np.float32)
    return scene.cast_rays(o3d.core.Tensor(rays))["primitive_ids"].numpy().astype(np.int64)


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("cuts")
    phantom = load_phantom(write_toy_phantom(root / "p", n_bites=2))
    mesh = load_mesh(phantom.steps[2].mesh_path)
    labels = load_cut_faces(phantom, 2, len(mesh.faces))
    cfg = replace_in(
        SimConfig(),
        **{
            "camera.width": 64,
            "camera.height": 48,
            "imaging.spp": 4,
            "appearance.specular": 0.0,  # diffuse only: the colour is the base colour's
            "appearance.color_variation": 0.0,
            "appearance.vessel_strength": 0.0,
            "appearance.albedo_rgb": [0.5, 0.5, 0.0],
            "appearance.texture_voxel_mm": 1.0,
        },
    )
    box = np.stack([mesh.bounds[0] - 1, mesh.bounds[1] + 1])
    mucosa = texture_volume(box, cfg.appearance, 0)
    cut_look = replace_in(cfg, **{"appearance.albedo_rgb": [0.5, 0.0, 0.5]}).appearance
    cut = texture_volume(box, cut_look, 0)
    renderer = MeshRenderer(mesh, cfg, mucosa, cut_faces=labels, cut_texture=cut)
    eye = CHAMBER_CENTER_MM + np.array([2.0, 0.0, 0.0])
    T = look_at(eye, CHAMBER_CENTER_MM + np.array([9.0, 0.0, 0.0]), up=np.array([0.0, 0.0, 1.0]))
    return phantom, mesh, labels, renderer, T


def _classes(rad: np.ndarray) -> np.ndarray:
    """0 dark, 1 mucosa only (green, no blue), 2 cut only (blue, no green), 3 mixed."""
    g, b = rad[..., 1] > 1e-6, rad[..., 2] > 1e-6
    return np.where(g & b, 3, np.where(g, 1, np.where(b, 2, 0)))


def test_labels_are_read_and_checked(setup, tmp_path: Path) -> None:
    phantom, mesh, labels, _, _ = setup
    assert labels is not None and labels.any() and not labels.all()
    assert load_cut_faces(phantom, 0, len(load_mesh(phantom.steps[0].mesh_path).faces)).sum() == 0
    with pytest.raises(PhantomError, match="cut_faces"):
        load_cut_faces(phantom, 2, len(mesh.faces) + 1)


@pytest.mark.parametrize("reference", [False, True], ids=["spot_direct", "mitsuba_direct"])
def test_cut_faces_get_the_cut_material_and_no_other_face(setup, reference: bool) -> None:
    _, mesh, labels, renderer, T = setup
    cam = renderer.camera
    used = renderer.field_stop
    if reference:
        rad = renderer.render_radiance_reference(T, seed=3)
    else:
        rad = renderer.render_radiance(T, seed=3)
    cls = _classes(rad)
    # Open3D: which face each of 5x5 points across a pixel (edges included) hits.
    ray, d_du, d_dv = pixel_ray_frames(cam, used)
    grid = np.linspace(-0.5, 0.5, 5)
    hits = [_face_ids(mesh, T, ray + a * d_du + b * d_dv) for a in grid for b in grid]
    hits.insert(0, hits.pop(12))  # the pixel centre first
    hit_cut = np.stack([labels[np.maximum(h, 0)] & (h >= 0) for h in hits])
    all_cut = np.zeros(cam.shape, bool)
    no_cut = np.zeros(cam.shape, bool)
    all_cut[used] = hit_cut.all(axis=0)
    no_cut[used] = ~hit_cut.any(axis=0) & (hits[0] >= 0)
    if reference:  # the bilinear remap blends neighbours: only pixels inside a region
        from scipy.ndimage import binary_erosion  # noqa: PLC0415

        all_cut, no_cut = binary_erosion(all_cut), binary_erosion(no_cut)
    assert all_cut.sum() >= 20 and no_cut.sum() >= 200
    lit = cls > 0
    assert np.all(cls[all_cut & lit] == 2), np.unique(cls[all_cut & lit], return_counts=True)
    assert np.all(cls[no_cut & lit] == 1), np.unique(cls[no_cut & lit], return_counts=True)
    # A cut colour appears only where some sample can hit a cut face.
    some_cut = np.zeros(cam.shape, bool)
    some_cut[used] = hit_cut.any(axis=0)
    if not reference:
        assert not np.any((cls == 2) & ~some_cut)


def test_without_labels_one_material(setup) -> None:
    _, mesh, labels, renderer, T = setup
    cfg = renderer.cfg
    box = np.stack([mesh.bounds[0] - 1, mesh.bounds[1] + 1])
    plain = MeshRenderer(mesh, cfg, texture_volume(box, cfg.appearance, 0))
    assert not np.any(_classes(plain.render_radiance(T, seed=3)) >= 2)
    with pytest.raises(ValueError, match="cut-face labels"):
        MeshRenderer(mesh, cfg, texture_volume(box, cfg.appearance, 0), cut_faces=labels[:-1])


def test_renderers_sharing_materials_render_the_same_bytes(setup) -> None:
    # A phantom's renderers share the tissue BSDF and packed textures (sim.pipeline):
    # step 2 rendered after step 1 built them equals step 2 rendered on its own.
    phantom, mesh, labels, alone, T = setup
    cfg = alone.cfg
    box = np.stack([mesh.bounds[0] - 1, mesh.bounds[1] + 1])
    mucosa = texture_volume(box, cfg.appearance, 0)
    cut_look = replace_in(cfg, **{"appearance.albedo_rgb": [0.5, 0.0, 0.5]}).appearance
    cut = texture_volume(box, cut_look, 0)
    shared = SharedMaterials()
    step1 = load_mesh(phantom.steps[1].mesh_path)
    labels1 = load_cut_faces(phantom, 1, len(step1.faces))
    first = MeshRenderer(step1, cfg, mucosa, cut_faces=labels1, cut_texture=cut, shared=shared)
    second = MeshRenderer(mesh, cfg, mucosa, cut_faces=labels, cut_texture=cut, shared=shared)
    assert first._direct is not None and second._direct is not None
    assert second._direct.texture is first._direct.texture  # shared, not built again
    assert second.mesh.bsdf() is first.mesh.bsdf()
    for render in ("render_radiance", "render_radiance_reference"):
        a = getattr(second, render)(T, seed=3)
        b = getattr(alone, render)(T, seed=3)
        # two renderers of one mesh in one process already differ by a float32 ulp (the
        # JIT's kernels), shared materials or not
        assert a.max() > 0.05 and np.allclose(a, b, rtol=1e-6, atol=1e-6), render
