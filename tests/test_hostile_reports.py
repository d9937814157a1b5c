"""Hostile inputs to the evaluation's and the report's readers, and to the simulator's
cut-face labels: each is one ``InvalidInputError`` naming the file (and key), never a raw
traceback, and nothing is written (docs/bad-inputs.md).

Covered: ``chisel evaluate --change-masks`` (:func:`chisel.eval.step.load_change_masks`,
:func:`~chisel.eval.step.load_mask_poses`), ``chisel report --panels / --ct-slices /
--sweep`` (:func:`~chisel.eval.panels.read_panels`,
:func:`~chisel.eval.ct_slices.read_ct_slices`, :func:`~chisel.eval.tables.read_sweep_csv`)
and ``python -m sim render`` with ``phantom.json``'s ``steps[k].cut_faces``
(:func:`sim.pipeline.load_cut_faces`). Each case has a positive control beside it, so the
tests can fail.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from chisel.cli import main as cli_main
from chisel.core.errors import FormatVersionError, InvalidInputError, OutsideManifestError
from chisel.core.geometry import Camera
from chisel.eval.ct_slices import CtSlice, read_ct_slices, write_ct_slices
from chisel.eval.panels import StepPanel, read_panels, write_panels
from chisel.eval.step import load_change_masks, load_mask_poses
from chisel.eval.tables import (
    METRIC_KEYS,
    SWEEP_COLUMNS,
    assemble_table,
    read_sweep_csv,
    tabulate_sweep,
    write_sweep_csv,
    write_table,
)
from chisel.io.sequence import Frame, write_sequence
from sim.cli import main as sim_main
from sim.errors import PhantomError
from sim.phantom import load_mesh, load_phantom
from sim.pipeline import load_cut_faces
from sim.synthetic import write_toy_phantom

CAM = Camera.from_fov(48, 36, 60)
N_FRAMES = 2
NOT_A_ZIP = b"PK\x03\x04" + b"\x00junk, not a zip archive" * 4


def _one_line_naming(err: str, *names: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for name in names:
        assert name in lines[0], (name, lines[0])


# ----------------------------------------------------- chisel evaluate --change-masks


def _plane(z_mm: float) -> trimesh.Trimesh:
    v = np.array([[-60, -60, z_mm], [60, -60, z_mm], [60, 60, z_mm], [-60, 60, z_mm]], float)
    return trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("eval_scene")
    paths = {"gt": root / "gt.ply", "updated": root / "updated.ply", "start": root / "start.ply"}
    _plane(20.0).export(paths["gt"])
    _plane(20.5).export(paths["updated"])
    _plane(18.0).export(paths["start"])  # 2 mm of tissue gone in front of the GT: all changed
    frames = [Frame(index=i, T_world_from_cam=T) for i, T in enumerate(_poses())]
    paths["seq"] = write_sequence(root / "seq", CAM, frames)
    return paths


def _masks() -> np.ndarray:
    m = np.zeros((N_FRAMES, *CAM.shape), bool)
    m[:, :, : CAM.width // 2] = True
    return m


def _poses() -> np.ndarray:
    """Cameras 10 mm apart looking down +z (tracker units are checked to be mm)."""
    poses = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    poses[:, 0, 3] = np.linspace(-5.0, 5.0, N_FRAMES)
    return poses


# name, what the file holds (None: the bytes of a file that starts like a zip but is not
# one), which reader refuses it, and the message (after the file's name).
MASK_CASES: list[tuple[str, dict[str, np.ndarray] | None, str, str]] = [
    (
        "object_masks",
        {"masks": np.array([np.zeros(CAM.shape, bool), None], dtype=object)},
        "masks",
        r" member masks\.npy: this \.npy holds Python objects",
    ),
    ("not_a_zip", None, "masks", r": cannot read change masks \(\.npz without pickle\)"),
    (
        "frame_index_strings",
        {"masks": _masks(), "frame_index": np.array(["0", "1"])},
        "masks",
        r": frame_index must be 2 integer-typed frame indices, shape \(2,\), got <U1",
    ),
    (
        "frame_index_floats",
        {"masks": _masks(), "frame_index": np.array([0.5, 1.7])},
        "masks",
        r": frame_index must be 2 integer-typed frame indices, shape \(2,\), got float64",
    ),
    (
        "frame_index_negative",
        {"masks": _masks(), "frame_index": np.array([-1, 0])},
        "masks",
        r": frame_index must hold non-negative indices in 0\.\.1 .*got -1\.\.0",
    ),
    (
        "frame_index_repeated",
        {"masks": _masks(), "frame_index": np.array([1, 1])},
        "masks",
        r": frame_index names frame 1 more than once",
    ),
    (
        "pose_strings",
        {"masks": _masks(), "T_world_from_cam": np.full((N_FRAMES, 4, 4), "a")},
        "poses",
        r": T_world_from_cam must be numbers \(N, 4, 4\), got dtype <U1",
    ),
]


def _write_masks(path: Path, content: dict[str, np.ndarray] | None) -> Path:
    if content is None:
        path.write_bytes(NOT_A_ZIP)
    else:
        np.savez(path, allow_pickle=True, **content)  # type: ignore[arg-type]
    return path


@pytest.mark.parametrize(
    ("content", "reader", "match"),
    [c[1:] for c in MASK_CASES],
    ids=[c[0] for c in MASK_CASES],
)
def test_hostile_change_masks_are_one_error_naming_file_and_key(
    tmp_path: Path, content: dict[str, np.ndarray] | None, reader: str, match: str
) -> None:
    path = _write_masks(tmp_path / "hostile_masks.npz", content)
    with pytest.raises(InvalidInputError, match="hostile_masks\\.npz" + match):
        if reader == "masks":
            load_change_masks(path, N_FRAMES, CAM.shape)
        else:
            load_mask_poses(path, _poses())


def test_change_masks_as_chisel_update_writes_them_are_read(tmp_path: Path) -> None:
    # Positive control: what `chisel update --masks` writes (int64 frame_index, poses).
    masks, poses = _masks(), _poses()
    path = tmp_path / "good.npz"
    np.savez(path, frame_index=np.array([1, 0]), masks=masks[::-1], T_world_from_cam=poses)
    assert np.array_equal(load_change_masks(path, N_FRAMES, CAM.shape), masks)
    got = load_mask_poses(path, np.zeros((N_FRAMES, 4, 4)))
    assert np.array_equal(got, poses[[1, 0]])
    np.savez(tmp_path / "u8.npz", masks=masks, frame_index=np.array([0, 1], np.uint8))
    assert load_change_masks(tmp_path / "u8.npz", N_FRAMES, CAM.shape).sum() == masks.sum()


def _evaluate(scene: dict[str, Path], masks: Path, out: Path) -> int:
    return cli_main(
        [
            "evaluate",
            "--gt-mesh",
            str(scene["gt"]),
            "--method",
            f"updated={scene['updated']}",
            "--eval-sequence",
            str(scene["seq"]),
            "--roi=-4,-3,15,4,3,25",
            "--step",
            "1",
            "--samples",
            "500",
            "--out",
            str(out),
            "--change-masks",
            f"updated={masks}",
            "--change-sequence",
            str(scene["seq"]),
            "--start-surfaces",
            f"updated={scene['start']}",
        ]
    )


@pytest.mark.parametrize(
    ("content", "match"),
    [(c[1], c[3]) for c in MASK_CASES],
    ids=[c[0] for c in MASK_CASES],
)
def test_cli_evaluate_refuses_hostile_change_masks_and_writes_nothing(
    scene: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    content: dict[str, np.ndarray] | None,
    match: str,
) -> None:
    path = _write_masks(tmp_path / "hostile_masks.npz", content)
    out = tmp_path / "s1.json"
    assert _evaluate(scene, path, out) == 1
    err = capsys.readouterr().err
    _one_line_naming(err, "chisel evaluate: error:", str(path))
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [path]  # no partial or temporary output either


def test_cli_evaluate_scores_good_change_masks(
    scene: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = tmp_path / "good.npz"
    np.savez(good, frame_index=np.arange(N_FRAMES), masks=_masks(), T_world_from_cam=_poses())
    out = tmp_path / "s1.json"
    assert _evaluate(scene, good, out) == 0, capsys.readouterr().err
    cell = json.loads(out.read_text())["methods"]["updated"]
    assert cell["mask_precision"] == 1.0 and cell["mask_recall"] == pytest.approx(0.5)


# ------------------------------------------- chisel report --panels / --ct-slices / --sweep


def _metrics() -> dict:
    cell: dict[str, float | None] = {k: 0.1 for k in METRIC_KEYS}
    cell.update(n_points=100, n_gt_in_box=110, mask_precision=None, mask_recall=None)
    steps = [{"step": s, "label": "", "methods": {"updated": dict(cell)}} for s in (0, 1)]
    return assemble_table(steps, "hostile")


def _ct_slice() -> CtSlice:
    hu = np.zeros((6, 8), np.float32)
    return CtSlice(1, "axial", 0.0, np.eye(4), {"preoperative": hu, "updated": hu + 100})


def _sweep_header() -> str:
    return ",".join(["param_name", *SWEEP_COLUMNS]) + "\n"


def _npz(**arrays: object) -> Callable[[Path], None]:
    return lambda p: np.savez(p, **arrays)  # type: ignore[arg-type]


def _bytes(data: bytes) -> Callable[[Path], None]:
    def write(p: Path) -> None:
        p.write_bytes(data)

    return write


PANELS = "endoscopic-chisel/panels"
RGB = np.zeros((1, 4, 4, 3), np.uint8)

# option, file name, how to write it, the error class, the message (after the file's name)
REPORT_CASES: list[tuple[str, str, str, Callable[[Path], None], type[Exception], str]] = [
    (
        "panels_without_version",
        "--panels",
        "p.npz",
        _npz(format=np.array(PANELS), step=np.array([1]), frame_index=np.array([0]), rgb=RGB),
        FormatVersionError,
        r": panels file has no 'version'; this reader reads version 1",
    ),
    (
        "panels_version_a_string",
        "--panels",
        "p.npz",
        _npz(
            format=np.array(PANELS),
            version=np.array("1"),
            step=np.array([1]),
            frame_index=np.array([0]),
            rgb=RGB,
        ),
        FormatVersionError,
        r": panels version '1'; this reader reads 1",
    ),
    (
        "panels_not_a_zip",
        "--panels",
        "p.npz",
        _bytes(NOT_A_ZIP),
        InvalidInputError,
        r": cannot read panels \(\.npz without pickle\)",
    ),
    (
        "ct_meta_not_an_object",
        "--ct-slices",
        "ct.npz",
        _npz(meta=np.array("[1,2]")),
        InvalidInputError,
        r": meta: expected a JSON object, got an array",
    ),
    (
        "ct_meta_nested_100000_deep",
        "--ct-slices",
        "ct.npz",
        _npz(meta=np.array("[" * 100000 + "]" * 100000)),
        InvalidInputError,
        r": meta: JSON nested deeper than 64 levels",
    ),
    (
        "sweep_short_row",
        "--sweep",
        "sweep.csv",
        _bytes((_sweep_header() + "frames,10,1\n").encode()),
        InvalidInputError,
        r": line 2: expected 9 fields, got 3",
    ),
    (
        "sweep_not_utf8",
        "--sweep",
        "sweep.csv",
        _bytes(_sweep_header().encode() + b"frames,10\xff,1\n"),
        InvalidInputError,
        r": cannot parse sweep CSV: not UTF-8 text",
    ),
]

READERS: dict[str, Callable[[Path], object]] = {
    "--panels": read_panels,
    "--ct-slices": read_ct_slices,
    "--sweep": read_sweep_csv,
}


def _report_args(option: str, path: Path) -> list[str]:
    return [option, f"frames={path}" if option == "--sweep" else str(path)]


@pytest.mark.parametrize(
    ("option", "name", "write", "error", "match"),
    [c[1:] for c in REPORT_CASES],
    ids=[c[0] for c in REPORT_CASES],
)
def test_report_refuses_hostile_inputs_naming_the_file_and_writes_nothing(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    option: str,
    name: str,
    write: Callable[[Path], None],
    error: type[Exception],
    match: str,
) -> None:
    path = tmp_path / name
    write(path)
    with pytest.raises(error, match=name.replace(".", r"\.") + match):
        READERS[option](path)
    write_table(tmp_path, _metrics())
    out = tmp_path / "r.html"
    rc = cli_main(
        ["report", "--metrics", str(tmp_path / "metrics.json"), "--out", str(out)]
        + _report_args(option, path)
    )
    assert rc == 1
    _one_line_naming(capsys.readouterr().err, "chisel report: error:", str(path))
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith((".r.html", "r.html"))]


def test_report_reads_good_panels_ct_slices_and_sweep(tmp_path: Path) -> None:
    # Positive control for the cases above: the files as the project writes them.
    metrics = _metrics()
    write_table(tmp_path, metrics)
    write_panels(tmp_path / "p.npz", [StepPanel(1, 0, rgb=RGB[0])])
    write_ct_slices(tmp_path / "ct.npz", [_ct_slice()])
    write_sweep_csv(tmp_path / "sweep.csv", tabulate_sweep("frames", [(10.0, metrics)]))
    assert [p.step for p in read_panels(tmp_path / "p.npz")] == [1]
    assert read_ct_slices(tmp_path / "ct.npz")[0].methods == ["updated"]
    assert read_sweep_csv(tmp_path / "sweep.csv").values() == [10.0]
    out = tmp_path / "r.html"
    rc = cli_main(
        ["report", "--metrics", str(tmp_path / "metrics.json"), "--out", str(out)]
        + _report_args("--panels", tmp_path / "p.npz")
        + _report_args("--ct-slices", tmp_path / "ct.npz")
        + _report_args("--sweep", tmp_path / "sweep.csv")
    )
    assert rc == 0 and out.stat().st_size > 0


# ----------------------------------------------- python -m sim render: steps[k].cut_faces


@pytest.fixture(scope="module")
def toy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_toy_phantom(tmp_path_factory.mktemp("hostile_toy") / "toy", n_bites=1)


def _object_npy(p: Path) -> None:
    np.save(p, np.array([1, None], dtype=object), allow_pickle=True)


# file name (beside the phantom's meshes unless it starts with ".."), how to write it,
# the error class, the message (after the file's name)
CUT_CASES: list[tuple[str, str, Callable[[Path], None] | None, type[Exception], str]] = [
    (
        "an_npz_archive",
        "meshes/cut.npz",
        _npz(labels=np.zeros(3, np.uint8)),
        PhantomError,
        r"cut\.npz: steps\[1\]\.cut_faces: not a \.npy array \(bad header",
    ),
    (
        "a_corrupt_zip",
        "meshes/cut.npy",
        _bytes(NOT_A_ZIP),
        PhantomError,
        r"cut\.npy: steps\[1\]\.cut_faces: not a \.npy array \(bad header",
    ),
    (
        "python_objects",
        "meshes/cut.npy",
        _object_npy,
        PhantomError,
        r"cut\.npy: steps\[1\]\.cut_faces: this \.npy holds Python objects",
    ),
    (
        "outside_the_phantom",
        "../other/meshes/step_01_cut_faces.npy",
        None,
        OutsideManifestError,
        r"phantom\.json: steps\[1\]\.cut_faces names '\.\./other/.*outside the manifest's "
        r"folder .*--allow-outside-phantom",
    ),
]


@pytest.mark.parametrize(
    ("rel", "write", "error", "match"),
    [c[1:] for c in CUT_CASES],
    ids=[c[0] for c in CUT_CASES],
)
def test_sim_render_refuses_hostile_cut_faces_before_rendering(
    toy: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    rel: str,
    write: Callable[[Path], None] | None,
    error: type[Exception],
    match: str,
) -> None:
    ph = tmp_path / "ph"
    shutil.copytree(toy, ph)
    shutil.copytree(toy, tmp_path / "other")
    if write is not None:
        write(ph / rel)
    manifest = json.loads((ph / "phantom.json").read_text())
    manifest["steps"][1]["cut_faces"] = rel
    (ph / "phantom.json").write_text(json.dumps(manifest))
    phantom = load_phantom(ph)
    n_faces = len(load_mesh(phantom.steps[1].mesh_path).faces)
    with pytest.raises(error, match=match):
        load_cut_faces(phantom, 1, n_faces)
    out = tmp_path / "out"
    small = ["--frames", "2", "--preop-frames", "2", "--width", "32", "--height", "24"]
    rc = sim_main(["render", "--phantom", str(ph), "--out", str(out), *small, "--quiet"])
    assert rc == 1
    named = "phantom.json" if write is None else Path(rel).name
    _one_line_naming(capsys.readouterr().err, "sim render: error:", named, "steps[1].cut_faces")
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other", "ph"]


def test_cut_faces_as_the_generator_writes_them_are_read(toy: Path, tmp_path: Path) -> None:
    # Positive control: the toy phantom's own labels, and (allowed explicitly, as for its
    # meshes) another folder's labels.
    phantom = load_phantom(toy)
    n_faces = len(load_mesh(phantom.steps[1].mesh_path).faces)
    labels = load_cut_faces(phantom, 1, n_faces)
    assert labels is not None and labels.any() and not labels.all()
    ph = tmp_path / "ph"
    shutil.copytree(toy, ph)
    shutil.copytree(toy, tmp_path / "other")
    manifest = json.loads((ph / "phantom.json").read_text())
    manifest["steps"][1]["cut_faces"] = "../other/meshes/step_01_cut_faces.npy"
    (ph / "phantom.json").write_text(json.dumps(manifest))
    outside = load_cut_faces(load_phantom(ph), 1, n_faces, allow_outside=True)
    assert outside is not None and np.array_equal(outside, labels)
