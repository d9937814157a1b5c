"""CLI, determinism, bad inputs, tet export and surface repair of the phantom generator.

These use a coarse configuration (1 mm CT, 1 mm surface edges, few bites) to stay fast.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from chisel.io.manifest import MAX_MANIFEST_BYTES
from phantoms import generate
from phantoms.anatomy import arrays_from_manifold, build_anatomy, manifold_from_arrays
from phantoms.bites import Bite, apply_bites, cutter_manifold, find_target
from phantoms.cli import main
from phantoms.errors import (
    BiteMissError,
    NotManifoldError,
    OutputError,
    ParameterRangeError,
    UnknownParameterError,
    UnknownTargetError,
)
from phantoms.params import PhantomConfig, sample_params
from phantoms.surface import load_tissue
from phantoms.tet import read_vtu, repair_surface, tet_volumes

COARSE = [
    "--spacing-mm",
    "1.0",
    "--mesh-edge-mm",
    "1.0",
    "--mucosa-mm",
    "1.5",
    "--procedure",
    "bites",
]


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def coarse_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("coarse") / "seed3"
    assert main(["generate", "--seed", "3", "--bites", "2", "--out", str(out), *COARSE]) == 0
    return out


def test_help_explains_units_and_outputs():
    proc = subprocess.run(
        [sys.executable, "-m", "phantoms", "generate", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    for word in (
        "mm",
        "phantom.json",
        "step_NN_label.nii.gz",
        "HU",
        "--tet",
        "--spacing-mm",
        "--target",
        "--noise-hu",
    ):
        assert word in proc.stdout
    top = subprocess.run(
        [sys.executable, "-m", "phantoms", "--help"], capture_output=True, text=True, check=True
    )
    assert "+x lateral" in top.stdout and "repair" in top.stdout


def test_same_seed_gives_identical_bytes_another_seed_other_anatomy(coarse_dir, tmp_path):
    # a second run in a fresh process (the CLI entry point) must give the same bytes
    again = tmp_path / "again"
    cmd = [
        sys.executable,
        "-m",
        "phantoms",
        "generate",
        "--seed",
        "3",
        "--bites",
        "2",
        "--out",
        str(again),
        *COARSE,
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    first, second = _digest(coarse_dir), _digest(again)
    assert len(first) == 1 + 3 + 3 + 2 + 3 * 2  # manifest, 3 steps + cut faces, 2 cutters, volumes
    assert first == second
    other = tmp_path / "other"
    assert main(["generate", "--seed", "4", "--bites", "2", "--out", str(other), *COARSE]) == 0
    m3, m4 = (json.loads((d / "phantom.json").read_text()) for d in (coarse_dir, other))
    assert m3["params"]["airway_length_mm"] != m4["params"]["airway_length_mm"]
    v3 = trimesh.load(coarse_dir / "meshes/step_00.ply").volume
    v4 = trimesh.load(other / "meshes/step_00.ply").volume
    assert abs(v3 - v4) > 100.0


def test_coarse_phantom_volumes_and_noise(coarse_dir, tmp_path):
    import nibabel as nib

    m = json.loads((coarse_dir / "phantom.json").read_text())
    assert m["ct"]["spacing_mm"] == 1.0
    img = nib.load(coarse_dir / m["steps"][0]["ct_hu"])
    assert np.allclose(np.abs(np.diag(img.affine)[:3]), 1.0)
    clean = np.asarray(img.dataobj)
    noisy_dir = tmp_path / "noisy"
    assert (
        main(
            [
                "generate",
                "--seed",
                "3",
                "--bites",
                "1",
                "--noise-hu",
                "20",
                "--out",
                str(noisy_dir),
                *COARSE,
            ]
        )
        == 0
    )
    noisy = np.asarray(nib.load(noisy_dir / "ct/step_00_hu.nii.gz").dataobj).astype(float)
    diff = noisy - clean
    assert 18.0 < diff.std() < 22.0 and abs(diff.mean()) < 0.5


def test_bulla_target(tmp_path):
    out = tmp_path / "bulla"
    assert (
        main(
            [
                "generate",
                "--seed",
                "1",
                "--bites",
                "2",
                "--target",
                "bulla",
                "--out",
                str(out),
                *COARSE,
            ]
        )
        == 0
    )
    m = json.loads((out / "phantom.json").read_text())
    assert m["target"]["name"] == "bulla"
    cell = next(c for c in m["params"]["ethmoid_cells_mm"] if c["name"] == "ethmoid_bulla")
    # the first bite sits on the bulla's airway-facing wall
    assert np.linalg.norm(
        np.subtract(m["target"]["center_mm"], cell["center_mm"])
    ) == pytest.approx(cell["radius_mm"] + cell["wall_mm"], abs=1e-3)


# ----------------------------------------------------------------- bad input


def _no_output(out: Path) -> None:
    assert not out.exists()
    assert [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}")] == []


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--param", "nose_mm=3"], "unknown shape parameter"),
        (["--param", "airway_length_mm=200"], "expected a value in [62.0, 76.0]"),
        (["--bites", "0"], "n_bites"),
        (["--spacing-mm", "5"], "spacing_mm"),
        (["--target", "frontal_sinus"], "no lamella 'frontal_sinus'"),
    ],
)
def test_cli_bad_arguments_fail_with_one_line_and_no_output(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert main(["generate", "--out", str(out), *argv]) == 1
    err = capsys.readouterr().err
    assert message in err and err.startswith("phantoms generate: error:")
    _no_output(out)


def test_specific_errors_for_bad_configs(tmp_path):
    with pytest.raises(UnknownParameterError):
        generate(PhantomConfig(overrides={"nose_mm": 3.0}), tmp_path / "a")
    with pytest.raises(ParameterRangeError):
        generate(PhantomConfig(overrides={"bulla_radius_mm": 50.0}), tmp_path / "a")
    with pytest.raises(UnknownTargetError):
        generate(PhantomConfig(target="sphenoid"), tmp_path / "a")
    _no_output(tmp_path / "a")


def test_a_plan_that_misses_the_tissue_raises_and_leaves_old_output(coarse_dir, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("earlier result")
    m = json.loads((coarse_dir / "phantom.json").read_text())
    c = np.asarray(m["target"]["center_mm"])
    n = np.asarray(m["target"]["normal"])
    good = m["steps"][1]["bite"]
    in_air = {"center_mm": (c + 2.5 * n).tolist(), "size_mm": [2.0, 2.0, 2.0]}  # inside the airway
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps([good, in_air]))
    with pytest.raises(BiteMissError) as info:
        generate(
            PhantomConfig(
                seed=3, spacing_mm=1.0, mesh_edge_mm=1.0, mucosa_mm=1.5, procedure="bites"
            ),
            out,
            bites=[
                Bite(
                    tuple(good["center_mm"]),
                    tuple(good["size_mm"]),
                    tuple(map(tuple, good["R_world_from_cutter"])),
                    good["shape"],
                ),
                Bite(
                    tuple(in_air["center_mm"]), (2.0, 2.0, 2.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1))
                ),
            ],
        )
    assert info.value.source == "plan bite 1" and "misses the tissue" in str(info.value)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "plan.json"]
    # the same through the CLI's --plan
    assert main(["generate", "--seed", "3", "--plan", str(plan), "--out", str(out), *COARSE]) == 1
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_unwritable_output_folder_fails_before_any_work(tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("x")
    with pytest.raises(OutputError) as info:
        generate(PhantomConfig(), blocker / "out")
    assert "not_a_folder" in str(info.value)
    assert main(["generate", "--out", str(blocker / "out")]) == 1
    assert blocker.read_text() == "x"


def test_unknown_target_name_in_the_bite_planner():
    p = sample_params(3)
    anatomy = build_anatomy(p, 3, 1.0)
    with pytest.raises(UnknownTargetError):
        find_target(anatomy, "agger_nasi")


# ----------------------------------------------------------------- tet and repair


@pytest.mark.slow
def test_tet_export_per_step(tmp_path):
    import pyvista as pv

    from phantoms.ct import SurfaceDistance

    out = tmp_path / "tet"
    argv = [
        "generate",
        "--seed",
        "3",
        "--bites",
        "1",
        "--tet",
        "--tet-edge-mm",
        "4",
        "--out",
        str(out),
        *COARSE,
    ]
    assert main(argv) == 0
    m = json.loads((out / "phantom.json").read_text())
    grids = []
    for step in m["steps"]:
        pts, tets = read_vtu(out / step["tet_mesh"])
        vol = tet_volumes(pts, tets)
        assert np.all(vol > 0)
        assert vol.sum() == pytest.approx(step["volume_mm3"], rel=0.01)
        grids.append(pv.UnstructuredGrid({pv.CellType.TETRA: tets}, pts))
    # the bite is carved out of the tet mesh: points well inside the removed tissue are
    # in the preoperative tets and not in those after the bite
    before = trimesh.load(out / m["steps"][0]["mesh"], process=False)
    cutter = trimesh.load(out / m["steps"][1]["cutter_mesh"], process=False)
    piece = manifold_from_arrays(before.vertices, before.faces) ^ manifold_from_arrays(
        cutter.vertices, cutter.faces
    )
    pv_, pf = arrays_from_manifold(piece)
    lo, hi = cutter.bounds
    q = lo + (hi - lo) * np.random.default_rng(0).random((20_000, 3))
    surf = SurfaceDistance(pv_, pf)
    q = q[surf.inside(q) & (surf.distance(q) > 0.3)]
    assert len(q) > 20
    assert np.all(grids[0].find_containing_cell(q) >= 0)
    assert np.all(grids[1].find_containing_cell(q) < 0)


def test_repair_closes_a_broken_surface_so_it_can_be_cut(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    faces = sphere.faces.copy()
    faces[::7] = faces[::7, ::-1]  # flipped faces
    broken = trimesh.Trimesh(
        sphere.vertices, np.vstack([faces[20:], faces[:3]]), process=False
    )  # holes + duplicates
    src = tmp_path / "broken.stl"
    broken.export(src)
    with pytest.raises(NotManifoldError) as info:
        load_tissue(src)
    assert "repair" in str(info.value)
    tissue = load_tissue(src, repair=True)
    assert tissue.volume() == pytest.approx(sphere.volume, rel=0.03)
    bite = Bite((0.0, 0.0, 10.0), (4.0, 4.0, 4.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1)))
    (res,) = apply_bites(tissue, [bite])
    assert tissue.volume() - res.tissue.volume() == pytest.approx(res.removed_volume_mm3, rel=1e-6)
    # the same bite on the intact sphere removes the same tissue (repair envelope: 0.1 %)
    intact = manifold_from_arrays(sphere.vertices, sphere.faces) ^ cutter_manifold(bite)
    assert res.removed_volume_mm3 == pytest.approx(intact.volume(), rel=0.03)
    # the CLI path
    out = tmp_path / "fixed.ply"
    assert main(["repair", str(src), str(out)]) == 0
    fixed = trimesh.load(out, process=False)
    assert fixed.is_watertight and fixed.is_winding_consistent
    assert fixed.volume == pytest.approx(sphere.volume, rel=0.03)
    v, f = repair_surface(broken.vertices, broken.faces)
    assert trimesh.Trimesh(v, f).is_watertight


def test_repair_of_nothing_raises(tmp_path):
    with pytest.raises(NotManifoldError):
        repair_surface(np.zeros((2, 3)), np.zeros((1, 3), int))
    bad = tmp_path / "bad.ply"
    bad.write_text("not a mesh")
    assert main(["repair", str(bad), str(tmp_path / "o.ply")]) == 1


def test_generated_step_is_accepted_by_load_tissue(coarse_dir):
    tissue = load_tissue(coarse_dir / "meshes/step_02.ply")
    v, _ = arrays_from_manifold(tissue)
    assert len(v) > 1000


def test_a_plan_with_text_for_a_number_is_one_line(tmp_path, capsys):
    plan = tmp_path / "plan.json"
    plan.write_text('[{"center_mm": [1, "a", 3], "size_mm": [2, 2, 2]}]')
    rc = main(
        [
            "generate",
            "--seed",
            "0",
            "--bites",
            "1",
            "--plan",
            str(plan),
            "--out",
            str(tmp_path / "p"),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "bite 0" in err and "lists of numbers" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize(
    "kind, problem",
    [
        ("malformed", "invalid JSON"),
        ("deep", "nested deeper than"),
        ("huge", "a manifest is at most"),
        ("binary", "not a text file"),
        ("missing", "cannot read"),
    ],
)
def test_an_unreadable_plan_file_is_one_line_naming_it(tmp_path, capsys, kind, problem):
    # The plan goes through the project's one bounded JSON reader: a huge file is refused
    # by its size before it is read, a deep one before json recurses into a traceback.
    plan = tmp_path / "plan.json"
    if kind == "malformed":
        plan.write_text('[{"center_mm": [1, 2, 3], "size_mm": [2, 2, 2]')
    elif kind == "deep":
        plan.write_text("[" * 100_000 + "]" * 100_000)
    elif kind == "huge":
        with plan.open("wb") as f:  # sparse: the size alone is over the limit
            f.truncate(MAX_MANIFEST_BYTES + 1)
    elif kind == "binary":
        plan.write_bytes(b"[\xff\xfe]")
    argv = ["generate", "--seed", "0", "--bites", "1", "--plan", str(plan)]
    rc = main([*argv, "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1, err
    assert err.startswith(f"phantoms generate: error: {plan}: ") and problem in err, err
    assert not (tmp_path / "p").exists()
