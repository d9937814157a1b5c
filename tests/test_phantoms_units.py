"""Unit tests of the phantom generator against analytic truth (fast, no full phantom)."""

from __future__ import annotations

import gzip
import math

import manifold3d as m3d
import nibabel as nib
import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes

from phantoms.anatomy import arrays_from_manifold, drop_air_pockets, manifold_from_arrays
from phantoms.bites import Bite, apply_bites, cutter_manifold
from phantoms.ct import (
    ISO_HU,
    SurfaceDistance,
    grid_for_box,
    hu_from_sd,
    labels_from_sd,
    nifti_gz_bytes,
    update_sd,
)
from phantoms.errors import (
    BiteMissError,
    NotManifoldError,
    OutputError,
    ParameterRangeError,
    PhantomError,
    UnknownParameterError,
    UnknownTargetError,
)
from phantoms.io import atomic_dir, check_output_dir
from phantoms.params import PARAM_RANGES, PhantomConfig, sample_params

# ------------------------------------------------------------------ parameters


def test_sampled_params_lie_in_their_ranges_and_depend_on_the_seed():
    a, b = sample_params(0), sample_params(1)
    for p in (a, b):
        assert set(p) == set(PARAM_RANGES)
        for name, (lo, hi, _) in PARAM_RANGES.items():
            assert lo <= p[name] <= hi, name
    assert a != b
    assert sample_params(0) == a
    assert isinstance(a["ethmoid_cells"], int)


def test_overrides_replace_sampled_values():
    p = sample_params(0, {"airway_length_mm": 70.0, "ethmoid_cells": 3})
    assert p["airway_length_mm"] == 70.0 and p["ethmoid_cells"] == 3


@pytest.mark.parametrize(
    ("overrides", "error"),
    [
        ({"nose_length_mm": 50.0}, UnknownParameterError),
        ({"airway_length_mm": 200.0}, ParameterRangeError),
        ({"airway_length_mm": float("nan")}, ParameterRangeError),
        ({"airway_length_mm": "long"}, ParameterRangeError),
        ({"ethmoid_cells": 2.5}, ParameterRangeError),
    ],
)
def test_bad_overrides_raise_specific_errors(overrides, error):
    with pytest.raises(error) as info:
        sample_params(0, overrides)
    assert list(overrides)[0] in str(info.value)
    with pytest.raises(error):
        PhantomConfig(overrides=overrides)


@pytest.mark.parametrize(
    ("kwargs", "error", "name"),
    [
        ({"seed": -1}, ParameterRangeError, "seed"),
        ({"seed": 1.5}, ParameterRangeError, "seed"),
        ({"n_bites": 0}, ParameterRangeError, "n_bites"),
        ({"n_bites": 21}, ParameterRangeError, "n_bites"),
        ({"target": "frontal_sinus"}, UnknownTargetError, "target"),
        ({"spacing_mm": 0.0}, ParameterRangeError, "spacing_mm"),
        ({"spacing_mm": 1.0, "mucosa_mm": 1.0}, ParameterRangeError, "mucosa_mm"),
        ({"noise_hu": -5.0}, ParameterRangeError, "noise_hu"),
        ({"bite_size_mm": (5.0, 2.0)}, ParameterRangeError, "bite_size_mm"),
        ({"bite_size_mm": (2.0, 9.0)}, ParameterRangeError, "bite_size_mm"),
        ({"roi_margin_mm": -1.0}, ParameterRangeError, "roi_margin_mm"),
        ({"mesh_edge_mm": 0.1}, ParameterRangeError, "mesh_edge_mm"),
        ({"tet": "yes"}, ParameterRangeError, "tet"),
    ],
)
def test_bad_config_fields_raise_specific_errors(kwargs, error, name):
    with pytest.raises(error) as info:
        PhantomConfig(**kwargs)
    assert info.value.source == name
    assert isinstance(info.value, PhantomError) and isinstance(info.value, ValueError)


# ------------------------------------------------------------------ CT model


