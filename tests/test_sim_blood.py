"""The blood film below fresh cuts (``blood.*``, ``sim/blood.py``).

The film's faces are checked against the analytic geometry of a flat wall with a
rectangular cut: blood runs straight down gravity's in-plane direction, so a film face
lies in the band the cut's lower edge sweeps downhill, within the film's length, and its
coverage is ``strength * (1 - s / length)``, ``s`` its distance below the edge. Fresh cut
faces are checked against the toy phantom's bite boxes; renders with the film against
the same renders without it (same bytes where there is no film, redder where there is).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh
import yaml

from chisel.core.geometry import look_at
from sim.appearance import texture_volume
from sim.blood import blood_film_weight, fresh_cut_faces
from sim.cli import main
from sim.config import BloodConfig, ConfigError, SimConfig, load_config, replace_in
from sim.render import MeshRenderer
from sim.synthetic import (
    BITE_EXTENTS_MM,
    bite_centers_mm,
    toy_cut_faces,
    toy_meshes,
    write_toy_phantom,
)

CELL_MM = 20.0 / 32
"""Grid step of the wall (a 20 mm slab face subdivided 5 times)."""
CUT_Y = (-6.25, -1.875)
CUT_Z = (-3.125, 3.125)
"""The cut rectangle on the wall, on grid lines (both triangles of a cell labelled)."""


def _slab() -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    """A closed 2 x 20 x 20 mm slab; its +x face (the wall) carries a rectangular cut.
    Returns the mesh, the wall's faces and the cut's faces."""
    mesh = trimesh.creation.box(extents=[2.0, 20.0, 20.0])
    for _ in range(5):
        mesh = mesh.subdivide()
    c = mesh.triangles_center
    wall = mesh.face_normals[:, 0] > 0.999
    cut = (
        wall
        & (c[:, 1] > CUT_Y[0])
        & (c[:, 1] < CUT_Y[1])
        & (c[:, 2] > CUT_Z[0])
        & (c[:, 2] < CUT_Z[1])
    )
    return mesh, wall, cut


def _cfg(**kw: object) -> BloodConfig:
    base: dict = {
        "enabled": True,
        "strength": 0.9,
        "streaks": (4, 4),
        "film_length_mm": (6.0, 6.0),
        "width_mm": (1.0, 1.0),
    }
    base.update(kw)
    return BloodConfig(**base)


def test_film_is_the_band_below_the_cut_thinning_with_distance() -> None:
    mesh, wall, cut = _slab()
    cfg = _cfg()
    w = blood_film_weight(mesh, cut, cfg, seed=3)
    film = w > 0
    c = mesh.triangles_center[film]
    assert film.sum() >= 20
    assert np.all(wall[film]) and not np.any(film & cut)
    # Gravity +y: the cut's lower edge is y = CUT_Y[1]; nothing above it or beyond the
    # film's length below it, nothing beside the cut beyond half a streak's width.
    s = c[:, 1] - CUT_Y[1]
    assert s.min() > 0 and s.max() < 6.0
    half = 0.5 + CELL_MM
    assert c[:, 2].min() > CUT_Z[0] - half and c[:, 2].max() < CUT_Z[1] + half
    # Straight streaks: the coverage is the strength less the distance run below the edge.
    np.testing.assert_allclose(w[film], 0.9 * (1.0 - s / 6.0), atol=1e-5)
    # Each streak is at most a width wide: 4 streaks cover at most 4 x (1 mm + a cell) of z.
    z_cells = np.unique(np.floor(c[:, 2] / CELL_MM))
    assert len(z_cells) * CELL_MM <= 4 * (1.0 + 2 * CELL_MM)


def test_film_follows_gravity_in_the_wall_plane() -> None:
    """Gravity down and sideways (and partly into the wall): the streaks follow its
    in-plane part, a diagonal; every film face's uphill line meets the cut."""
    mesh, wall, cut = _slab()
    g = np.array([-0.5, 1.0, 1.0])
    w = blood_film_weight(mesh, cut, _cfg(gravity=tuple(g)), seed=5)
    film = w > 0
    assert film.sum() >= 20 and np.all(wall[film]) and not np.any(film & cut)
    d = np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0)  # in-plane steepest descent
    margin = 0.5 + CELL_MM
    t = np.linspace(0.0, 6.0 + CELL_MM, 400)
    for p in mesh.triangles_center[film]:
        up = p[None, 1:] - t[:, None] * d[None, 1:]
        inside = (
            (up[:, 0] > CUT_Y[0] - margin)
            & (up[:, 0] < CUT_Y[1] + margin)
            & (up[:, 1] > CUT_Z[0] - margin)
            & (up[:, 1] < CUT_Z[1] + margin)
        )
        assert inside.any(), p


