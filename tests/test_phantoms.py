"""End-to-end tests of ``python -m phantoms generate`` on the default phantom.

One phantom of the fine-change regime (seed 0, ``--procedure bites``: 5 bites on the
uncinate, 0.5 mm CT) is generated per test
session worker and checked against independent references: trimesh for watertightness and
volumes, trimesh ray tests for voxel-in-mesh, manifold3d / Monte Carlo for the removed
volumes, scikit-image marching cubes for the CT surface.
"""

from __future__ import annotations

import json
from pathlib import Path

import manifold3d as m3d
import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes

from chisel.io.ct import read_ct_volume
from phantoms.anatomy import manifold_from_arrays
from phantoms.cli import main
from phantoms.ct import SurfaceDistance
from phantoms.params import PARAM_RANGES


@pytest.fixture(scope="module")
def default_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("phantom") / "seed0"
    args = ["generate", "--seed", "0", "--procedure", "bites", "--bites", "5", "--out", str(out)]
    assert main(args) == 0
    return out


@pytest.fixture(scope="module")
def manifest(default_dir) -> dict:
    return json.loads((default_dir / "phantom.json").read_text())


def _winding_inside(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """Generalised winding number > 1/2 (van Oosterom & Strackee solid angles): an
    independent, exact inside test for a closed mesh. points : (N, 3) mm -> (N,) bool."""
    total = np.zeros(len(points))
    tri = mesh.vertices[mesh.faces]
    for start in range(0, len(tri), 20_000):
        t = tri[start : start + 20_000]
        a, b, c = (t[None, :, i, :] - points[:, None, :] for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (
            la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la
        )
        den += np.einsum("pfi,pfi->pf", c, a) * lb
        total += 2.0 * np.arctan2(det, den).sum(axis=1)
    return total / (4.0 * np.pi) > 0.5


def _mesh(folder: Path, rel: str) -> trimesh.Trimesh:
    return trimesh.load(folder / rel, process=False)


def _volume(folder: Path, rel: str) -> np.ndarray:
    vol = read_ct_volume(folder / rel)  # the NIfTI's RAS affine, back in the LPS world
    return vol.data, vol.T_world_from_voxel


def test_manifest_follows_the_contract(default_dir, manifest):
    m = manifest
    assert m["format"] == "endoscopic-chisel/phantom" and m["version"] == 1 and m["seed"] == 0
    assert (
        "+x lateral" in m["world_frame"]
        and "+y posterior" in m["world_frame"]
        and "+z superior" in m["world_frame"]
    )
    assert set(PARAM_RANGES) <= set(m["params"])
    assert [s["step"] for s in m["steps"]] == list(range(6))
    assert [s["name"] for s in m["steps"]] == ["preop"] + [f"bite_{k}" for k in range(1, 6)]
    for s in m["steps"]:
        for key in ("mesh", "ct_label", "ct_hu") + (("cutter_mesh",) if s["step"] else ()):
            assert not Path(s[key]).is_absolute() and (default_dir / s[key]).is_file(), s[key]
        assert "tet_mesh" not in s  # off by default
    assert m["steps"][0]["removed_volume_mm3"] == 0.0
    assert np.asarray(m["roi_box_mm"]).shape == (2, 3)
    assert m["target"]["name"] == "uncinate"
    assert np.linalg.norm(m["target"]["normal"]) == pytest.approx(1.0, abs=1e-5)
    assert m["ct"]["spacing_mm"] == 0.5
    assert m["ct"]["labels"] == {"air": 0, "soft_tissue": 1, "bone": 2}
    assert m["ct"]["hu"] == {"air": -1000, "soft_tissue": 40, "bone": 700}
    # no temporary siblings left behind
    assert sorted(p.name for p in default_dir.parent.iterdir()) == ["seed0"]


def test_every_step_is_a_watertight_volume_that_shrinks(default_dir, manifest):
    volumes = []
    for s in manifest["steps"]:
        mesh = _mesh(default_dir, s["mesh"])
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume, s["mesh"]
        assert mesh.volume == pytest.approx(s["volume_mm3"], rel=1e-6)
        assert len(mesh.faces) < 400_000
        volumes.append(mesh.volume)
    assert all(b < a for a, b in zip(volumes, volumes[1:], strict=False))


def test_removed_volume_is_cutter_intersection(default_dir, manifest):
    steps = manifest["steps"]
    rng = np.random.default_rng(0)
    for prev, cur in zip(steps, steps[1:], strict=False):
        before = _mesh(default_dir, prev["mesh"])
        after = _mesh(default_dir, cur["mesh"])
        cutter = _mesh(default_dir, cur["cutter_mesh"])
        assert cutter.is_watertight
        removed = cur["removed_volume_mm3"]
        assert removed > 0
        assert before.volume - after.volume == pytest.approx(removed, rel=0.01)
        inter = manifold_from_arrays(before.vertices, before.faces) ^ manifold_from_arrays(
            cutter.vertices, cutter.faces
        )
        assert inter.volume() == pytest.approx(removed, rel=0.01)
        # independent Monte Carlo estimate (Open3D ray parity, not manifold3d)
        lo, hi = cutter.bounds
        pts = lo + (hi - lo) * rng.random((200_000, 3))
        in_cutter = SurfaceDistance(cutter.vertices, cutter.faces).inside(pts)
        in_tissue = SurfaceDistance(before.vertices, before.faces).inside(pts)
        mc = np.prod(hi - lo) * np.mean(in_cutter & in_tissue)
        assert mc == pytest.approx(removed, rel=0.05)
        # the bite widens one opening: it touches the previous cutter's hole
        assert (
            np.linalg.norm(np.subtract(cur["bite"]["center_mm"], steps[1]["bite"]["center_mm"]))
            < 15.0
        )


def test_ct_label_agrees_with_the_mesh(default_dir, manifest):
    rng = np.random.default_rng(1)
    for s in (manifest["steps"][0], manifest["steps"][-1]):
        label, A = _volume(default_dir, s["ct_label"])
        assert np.allclose(A, manifest["ct"]["T_world_from_voxel"])
        mesh = _mesh(default_dir, s["mesh"])
        idx = np.stack([rng.integers(0, n, 150) for n in label.shape], axis=1)
        pts = idx @ A[:3, :3].T + A[:3, 3]
        # away from the boundary: at least one voxel from the surface
        dist = SurfaceDistance(mesh.vertices, mesh.faces).distance(pts)
        keep = dist > manifest["ct"]["spacing_mm"]
        inside = _winding_inside(pts[keep], mesh)  # independent of Open3D / manifold3d
        lab = label[tuple(idx[keep].T)]
        assert np.array_equal(lab > 0, inside)
        assert keep.sum() > 100 and inside.any() and (~inside).any()
        # bone only deeper than the mucosa layer
        assert np.all(dist[keep][lab == 2] >= manifest["ct"]["mucosa_mm"] - 1e-4)


def test_hu_iso_surface_reconstructs_the_mesh(default_dir, manifest):
    s = manifest["steps"][-1]
    hu, A = _volume(default_dir, s["ct_hu"])
    label, _ = _volume(default_dir, s["ct_label"])
    assert hu.dtype == np.int16 and label.dtype == np.uint8
    # int16 rounding may put a voxel right at the iso-level on either side
    assert np.all(hu[label == 0] <= -480) and np.all(hu[label > 0] >= -480)
    assert hu.min() == -1000 and hu.max() == 700
    verts, _, _, _ = marching_cubes(hu.astype(np.float32), level=manifest["ct"]["iso_hu"])
    world = verts @ A[:3, :3].T + A[:3, 3]
    mesh = _mesh(default_dir, s["mesh"])
    d = SurfaceDistance(mesh.vertices, mesh.faces).distance(world)
    spacing = manifest["ct"]["spacing_mm"]
    assert np.median(d) < 0.01 * spacing
    assert np.percentile(d, 99) < 0.1 * spacing
    assert d.max() < 0.5 * spacing


def test_roi_box_contains_every_removed_voxel(default_dir, manifest):
    before, A = _volume(default_dir, manifest["steps"][0]["ct_label"])
    after, _ = _volume(default_dir, manifest["steps"][-1]["ct_label"])
    removed = (before > 0) & (after == 0)
    assert removed.sum() > 50
    pts = np.argwhere(before != after) @ A[:3, :3].T + A[:3, 3]
    lo, hi = np.asarray(manifest["roi_box_mm"])
    assert np.all(pts >= lo) and np.all(pts <= hi)
    # the removed tissue's exact bounds plus the 3 mm margin lie inside the box
    removed_pts = np.argwhere(removed) @ A[:3, :3].T + A[:3, 3]
    assert np.all(removed_pts.min(axis=0) - lo >= 3.0 - 1e-6)
    assert np.all(hi - removed_pts.max(axis=0) >= 3.0 - 1e-6)
    block_lo, block_hi = np.asarray(manifest["params"]["block_mm"])
    assert np.all(lo >= block_lo - 3.0) and np.all(hi <= block_hi + 3.0)


def test_roi_box_holds_the_surface_the_removal_reveals(default_dir, manifest):
    """Rays from the end of the airway path through the removed voxels: where the last
    step's surface lies 1-25 mm behind the preoperative one, it lies in the box."""
    before, A = _volume(default_dir, manifest["steps"][0]["ct_label"])
    after, _ = _volume(default_dir, manifest["steps"][-1]["ct_label"])
    removed_pts = np.argwhere((before > 0) & (after == 0)) @ A[:3, :3].T + A[:3, 3]
    eye = np.asarray(manifest["airway_path_mm"][-1])
    dirs = removed_pts - eye
    dist = np.linalg.norm(dirs, axis=1)
    dirs /= dist[:, None]
    meshes = [_mesh(default_dir, manifest["steps"][k]["mesh"]) for k in (0, -1)]
    pre, post = (
        SurfaceDistance(m.vertices, m.faces).first_hit(np.repeat(eye[None], len(dirs), 0), dirs)
        for m in meshes
    )
    revealed = np.isfinite(post) & (post > dist) & (post - pre > 1.0) & (post - pre <= 25.0)
    assert revealed.sum() > 10  # the removal opens a view behind the lamella
    hits = eye + dirs[revealed] * post[revealed, None]
    lo, hi = np.asarray(manifest["roi_box_mm"])
    # the box is built from other sample points of the removed tissue: 1 mm of its 3 mm
    # margin covers the difference
    assert np.all(hits >= lo + 2.0) and np.all(hits <= hi - 2.0)
    assert np.any(hits.max(axis=0) - removed_pts.max(axis=0) > 5.0)  # it reaches deeper


def test_bites_open_a_cavity_behind_the_lamella(default_dir, manifest):
    c = np.asarray(manifest["target"]["center_mm"])
    n = np.asarray(manifest["target"]["normal"])
    origin = (c + 1.0 * n)[None]
    pre = _mesh(default_dir, manifest["steps"][0]["mesh"])
    post = _mesh(default_dir, manifest["steps"][-1]["mesh"])
    d_pre = SurfaceDistance(pre.vertices, pre.faces).first_hit(origin, -n[None])[0]
    d_post = SurfaceDistance(post.vertices, post.faces).first_hit(origin, -n[None])[0]
    assert d_pre == pytest.approx(1.0, abs=0.05)  # the lamella surface faces the airway
    assert 10.0 <= d_post - 1.0 <= 40.0  # depth behind the removed tissue jumps


def test_anatomy_sizes_are_in_the_documented_ranges(default_dir, manifest):
    from scipy import ndimage

    label, A = _volume(default_dir, manifest["steps"][0]["ct_label"])
    spacing = manifest["ct"]["spacing_mm"]
    air, n_comp = ndimage.label(label == 0)
    nostril = np.asarray(manifest["params"]["nostril_mm"]) + [0.0, 1.0, 0.0]
    ijk = np.rint(np.linalg.solve(A, [*nostril, 1.0])[:3]).astype(int)
    airway = air == air[tuple(ijk)]
    pts = np.argwhere(airway) @ A[:3, :3].T + A[:3, 3]
    block_lo, block_hi = np.asarray(manifest["params"]["block_mm"])
    inside_block = np.all((pts > block_lo) & (pts < block_hi), axis=1)
    pts = pts[inside_block]
    length = pts[:, 1].max() - pts[:, 1].min()
    height = pts[:, 2].max() - pts[:, 2].min()
    assert 50.0 <= length <= 80.0
    assert 30.0 <= height <= 45.0
    near_floor = pts[np.abs(pts[:, 2] - 6.0) < spacing]
    width = near_floor[:, 0].max() - near_floor[:, 0].min()
    assert 10.0 <= width <= 16.0
    # closed air cells: one per cell plus nothing else (the maxillary sinus joins the
    # infundibulum); the outside air and airway are one component
    cells = manifest["params"]["ethmoid_cells_mm"]
    assert n_comp == 1 + len(cells)
    # lamella thicknesses within 0.5-2 mm, measured by ray casting through each wall
    mesh = _mesh(default_dir, manifest["steps"][0]["mesh"])
    surf = SurfaceDistance(mesh.vertices, mesh.faces)
    for cell in cells[:3]:  # uncinate (infundibulum wall), bulla, basal lamella
        c = np.asarray(cell["center_mm"])
        outer = cell["radius_mm"] + cell["wall_mm"]
        on_wall = np.abs(np.linalg.norm(mesh.vertices - c, axis=1) - outer) < 1e-3
        assert on_wall.sum() > 20, f"{cell['name']} wall is not exposed to the airway"
        # the wall vertex nearest the middle of the exposed patch (away from its rim,
        # where the wall runs into the lateral wall's tissue)
        wall = mesh.vertices[on_wall]
        mid = (wall - c).mean(axis=0)
        p = wall[np.argmax((wall - c) @ (mid / np.linalg.norm(mid)))]
        u = (c - p) / np.linalg.norm(c - p)
        assert surf.first_hit((p - 0.3 * u)[None], u[None])[0] == pytest.approx(0.3, abs=0.02)
        thickness = surf.first_hit((p + 0.01 * u)[None], u[None])[0] + 0.01
        assert thickness == pytest.approx(cell["wall_mm"], abs=0.02), cell["name"]
        assert 0.5 <= thickness <= 2.0
        # behind the lamella, the air cell: the next wall is a cell diameter away
        behind = surf.first_hit((p + (thickness + 0.01) * u)[None], u[None])[0]
        assert behind > cell["radius_mm"]
    # maxillary sinus of realistic volume (10-20 mL)
    assert 10_000 <= manifest["params"]["maxillary_sinus"]["volume_mm3"] <= 20_000
    # turbinates: the coronal section through the middle of the cavity shows several
    # tissue islands/shelves between septum and lateral wall (septum, inferior and middle
    # turbinate): count tissue runs along x at the inferior turbinate's height
    y_mid = 0.5 * (pts[:, 1].min() + pts[:, 1].max())
    row_pts = np.stack(
        [
            np.arange(-3.0, 20.0, 0.1),
            np.full(230, y_mid),
            np.full(230, manifest["params"]["it_center_z_mm"]),
        ],
        1,
    )
    inside = surf.inside(row_pts)
    runs = np.count_nonzero(np.diff(inside.astype(int)) == 1) + int(inside[0])
    assert runs >= 2  # septum, then the turbinate, then the lateral wall


def test_airway_path_keeps_clearance_and_reaches_the_view(default_dir, manifest):
    path = np.asarray(manifest["airway_path_mm"])
    assert path.ndim == 2 and path.shape[1] == 3 and len(path) > 10
    mesh = _mesh(default_dir, manifest["steps"][0]["mesh"])
    surf = SurfaceDistance(mesh.vertices, mesh.faces)
    dense = np.concatenate(
        [np.linspace(a, b, 5, endpoint=False) for a, b in zip(path[:-1], path[1:], strict=False)]
    )
    assert not surf.inside(dense).any()
    assert surf.distance(dense).min() >= 3.0 - 1e-4
    # independent check of a few points with trimesh's exact closest point
    closest, dist, _ = trimesh.proximity.closest_point(mesh, path[:: max(1, len(path) // 8)])
    assert dist.min() >= 3.0 - 1e-4
    # starts at the nostril, ends 8-15 mm in front of the target, with the target in sight
    assert path[0][1] == pytest.approx(0.0, abs=1.0)
    c = np.asarray(manifest["target"]["center_mm"])
    n = np.asarray(manifest["target"]["normal"])
    view = path[-1] - c
    assert 8.0 - 1e-4 <= np.linalg.norm(view) <= 15.0 + 1e-4
    assert view @ n > 0
    t = surf.first_hit(path[-1][None], (-view / np.linalg.norm(view))[None])[0]
    assert t == pytest.approx(np.linalg.norm(view), abs=0.35)
    # smooth: no kinks sharper than 45 degrees between 1 mm segments
    seg = np.diff(path, axis=0)
    seg /= np.linalg.norm(seg, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip((seg[1:] * seg[:-1]).sum(1), -1, 1))).max() < 45.0


def test_nifti_is_gzip_deterministic(default_dir, manifest):
    for s in manifest["steps"]:
        for key in ("ct_label", "ct_hu"):
            raw = (default_dir / s[key]).read_bytes()
            assert raw[:2] == b"\x1f\x8b" and raw[4:8] == b"\x00\x00\x00\x00"


def test_manifold3d_reads_every_step(default_dir, manifest):
    for s in manifest["steps"]:
        mesh = _mesh(default_dir, s["mesh"])
        man = m3d.Manifold(
            m3d.Mesh64(
                vert_properties=np.ascontiguousarray(mesh.vertices),
                tri_verts=np.ascontiguousarray(mesh.faces, dtype=np.uint64),
            )
        )
        assert man.status() == m3d.Error.NoError