def _sphere_solid(radius: float, center=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    return arrays_from_manifold(m3d.Manifold.sphere(radius, 256).translate(center))


def test_signed_distance_grid_matches_the_analytic_sphere():
    r = 6.0
    v, f = _sphere_solid(r)
    grid = grid_for_box((-r, -r, -r), (r, r, r), 0.5)
    pts = grid.points()
    sd = SurfaceDistance(v, f).signed_distance_grid(pts, clip_mm=(1.5, 0.5), spacing_mm=0.5)
    truth = np.clip(np.linalg.norm(pts, axis=-1) - r, -1.5, 0.5)
    # the 256-segment polyhedron lies within ~0.005 mm of the true sphere
    assert np.abs(sd - truth).max() < 0.01


def test_hu_iso_surface_reproduces_a_plane_exactly():
    spacing = 0.5
    n = np.array([0.3, -0.5, 0.81])
    n /= np.linalg.norm(n)
    grid = grid_for_box((-5, -5, -5), (5, 5, 5), spacing)
    pts = grid.points().astype(np.float64)
    sd = (pts @ n - 0.37).astype(np.float32)  # air on the +n side
    hu = hu_from_sd(sd, spacing, mucosa_mm=1.0).astype(np.float32)
    verts, _, _, _ = marching_cubes(hu, level=ISO_HU)
    world = verts @ grid.T_world_from_voxel[:3, :3].T + grid.T_world_from_voxel[:3, 3]
    inner = np.all(np.abs(world) < 4.0, axis=1)
    # exact up to the int16 rounding of HU (0.5 HU / 1040 HU per voxel pair)
    assert np.abs(world[inner] @ n - 0.37).max() < 1e-3


def test_hu_iso_surface_of_a_sphere_is_sub_voxel():
    r, spacing = 5.0, 0.5
    v, f = _sphere_solid(r, (0.1, -0.2, 0.3))
    grid = grid_for_box((-6, -6, -6), (6, 6, 6), spacing)
    sd = SurfaceDistance(v, f).signed_distance_grid(grid.points(), (1.5, spacing), spacing)
    hu = hu_from_sd(sd, spacing, 1.0).astype(np.float32)
    verts, _, _, _ = marching_cubes(hu, level=ISO_HU)
    world = verts @ grid.T_world_from_voxel[:3, :3].T + grid.T_world_from_voxel[:3, 3]
    radius = np.linalg.norm(world - np.array([0.1, -0.2, 0.3]), axis=1)
    assert np.abs(radius - r).max() < 0.05 * spacing * 2


def test_labels_and_hu_follow_the_documented_model():
    sd = np.array([2.0, 0.6, 0.01, -0.01, -0.5, -0.99, -1.0, -3.0], np.float32)
    labels = labels_from_sd(sd, mucosa_mm=1.0)
    assert labels.tolist() == [0, 0, 0, 1, 1, 1, 2, 2]
    hu = hu_from_sd(sd, spacing_mm=0.5, mucosa_mm=1.0)
    assert hu[0] == -1000 and hu[-1] == 700
    assert hu[4] == 40  # 0.5 mm deep: soft tissue, no bone yet
    assert abs(int(hu[2]) + 480) < 15 and abs(int(hu[3]) + 480) < 15
    assert np.all((hu < ISO_HU) == (labels == 0))
    noise = np.full(sd.shape, 10.0, np.float32)
    assert np.array_equal(hu_from_sd(sd, 0.5, 1.0, noise), hu + 10)


def test_single_ray_occupancy_with_recheck_matches_three_rays():
    v, f = _sphere_solid(6.0)
    grid = grid_for_box((-7, -7, -7), (7, 7, 7), 0.25)
    surface = SurfaceDistance(v, f)
    pts = grid.points()
    assert np.array_equal(surface.inside_grid(pts), surface.inside(pts))


def test_incremental_update_equals_full_recompute():
    v, f = _sphere_solid(6.0)
    solid = manifold_from_arrays(v, f)
    cutter = m3d.Manifold.sphere(1.8, 64).translate((5.5, 0.4, 0.2))
    after = solid - cutter
    grid = grid_for_box((-7, -7, -7), (7, 7, 7), 0.5)
    pts = grid.points()
    clip = (1.5, 0.5)
    sd0 = SurfaceDistance(v, f).signed_distance_grid(pts, clip, 0.5)
    va, fa = arrays_from_manifold(after)
    surface = SurfaceDistance(va, fa)
    box = cutter.bounding_box()
    sd1 = update_sd(sd0, grid, surface, np.asarray(box[:3]), np.asarray(box[3:]), clip)
    full = surface.signed_distance_grid(pts, clip, 0.5)
    assert np.abs(sd1 - full).max() < 1e-5
    assert (labels_from_sd(sd1, 1.0) != labels_from_sd(sd0, 1.0)).any()


def test_nifti_bytes_are_deterministic_and_carry_the_affine():
    grid = grid_for_box((0, 0, 0), (3, 4, 5), 0.5)
    vol = np.arange(np.prod(grid.shape), dtype=np.int16).reshape(grid.shape)
    a = nifti_gz_bytes(vol, grid.T_world_from_voxel)
    assert a == nifti_gz_bytes(vol, grid.T_world_from_voxel)
    assert a[4:8] == b"\x00\x00\x00\x00"  # gzip header mtime
    img = nib.Nifti1Image.from_bytes(gzip.decompress(a))
    ras_from_lps = np.diag([-1.0, -1.0, 1.0, 1.0])  # NIfTI's world is RAS, the phantom's LPS
    assert np.allclose(img.affine, ras_from_lps @ grid.T_world_from_voxel)
    assert np.array_equal(np.asarray(img.dataobj), vol)
    # voxel (i, j, k) -> its centre
    assert np.allclose(
        ras_from_lps @ img.affine @ [2, 3, 4, 1],
        [*(np.asarray(grid.origin_mm) + 0.5 * np.array([2, 3, 4])), 1],
    )


# ------------------------------------------------------------------ bites


def _box_solid(size=(20.0, 20.0, 2.0)) -> m3d.Manifold:
    return m3d.Manifold.cube(size, center=True)


def test_bite_removes_cutter_intersection_and_nothing_else():
    plate = _box_solid()  # a 2 mm "lamella"
    bite = Bite((0.0, 0.0, 0.0), (3.0, 4.0, 5.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1)), "ellipsoid")
    (res,) = apply_bites(plate, [bite])
    # analytic: ellipsoid (1.5, 2, 2.5) cut by |z| <= 1: pi a b (2h - 2h^3 / (3 c^2))
    a, b, c, h = 1.5, 2.0, 2.5, 1.0
    analytic = math.pi * a * b * (2 * h - 2 * h**3 / (3 * c**2))
    assert res.removed_volume_mm3 == pytest.approx(analytic, rel=0.01)
    assert plate.volume() - res.tissue.volume() == pytest.approx(res.removed_volume_mm3, rel=1e-9)