def test_no_fresh_cut_no_strength_or_flat_wall_gives_no_film() -> None:
    mesh, _, cut = _slab()
    assert not blood_film_weight(mesh, np.zeros_like(cut), _cfg(), seed=1).any()
    assert not blood_film_weight(mesh, cut, _cfg(strength=0.0), seed=1).any()
    # Gravity into the wall: the wall is level, the blood has nowhere to run.
    assert not blood_film_weight(mesh, cut, _cfg(gravity=(-1.0, 0.0, 0.0)), seed=1).any()


def test_same_seed_same_film_other_seed_other_streaks() -> None:
    mesh, _, cut = _slab()
    cfg = _cfg(streaks=(2, 3), film_length_mm=(3.0, 8.0), width_mm=(0.6, 1.4))
    a = blood_film_weight(mesh, cut, cfg, seed=11)
    assert np.array_equal(a, blood_film_weight(mesh, cut, cfg, seed=11))
    assert not np.array_equal(a, blood_film_weight(mesh, cut, cfg, seed=12))


def test_fresh_cut_faces_are_the_last_bites() -> None:
    """Step 2 of the toy cut bite 2 after bite 1: fresh = the faces on bite 2's box and
    not on bite 1's (from the boxes' planes, not from the meshes' distances)."""
    meshes = toy_meshes(2)
    labels = [toy_cut_faces(m, k) for k, m in enumerate(meshes)]
    fresh = fresh_cut_faces(meshes[2], labels[2], meshes[1], labels[1])
    c = meshes[2].triangles_center
    q1 = np.abs(c - bite_centers_mm(2)[0]) / (BITE_EXTENTS_MM / 2)
    on_box1 = np.abs(q1.max(axis=1) - 1.0) < 1e-5
    expected = labels[2] & ~on_box1
    assert expected.sum() > 10 and (labels[2] & on_box1).sum() > 10
    assert np.array_equal(fresh, expected)
    assert np.array_equal(fresh_cut_faces(meshes[1], labels[1], meshes[0], labels[0]), labels[1])


def _renderers(spp: int = 1) -> tuple:
    mesh, _, cut = _slab()
    cfg = replace_in(
        SimConfig(),
        **{
            "camera.width": 48,
            "camera.height": 40,
            "imaging.spp": spp,
            "appearance.texture_voxel_mm": 1.0,
            "blood.enabled": True,
        },
    )
    box = np.stack([mesh.bounds[0] - 1, mesh.bounds[1] + 1])
    tex = texture_volume(box, cfg.appearance, 0)
    film = blood_film_weight(mesh, cut, _cfg(streaks=(5, 5), width_mm=(1.5, 1.5)), seed=2)
    plain = MeshRenderer(mesh, cfg, tex)
    zero = MeshRenderer(mesh, cfg, tex, blood_weight=np.zeros(len(mesh.faces)))
    bloody = MeshRenderer(mesh, cfg, tex, blood_weight=film)
    # The camera 12 mm in front of the wall, looking at the film below the cut.
    T = look_at(
        np.array([13.0, 1.0, 0.0]), np.array([1.0, 1.0, 0.0]), up=np.array([0.0, -1.0, 0.0])
    )
    return mesh, film, plain, zero, bloody, T


