"""Surgical procedures of the phantom generator: uncinectomy, ethmoidectomy, bites.

Coarse phantoms (1 mm CT, 1 mm surface edges) keep these fast. Checked against
independent references: Open3D ray parity for nesting, trimesh volumes for the removed
tissue, Open3D point-to-surface distances to the written cutter meshes for the cut-face
labels.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from phantoms import generate
from phantoms.anatomy import arrays_from_manifold, build_anatomy
from phantoms.bites import Bite
from phantoms.cli import main
from phantoms.cutters import exposed_cap
from phantoms.errors import (
    BiteMissError,
    ParameterRangeError,
    ProcedureError,
    UnknownProcedureError,
)
from phantoms.params import PARAM_RANGES, PhantomConfig, sample_params
from phantoms.procedures import (
    FIRST_AREA_RANGE,
    FIRST_PAST_TARGET_RANGE,
    FRAGMENT_SHARE_RANGE,
    MAX_PROTRUSION_MM,
    STEP_RANGES,
    Fragment,
    cap_schedule,
    cut_steps,
    plan_procedure,
)

COARSE = ["--spacing-mm", "1.0", "--mesh-edge-mm", "1.0", "--mucosa-mm", "1.5"]
RUNS = {
    "uncinectomy": ["--seed", "0", "--procedure", "uncinectomy"],
    "ethmoidectomy": ["--seed", "1", "--procedure", "ethmoidectomy", "--bites", "5"],
    "bites": ["--seed", "0", "--procedure", "bites", "--bites", "3"],
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("procedures")
    out = {}
    for name, argv in RUNS.items():
        out[name] = root / name
        assert main(["generate", *argv, "--out", str(out[name]), *COARSE]) == 0
    return out


def _manifest(folder: Path) -> dict:
    return json.loads((folder / "phantom.json").read_text())


def _mesh(folder: Path, rel: str) -> trimesh.Trimesh:
    return trimesh.load(folder / rel, process=False)


def _scene(mesh: trimesh.Trimesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    return scene


def _inside(mesh: trimesh.Trimesh, pts: np.ndarray) -> np.ndarray:
    occ = _scene(mesh).compute_occupancy(o3d.core.Tensor(pts.astype(np.float32)), nsamples=3)
    return occ.numpy() > 0.5


@pytest.mark.parametrize("procedure", list(RUNS))
def test_steps_are_nested_and_each_removes_what_its_volume_drops(runs, procedure):
    folder = runs[procedure]
    m = _manifest(folder)
    assert m["procedure"] == procedure and m["config"]["procedure"] == procedure
    steps = m["steps"]
    lo, hi = np.asarray(m["roi_box_mm"])
    rng = np.random.default_rng(1)
    pts = lo + (hi - lo) * rng.random((60_000, 3))
    for prev, cur in zip(steps, steps[1:], strict=False):
        before, after = _mesh(folder, prev["mesh"]), _mesh(folder, cur["mesh"])
        assert after.is_watertight and after.is_volume
        assert cur["removed_volume_mm3"] > 0.5, cur["name"]
        assert before.volume - after.volume == pytest.approx(cur["removed_volume_mm3"], rel=0.01)
        # nested: no point of this step's tissue lies outside the previous step's tissue
        inside_after = _inside(after, pts)
        inside_before = _inside(before, pts)
        assert inside_after.sum() > 100
        assert (inside_after & ~inside_before).mean() < 2e-4, cur["name"]
        # and some tissue was removed inside the change box
        assert (inside_before & ~inside_after).sum() > 0


@pytest.mark.parametrize("procedure", list(RUNS))
def test_cut_face_labels_cover_exactly_the_faces_on_the_cutters(runs, procedure):
    folder = runs[procedure]
    m = _manifest(folder)
    cutters = []
    for k, st in enumerate(m["steps"]):
        mesh = _mesh(folder, st["mesh"])
        labels = np.load(folder / st["cut_faces"], allow_pickle=False)
        assert labels.dtype == np.uint8 and labels.shape == (len(mesh.faces),)
        assert int(labels.sum()) == st["cut_face_count"]
        if k == 0:
            assert labels.sum() == 0
            continue
        cutters.append(_mesh(folder, st["cutter_mesh"]))
        union = trimesh.util.concatenate(cutters)
        centroids = mesh.triangles_center.astype(np.float32)
        dist = _scene(union).compute_distance(o3d.core.Tensor(centroids)).numpy()
        cut = labels.astype(bool)
        assert cut.sum() > 10
        assert dist[cut].max() < 1e-2, (st["name"], float(dist[cut].max()))
        # faces not from a cutter do not lie on any cutter's surface
        assert (dist[~cut] < 1e-4).mean() < 1e-3, st["name"]


def test_same_seed_gives_the_same_bytes(runs, tmp_path):
    again = tmp_path / "again"
    assert main(["generate", *RUNS["uncinectomy"], "--out", str(again), *COARSE]) == 0

    def digest(folder: Path) -> dict[str, str]:
        return {
            str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*"))
            if p.is_file()
        }

    assert digest(again) == digest(runs["uncinectomy"])


def test_no_ct_writes_the_same_meshes_and_no_volumes(runs, tmp_path):
    out = tmp_path / "no_ct"
    assert main(["generate", *RUNS["uncinectomy"], "--out", str(out), *COARSE, "--no-ct"]) == 0
    full = runs["uncinectomy"]
    m, m_full = _manifest(out), _manifest(full)
    assert m["ct"] is None and not (out / "ct").exists()
    assert all("ct_label" not in s and "ct_hu" not in s for s in m["steps"])
    assert all("ct_label" in s for s in m_full["steps"])
    meshes = sorted(p.relative_to(full) for p in (full / "meshes").iterdir())
    assert sorted(p.relative_to(out) for p in (out / "meshes").iterdir()) == meshes
    for rel in meshes:
        assert (out / rel).read_bytes() == (full / rel).read_bytes(), rel
    skip = {"ct", "steps", "config"}
    assert {k: v for k, v in m.items() if k not in skip} == {
        k: v for k, v in m_full.items() if k not in skip
    }


def test_uncinectomy_removes_the_uncinate_from_below_upward(runs):
    m = _manifest(runs["uncinectomy"])
    steps = m["steps"][1:]
    assert len(steps) == 5 and all(s["structure"] == "uncinate process" for s in steps)
    frags = [s["fragment"] for s in steps]
    assert all(f["kind"] == "cap" and f["structure"] == "infundibulum" for f in frags)
    levels = [f["level_mm"] for f in frags]
    assert levels == sorted(levels)
    for f in frags:
        assert 1 <= f["n_bites"] <= 3 and 0.35 <= f["ragged_mm"] <= 0.7
    # the opening reaches the infundibulum: far more than a bite's worth is gone
    assert sum(s["removed_volume_mm3"] for s in steps) > 40.0


def test_ethmoidectomy_goes_uncinate_then_bulla(runs):
    m = _manifest(runs["ethmoidectomy"])
    order = [s["fragment"]["structure"] for s in m["steps"][1:]]
    assert order[:2] == ["infundibulum", "infundibulum"]
    assert set(order[2:]) == {"ethmoid_bulla"}
    kinds = [s["fragment"]["kind"] for s in m["steps"][1:]]
    assert kinds[2] == "cap" and kinds.index("cap", 2) == 2


# ------------------------------------------------------------ impossible / bad input


def _no_output(out: Path) -> None:
    assert not out.exists()
    assert [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}")] == []


@pytest.fixture(scope="module")
def anatomy():
    return build_anatomy(sample_params(1), 1, 1.0)


def test_no_bulla_wall_in_reach_names_procedure_and_step(anatomy):
    # move the bulla deep into the block: its wall no longer faces the airway
    cells = tuple(
        dataclasses.replace(c, center_mm=tuple(np.add(c.center_mm, (25.0, 0.0, 0.0))))
        if c.name == "ethmoid_bulla"
        else c
        for c in anatomy.cells
    )
    hidden = dataclasses.replace(anatomy, cells=cells)
    with pytest.raises(ProcedureError) as info:
        plan_procedure(hidden, "ethmoidectomy", 5, seed=1)
    assert info.value.source == "ethmoidectomy step 3"
    assert "no ethmoid bulla wall in reach" in str(info.value)


def test_a_step_into_the_block_walls_is_refused(anatomy):
    lo = np.asarray(anatomy.block_min_mm)
    hi = np.asarray(anatomy.block_max_mm)
    corner = np.array([hi[0] - 1.0, 0.5 * (lo[1] + hi[1]), hi[2] - 1.0])  # solid tissue
    bite = Bite(tuple(corner), (4.0, 4.0, 4.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1)))
    with pytest.raises(ProcedureError) as info:
        cut_steps(anatomy, [Fragment("bites", "uncinate", {}, (bite,))], "uncinectomy")
    assert info.value.source == "uncinectomy step 1" and "outer walls" in str(info.value)


def test_a_plan_cutting_past_the_uncinate_is_refused_and_writes_nothing(runs, tmp_path, capsys):
    m = _manifest(runs["uncinectomy"])
    c = np.asarray(m["target"]["center_mm"])
    n = np.asarray(m["target"]["normal"])
    # a broad cutter through the uncinate, 16 mm across: beyond the rim it cuts the wall
    e1 = np.cross(n, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    R = np.stack([e1, np.cross(n, e1), n], axis=1)
    deep = {
        "center_mm": c.tolist(),
        "size_mm": [16.0, 16.0, 3.0],
        "R_world_from_cutter": R.tolist(),
    }
    ok = m["steps"][1]["fragment"]
    assert ok["kind"] == "cap"
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps([deep, deep, deep]))
    out = tmp_path / "out"
    rc = main(["generate", "--seed", "0", "--plan", str(plan), "--out", str(out), *COARSE])
    err = capsys.readouterr().err
    assert rc == 1 and f"{plan} bite 0" in err and "beyond the" in err, err
    assert err.count("phantoms generate: error:") == 1
    _no_output(out)


def test_a_plan_fragment_in_air_names_the_entry(runs, tmp_path):
    m = _manifest(runs["bites"])
    c = np.asarray(m["target"]["center_mm"])
    n = np.asarray(m["target"]["normal"])
    good = m["steps"][1]["bite"]
    in_air = {"center_mm": (c + 2.5 * n).tolist(), "size_mm": [2.0, 2.0, 2.0]}
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps([good, {"bites": [in_air, in_air]}]))
    out = tmp_path / "out"
    argv = ["generate", "--seed", "0", "--procedure", "bites", "--plan", str(plan)]
    assert main([*argv, "--out", str(out), *COARSE]) == 1
    _no_output(out)
    with pytest.raises(BiteMissError) as info:
        generate(
            PhantomConfig(
                seed=0, procedure="bites", spacing_mm=1.0, mesh_edge_mm=1.0, mucosa_mm=1.5
            ),
            out,
            bites=[
                Bite(tuple(in_air["center_mm"]), (2.0, 2.0, 2.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1)))
            ],
            plan_source=str(plan) + " bite",
        )
    assert info.value.source == f"{plan} bite 0"
    _no_output(out)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--procedure", "sphenoidotomy"], "unknown procedure 'sphenoidotomy'"),
        (["--procedure", "uncinectomy", "--bites", "9"], "procedure uncinectomy takes 1-8 steps"),
        (["--procedure", "ethmoidectomy", "--bites", "2"], "procedure ethmoidectomy takes 4-12"),
        (["--procedure", "bites", "--bites", "21"], "procedure bites takes 1-20"),
    ],
)
def test_bad_procedure_options_fail_with_one_line_and_no_output(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert main(["generate", "--out", str(out), *argv]) == 1
    err = capsys.readouterr().err
    assert (
        message in err
        and err.startswith("phantoms generate: error:")
        and "--bites" in err
        or ("procedure" in err)
    )
    assert message in err
    _no_output(out)


def test_config_checks_procedure_and_step_count():
    with pytest.raises(UnknownProcedureError):
        PhantomConfig(procedure="septoplasty")
    lo, hi = STEP_RANGES["uncinectomy"]
    with pytest.raises(ParameterRangeError):
        PhantomConfig(procedure="uncinectomy", n_bites=hi + 1)
    assert PhantomConfig().procedure == "uncinectomy" and PhantomConfig().n_bites == 5


# ------------------------------------------------------------- the uncinectomy's schedule


@pytest.mark.parametrize("n", [1, 2, 5, 8])
@pytest.mark.parametrize("focus", [None, -4.0, 0.5, 4.5])
def test_cap_schedule_takes_bounded_nested_shares(n, focus):
    # a cap of 1001 equal faces evenly spread over heights -5..5 mm: the share below a
    # height h is (h + 5) / 10
    heights = np.linspace(-5.0, 5.0, 1001)
    areas = np.ones_like(heights)
    for seed in range(20):
        cum = cap_schedule(heights, areas, n, np.random.default_rng(seed), focus)
        assert cum.shape == (n,) and cum[-1] == pytest.approx(1.0)
        if n == 1:
            continue
        assert np.all(np.diff(cum) > 0)  # nested: every step takes more of the cap
        lo, hi = FIRST_AREA_RANGE
        assert lo - 1e-12 <= cum[0] <= hi + 1e-12
        if focus is not None:
            below = (focus + 5.0) / 10.0
            want = np.clip(below + np.array(FIRST_PAST_TARGET_RANGE), lo, hi)
            assert want[0] - 2e-3 <= cum[0] <= want[1] + 2e-3
        later = np.diff(cum)
        s_lo, s_hi = FRAGMENT_SHARE_RANGE
        assert later.max() / later.min() <= s_hi / s_lo + 1e-9
        # no later step takes more than its bounded share of what the first left
        assert later.max() <= (1.0 - cum[0]) * s_hi / (s_hi + (n - 2) * s_lo) + 1e-9


def test_uncinectomy_fragments_follow_the_area_schedule(runs):
    m = _manifest(runs["uncinectomy"])
    frags = [s["fragment"] for s in m["steps"][1:]]
    shares = [f["area_fraction"] for f in frags]
    assert shares[-1] == 1.0 and np.all(np.diff(shares) > 0)
    assert FIRST_AREA_RANGE[0] <= shares[0] <= FIRST_AREA_RANGE[1]
    # the first fragment's edge reaches past the target (unless its share is capped)
    infund = next(c for c in m["params"]["ethmoid_cells_mm"] if c["name"] == "infundibulum")
    R = np.asarray(frags[0]["R_world_from_local"])
    target_height = (np.subtract(m["target"]["center_mm"], infund["center_mm"])) @ R[:, 2]
    assert frags[0]["level_mm"] > target_height or shares[0] == FIRST_AREA_RANGE[1]


def test_uncinate_is_the_wall_proud_of_the_lateral_wall_not_a_recess():
    # seed 9: the lateral wall recedes around the infundibulum, exposing its sphere far
    # below the uncinate's largest protrusion (4 mm); the cut must not follow the recess
    an = build_anatomy(sample_params(9), 9, 1.0)
    cell = an.cell("infundibulum")
    ro = cell.outer_radius_mm
    assert MAX_PROTRUSION_MM["infundibulum"] == PARAM_RANGES["uncinate_bulge_mm"][1]
    bound = ro - PARAM_RANGES["uncinate_bulge_mm"][1]
    _, frags, cuts = plan_procedure(an, "uncinectomy", 5, seed=9)
    a = np.asarray(frags[0].params["R_world_from_local"])[:, 1]
    exposed_depth = exposed_cap(an.tissue, cell) @ a * ro
    assert np.quantile(exposed_depth, 0.08) < bound - 1.0  # the recess is there
    for frag, cut in zip(frags, cuts, strict=True):
        v = np.asarray(cut.removed.to_mesh64().vert_properties)[:, :3] - cell.center_mm
        # the cut's sides are cones through the centre: judge the removed tissue by its
        # radial projection onto the outer sphere, where the plan drew the bound
        depth = v @ a * ro / np.linalg.norm(v, axis=1)
        assert depth.min() >= bound + 0.4 - 0.02, frag.params["level_mm"]


def test_uncinectomy_cuts_cross_the_wall_square_to_it():
    # forceps cut a lamella across its thickness; an oblique cut left wedge tips thinner
    # than a CT voxel. Every cut face within the infundibulum's wall must be square to
    # the wall (its normal tangent to the spheres), which leaves the wall its full thickness
    an = build_anatomy(sample_params(4), 4, 1.0)
    cell = an.cell("infundibulum")
    _, _, cuts = plan_procedure(an, "uncinectomy", 5, seed=4)
    for cut in cuts:
        v, f = arrays_from_manifold(cut.tissue)
        tri = v[f[cut.cut_faces]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        rel = tri.mean(axis=1) - cell.center_mm
        r = np.linalg.norm(rel, axis=1)
        in_wall = (r > cell.radius_mm + 0.05) & (r < cell.outer_radius_mm - 0.05)
        assert in_wall.sum() > 50
        sin_tilt = np.abs(np.einsum("ij,ij->i", n[in_wall], rel[in_wall] / r[in_wall, None]))
        assert np.quantile(sin_tilt, 0.95) < 0.1  # within ~6 deg of square