def test_rounded_box_cutter_is_closed_and_within_its_size():
    R = trimesh.transformations.rotation_matrix(0.4, [1, 2, 3])[:3, :3]
    bite = Bite((1.0, 2.0, 3.0), (3.0, 4.0, 5.0), tuple(map(tuple, R)), "rounded_box")
    cutter = cutter_manifold(bite)
    v, f = arrays_from_manifold(cutter)
    assert trimesh.Trimesh(v, f).is_watertight
    local = (v - [1.0, 2.0, 3.0]) @ R
    assert np.all(np.abs(local) <= np.array([1.5, 2.0, 2.5]) + 1e-6)
    assert cutter.volume() > 0.6 * 3 * 4 * 5


def test_a_bite_in_air_raises_bite_miss():
    plate = _box_solid()
    inside = Bite((0.0, 0.0, 0.0), (3.0, 3.0, 4.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1)))
    air = Bite((0.0, 0.0, 10.0), (3.0, 3.0, 4.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1)))
    with pytest.raises(BiteMissError) as info:
        apply_bites(plate, [inside, air])
    assert info.value.source == "bite 2"


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"center_mm": (0.0, float("nan"), 0.0)}, "bite.center_mm"),
        ({"size_mm": (3.0, 0.0, 4.0)}, "bite.size_mm"),
        ({"R_world_from_cutter": ((2, 0, 0), (0, 1, 0), (0, 0, 1))}, "bite.R_world_from_cutter"),
        ({"shape": "cube"}, "bite.shape"),
    ],
)
def test_bad_bites_raise(kwargs, name):
    base = {
        "center_mm": (0.0, 0.0, 0.0),
        "size_mm": (3.0, 3.0, 3.0),
        "R_world_from_cutter": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    }
    base.update(kwargs)
    with pytest.raises(ParameterRangeError) as info:
        Bite(**base)
    assert info.value.source == name


def test_non_manifold_input_raises():
    mesh = trimesh.creation.icosphere(2)
    with pytest.raises(NotManifoldError):
        manifold_from_arrays(mesh.vertices, mesh.faces[:-3])