def _face_ids(mesh: trimesh.Trimesh, T: np.ndarray, renderer: MeshRenderer) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    d = renderer.camera.rays_cam().reshape(-1, 3)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)) @ T[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], axis=1).astype(np.float32)
    ids = scene.cast_rays(o3d.core.Tensor(rays))["primitive_ids"].numpy().view(np.int32)  # miss: -1
    return ids.astype(np.int64).reshape(renderer.camera.shape)


@pytest.mark.parametrize("reference", [False, True], ids=["spot_direct", "mitsuba_direct"])
def test_film_pixels_are_redder_and_the_rest_unchanged(reference: bool) -> None:
    mesh, film, plain, zero, bloody, T = _renderers()
    assert zero.blood_weight is None  # all-zero coverage: no film at all
    render = "render_radiance_reference" if reference else "render_radiance"
    a = getattr(plain, render)(T, seed=4)
    b = getattr(bloody, render)(T, seed=4)
    ids = _face_ids(mesh, T, plain)
    # Pixels inside the film (coverage > 0.5 here and at the neighbours: a sample may land
    # anywhere in its pixel, and the reference remaps bilinearly), and pixels whose
    # neighbourhood sees no film face at all.
    from scipy.ndimage import binary_dilation, binary_erosion  # noqa: PLC0415

    covered = binary_erosion((ids >= 0) & (film[np.maximum(ids, 0)] > 0.5))
    near = binary_dilation((ids >= 0) & (film[np.maximum(ids, 0)] > 0), iterations=2)
    clear = (ids >= 0) & ~near & (a.sum(axis=2) > 0)
    assert covered.sum() >= 10 and clear.sum() >= 100
    green_share = lambda r: r[..., 1] / np.maximum(r.sum(axis=2), 1e-12)  # noqa: E731
    ga, gb = green_share(a)[covered], green_share(b)[covered]
    assert np.all(gb < ga) and np.median(gb / ga) < 0.7, np.median(gb / ga)
    if reference:  # its render grid is finer than the pixels: an edge sample leaks a little
        np.testing.assert_allclose(a[clear], b[clear], rtol=1e-3)
    else:
        assert np.array_equal(a[clear], b[clear])


def test_blood_off_or_zero_strength_gives_the_same_bytes() -> None:
    _, _, plain, zero, _, T = _renderers()
    fa, fb = plain.render(T, index=1, seed=9), zero.render(T, index=1, seed=9)
    assert fa.rgb is not None and np.array_equal(fa.rgb, fb.rgb)


def test_blood_keys_through_config_file_and_cli(tmp_path: Path) -> None:
    cfg_file = tmp_path / "blood.yaml"
    cfg_file.write_text(
        yaml.safe_dump(
            {
                "blood": {"enabled": True, "streaks": [3, 3], "width_mm": [1.0, 1.5]},
                "camera": {"width": 32, "height": 24},
                "imaging": {"spp": 1},
                "paths": {"preop_frames": 2, "intraop_frames": 2, "eval_poses": 1},
            }
        )
    )
    assert load_config(cfg_file).blood.streaks == (3, 3)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"blood": {"strength": 1.5}}))
    with pytest.raises(ConfigError, match="blood.strength"):
        load_config(bad)
    with pytest.raises(ConfigError, match="blood.gravity"):
        BloodConfig(gravity=(0.0, 0.0, 0.0))
    phantom = write_toy_phantom(tmp_path / "p", n_bites=2)
    out = tmp_path / "out"
    assert main(["render", "--phantom", str(phantom), "--out", str(out), "--config",
                 str(cfg_file), "--quiet"]) == 0  # fmt: skip
    header = json.loads((out / "render.json").read_text())
    assert header["config"]["blood"]["enabled"] is True
    for k in (1, 2):
        meta = json.loads((out / f"step_{k:02d}" / "sequence.json").read_text())["meta"]
        assert meta["blood_faces"] > 0
    assert "blood_faces" not in json.loads((out / "preop" / "sequence.json").read_text())["meta"]