# ------------------------------------------------------------------ atomic output


def test_atomic_dir_keeps_the_old_folder_on_failure(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_dir(out, marker="old.txt") as tmp:
        (tmp / "new.txt").write_text("new")
        raise RuntimeError("boom")
    assert (out / "old.txt").read_text() == "old"
    assert not (out / "new.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    with atomic_dir(out, marker="old.txt") as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_unwritable_output_raises_output_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError) as info:
        check_output_dir(blocker / "out")
    assert "file" in str(info.value)
    with pytest.raises(OutputError):
        check_output_dir(blocker)  # exists and is not a folder


def test_output_holding_the_working_folder_is_refused(tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.txt").write_text("mine")
    monkeypatch.chdir(work)
    for out in (".", str(tmp_path)):
        with pytest.raises(OutputError, match="holds the current folder"):
            with atomic_dir(out):
                pass
    assert (work / "notes.txt").read_text() == "mine"


def test_a_folder_that_is_not_an_earlier_phantom_is_not_replaced(tmp_path):
    out = tmp_path / "thesis"
    out.mkdir()
    (out / "thesis.tex").write_text("months of work")
    with pytest.raises(OutputError, match="no phantom.json"):
        with atomic_dir(out):
            pass
    assert (out / "thesis.tex").read_text() == "months of work"
    (tmp_path / "empty").mkdir()
    with atomic_dir(tmp_path / "empty") as tmp:  # an empty folder is fine
        (tmp / "phantom.json").write_text("{}")


def test_phantoms_builds_on_chisels_base_only():
    """phantoms may use chisel's base and contracts (atomic writes, volumes, ray casting)
    but never the simulator nor chisel's method, at run time too (tests/test_layers.py
    checks the source)."""
    import subprocess
    import sys

    code = (
        "import sys, phantoms, phantoms.cli, phantoms.tet, phantoms.path, phantoms.generate;"
        "bad = [m for m in sys.modules if m.split('.')[0] == 'sim' or (m.startswith('chisel.')"
        " and m.split('.')[1] not in ('core', 'io'))];"
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_air_pockets_below_a_cubic_millimetre_are_dropped_and_one_part_is_kept_as_is():
    big = m3d.Manifold.sphere(5.0, 48)
    pocket = m3d.Manifold.sphere(0.3, 16).translate((20.0, 0.0, 0.0))  # 0.11 mm^3
    second = m3d.Manifold.sphere(2.0, 32).translate((-20.0, 0.0, 0.0))
    kept = drop_air_pockets(m3d.Manifold.compose([big, pocket, second]))
    assert len(kept.decompose()) == 2
    assert kept.volume() == pytest.approx(big.volume() + second.volume())
    assert drop_air_pockets(big) is big


def test_seed_whose_airway_field_pinched_off_a_pocket_builds():
    """Seed 1233's airway field closed a 0.1 mm^3 pocket: an air void no cell explains,
    and the generator refused the seed (found rendering a training set)."""
    from phantoms.anatomy import build_anatomy

    anatomy = build_anatomy(sample_params(1233, {}), 1233)
    assert anatomy.n_voids == len(anatomy.cells)


def _two_cubes(gap_mm: float) -> m3d.Manifold:
    """Two unit cubes diagonally apart by ``gap_mm`` along x and y: touching along one
    edge (each with its own copies of the edge's vertices) when the gap is 0."""
    a = m3d.Manifold.cube((1.0, 1.0, 1.0))
    b = m3d.Manifold.cube((1.0, 1.0, 1.0)).translate((1.0 + gap_mm, 1.0 + gap_mm, 0.0))
    return m3d.Manifold.compose([a, b])


@pytest.mark.parametrize("gap_mm", [0.0, 0.5])
def test_pinched_finds_an_edge_of_four_faces_as_trimesh_does(gap_mm):
    from phantoms.procedures import _pinched

    v, f = arrays_from_manifold(_two_cubes(gap_mm))
    # independent count: trimesh merges the coincident vertices, then counts edge uses
    merged = trimesh.Trimesh(v, f, process=True)
    counts = np.unique(merged.edges_sorted, axis=0, return_counts=True)[1]
    assert _pinched(_two_cubes(gap_mm)) == bool((counts > 2).any()) == (gap_mm == 0.0)
