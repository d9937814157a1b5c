"""Bad input, round three (issue 17, what was left): each case is refused with one of the
project's errors naming the file, and earlier outputs are kept."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from chisel.core.errors import CameraError, InvalidInputError, PoseError
from chisel.core.geometry import Camera, look_at
from chisel.io.calibration import read_calibration
from chisel.io.sequence import Frame, Sequence, write_sequence

CAM = Camera.from_fov(32, 24, 80)


def _sequence(path: Path, n: int = 3) -> Path:
    """A small sequence whose camera moves along x, 10-12 mm from the world origin."""
    rng = np.random.default_rng(0)
    frames = [
        Frame(
            i,
            look_at([10.0 + i, 0.0, 0.0], [10.0 + i, 0.0, 30.0], up=[0, -1, 0]),
            rng.integers(0, 255, (*CAM.shape, 3), dtype=np.uint8),
            rng.uniform(5, 20, CAM.shape).astype(np.float32),
        )
        for i in range(n)
    ]
    return write_sequence(path, CAM, frames)


def _edit_header(seq: Path, **changes: Any) -> None:
    header = json.loads((seq / "sequence.json").read_text())
    header.update(changes)
    (seq / "sequence.json").write_text(json.dumps(header))


# ------------------------------------------------------- a: pose translations in metres


def test_sequence_poses_in_metres_are_refused_naming_poses_txt(tmp_path: Path) -> None:
    seq = _sequence(tmp_path / "seq")
    poses_mm = Sequence(seq).poses
    metres = poses_mm.copy()
    metres[:, :3, 3] /= 1000.0  # 10-12 mm written as 0.010-0.012
    (seq / "poses.txt").write_text(
        "\n".join(" ".join(f"{v:.17g}" for v in T.ravel()) for T in metres) + "\n"
    )
    with pytest.raises(
        PoseError, match=r"within 0\.012 of the world origin.*look like metres"
    ) as info:
        Sequence(seq)
    assert info.value.source == str(seq / "poses.txt")
    assert "multiply the translations by 1000" in info.value.problem
    # A sequence imported with the units check switched off on purpose is read as written.
    _edit_header(seq, meta={"pose_units_checked": False})
    np.testing.assert_array_equal(Sequence(seq).poses[:, :3, 3], metres[:, :3, 3])


def test_one_frame_at_the_origin_is_not_taken_for_metres(tmp_path: Path) -> None:
    # The importers' rule: a single pose near the origin is a plausible mm pose.
    frames = [Frame(0, np.eye(4), np.zeros((*CAM.shape, 3), np.uint8))]
    seq = write_sequence(tmp_path / "seq", CAM, frames)
    assert len(Sequence(seq)) == 1


# ----------------------------------------- d: header and calibration through one reader


def test_sequence_json_nested_deep_is_one_error(tmp_path: Path) -> None:
    seq = _sequence(tmp_path / "seq")
    (seq / "sequence.json").write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(InvalidInputError, match="nested deeper than 64 levels") as info:
        Sequence(seq)
    assert info.value.source == str(seq / "sequence.json")


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        # json.loads raised RecursionError here: a traceback.
        ("c.json", "[" * 100000 + "]" * 100000, "nested deeper than 64 levels"),
        ("c.json", "[1, 2]", "expected a JSON object, got an array"),
        ("c.json", '{"K": 1} junk', "invalid JSON"),
        ("c.yaml", "- 1\n- 2\n", "expected a mapping of calibration keys"),
        ("c.yaml", "K: [1, 2\n", "invalid YAML"),
        ("c.yaml", "a: " + "x" * (2 << 20) + "\n", "larger than 1048576 bytes"),
    ],
    ids=["json-deep", "json-array", "json-junk", "yaml-list", "yaml-broken", "yaml-huge"],
)
def test_calibration_goes_through_the_one_json_and_yaml_reader(
    tmp_path: Path, name: str, content: str, message: str
) -> None:
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(CameraError, match=message) as info:
        read_calibration(path)
    assert info.value.source == str(path)


# ------------------------------------------------- b: out of memory names the input file


def _no_memory(*_args: Any, **_kwargs: Any) -> Any:
    raise MemoryError


def test_out_of_memory_in_a_reader_names_the_file(tmp_path: Path, monkeypatch) -> None:
    import nibabel
    import trimesh

    from chisel.core.errors import ResourceLimitError
    from chisel.io.ct import read_ct_volume
    from chisel.io.meshfile import read_mesh_file
    from chisel.model import TsdfModel

    seq = _sequence(tmp_path / "seq")
    opened = Sequence(seq)
    (tmp_path / "m.npz").write_bytes(b"not a zip: np.load is reached")
    (tmp_path / "ct.nii").write_bytes(b"\0" * 352)
    (tmp_path / "s.ply").write_text("ply\n")
    cases = [
        ("numpy.load", lambda: opened.depth_mm(1), seq / "depth" / "000001.npy", "depth map"),
        ("numpy.loadtxt", lambda: Sequence(seq), seq / "poses.txt", "pose file"),
        ("numpy.load", lambda: TsdfModel.load(tmp_path / "m.npz"), tmp_path / "m.npz", "model"),
        ("nibabel.load", lambda: read_ct_volume(tmp_path / "ct.nii"), tmp_path / "ct.nii", "CT"),
        ("trimesh.load", lambda: read_mesh_file(tmp_path / "s.ply"), tmp_path / "s.ply", "mesh"),
    ]
    modules = {"numpy": np, "nibabel": nibabel, "trimesh": trimesh}
    for target, call, path, what in cases:
        module, name = target.split(".")
        with monkeypatch.context() as m:
            m.setattr(modules[module], name, _no_memory)
            with pytest.raises(
                ResourceLimitError, match=f"out of memory reading this {what}"
            ) as info:
                call()
        assert info.value.source == str(path), target


def test_out_of_memory_elsewhere_names_the_commands_inputs(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    from chisel.cli import main as chisel_main
    from chisel.model import TsdfModel
    from sim.cli import main as sim_main

    (tmp_path / "m.npz").write_bytes(b"x")
    monkeypatch.setattr(TsdfModel, "load", _no_memory)  # a MemoryError no reader named
    assert (
        chisel_main(["mesh", "--model", str(tmp_path / "m.npz"), "--out", str(tmp_path / "o.ply")])
        == 1
    )
    err = capsys.readouterr().err
    assert f"chisel mesh: error: out of memory processing --model {tmp_path / 'm.npz'} (" in err
    assert "Traceback" not in err and not (tmp_path / "o.ply").exists()

    seq = _sequence(tmp_path / "seq")
    monkeypatch.setattr("sim.retrack.Sequence", _no_memory)
    assert sim_main(["retrack", "--sequence", str(seq), "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err
    assert f"sim retrack: error: out of memory processing --sequence {seq} (" in err


# ---------------------------------------- c: temporary files of killed single-file writes


def test_temp_file_of_a_killed_write_is_removed_by_the_next_write(tmp_path: Path, caplog) -> None:
    import os
    import signal
    import subprocess
    import sys

    from chisel.core.atomic import atomic_write_bytes

    out = tmp_path / "m.npz"
    atomic_write_bytes(out, b"earlier")
    code = (
        "import os, signal, sys\n"
        "from chisel.core.atomic import atomic_path\n"
        "with atomic_path(sys.argv[1]) as tmp:\n"
        "    tmp.write_bytes(b'half')\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(out)], timeout=120)
    assert proc.returncode == -signal.SIGKILL
    killed = [p for p in tmp_path.iterdir() if p != out]
    assert len(killed) == 1 and killed[0].read_bytes() == b"half"  # what a kill leaves
    assert out.read_bytes() == b"earlier"
    live = tmp_path / f".m.npz.tmp-{os.getppid()}-abcd1234.npz"  # a live concurrent writer
    live.write_bytes(b"in progress")
    legacy = tmp_path / ".m.npz.k3j_9xq2.npz"  # an older version's name: no pid
    legacy.write_bytes(b"old")
    with caplog.at_level("WARNING"):
        atomic_write_bytes(out, b"next")
    assert out.read_bytes() == b"next"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, live.name, legacy.name])
    assert f"{legacy} is left from an interrupted run; safe to delete" in caplog.text


# ---------------------------------------------------------- e: NIfTI headers (see also F)


def _nifti(path: Path, **fields: tuple[int, str, Any]) -> Path:
    """A small valid label NIfTI with header fields overwritten: name=(offset, fmt, value)."""
    import gzip
    import struct

    from chisel.io.ct import nifti_bytes

    data = np.zeros((4, 5, 6), np.int16)
    data[1:3, 1:4, 2:5] = 1
    raw = bytearray(nifti_bytes(data, np.diag([0.5, 0.6, 0.7, 1.0]), compress=False))
    for offset, fmt, value in fields.values():
        struct.pack_into(fmt, raw, offset, value)
    raw += bytes(4096)  # room for a wider data type
    path.write_bytes(gzip.compress(bytes(raw)) if path.name.endswith(".gz") else bytes(raw))
    return path


def test_nifti_headers_that_crashed_or_allocated_are_refused(tmp_path: Path) -> None:
    import tracemalloc

    from chisel.core.errors import ResourceLimitError
    from chisel.io.ct import read_ct_volume

    cases = [
        # RGB voxels: np.min raised numpy's UFuncTypeError (a traceback)
        ({"datatype": (70, "<h", 128)}, InvalidInputError, "voxels must be real numbers"),
        # complex voxels: read with the imaginary part silently dropped
        ({"datatype": (70, "<h", 32)}, InvalidInputError, "got data type complex64"),
        # a spatial unit code that is no unit: nibabel's KeyError (a traceback)
        ({"xyzt_units": (123, "<B", 4)}, InvalidInputError, "spatial unit code 4"),
        # 800 MB declared in a small .nii.gz: nibabel allocated it before reading
        (
            {"dim1": (42, "<h", 2000), "dim2": (44, "<h", 2000), "dim3": (46, "<h", 100)},
            InvalidInputError,
            "NIfTI declares 800000000 bytes of data .* but the file holds",
        ),
        (
            {"dim1": (42, "<h", 32767), "dim2": (44, "<h", 32767), "dim3": (46, "<h", 32767)},
            ResourceLimitError,
            r"over the limit of 8589934592 bytes",
        ),
    ]
    for fields, error, message in cases:
        path = _nifti(tmp_path / "ct.nii.gz", **fields)
        tracemalloc.start()
        try:
            with pytest.raises(error, match=message) as info:
                read_ct_volume(path)
        finally:
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
        assert info.value.source == str(path)
        assert peak < 64 * 2**20, (fields, peak)


def test_nifti_placed_a_universe_away_or_with_nanometre_voxels_is_refused(tmp_path: Path) -> None:
    # The model's own bounds on placement and voxel size (chisel.io.limits) hold for a CT's
    # affine too: 3e38 mm, or 1e-6 mm voxels, meshed into an unusable surface, exit 0.
    import nibabel as nib

    from chisel.io.ct import read_ct_volume

    data = np.zeros((4, 5, 6), np.int16)
    data[1:3, 1:4, 2:5] = 1
    path = tmp_path / "ct.nii"

    def write(affine: np.ndarray) -> None:  # nibabel: our writer refuses these affines too
        img = nib.Nifti1Image(data, affine)
        img.set_sform(affine, code=1)
        nib.save(img, str(path))

    for affine, message in (
        (
            np.array([[0.5, 0, 0, 3e38], [0, 0.5, 0, 0], [0, 0, 0.5, 0], [0, 0, 0, 1]]),
            "farther than",
        ),
        (np.diag([1e-6, 0.5, 0.5, 1.0]), "voxel spacing"),
        (np.diag([5e3, 0.5, 0.5, 1.0]), "voxel spacing"),
    ):
        write(affine)
        with pytest.raises(InvalidInputError, match=message) as info:
            read_ct_volume(path)
        assert info.value.source == str(path)
    # A usual scanner frame (origin 200 mm away, 0.5 mm voxels) is read.
    ok = np.array([[-0.5, 0, 0, 120.0], [0, -0.5, 0, 140.0], [0, 0, 0.5, -200.0], [0, 0, 0, 1]])
    write(ok)
    assert read_ct_volume(path).data.shape == (4, 5, 6)


# ------------------------------------------------------- f: a fresh hostile pass (found)


def test_an_output_that_is_a_symlink_loop_is_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    # Path.resolve raised RuntimeError ("Symlink loop"): a traceback from chisel and phantoms.
    from chisel.cli import main as chisel_main
    from phantoms.cli import main as phantoms_main
    from sim.cli import main as sim_main

    monkeypatch.chdir(tmp_path)
    Path("loop").symlink_to("loop")
    seq = _sequence(tmp_path / "seq")
    (tmp_path / "m.npz").write_bytes(b"x")
    runs = [
        (chisel_main, ["mesh", "--model", "m.npz", "--out", "loop"], "chisel mesh"),
        (chisel_main, ["mesh", "--model", "m.npz", "--out", "loop/x.ply"], "chisel mesh"),
        (sim_main, ["retrack", "--sequence", str(seq), "--out", "loop"], "sim retrack"),
        (phantoms_main, ["generate", "--seed", "0", "--out", "loop"], "phantoms generate"),
    ]
    for main, argv, prog in runs:
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert f"{prog}: error: " in err and "cannot resolve the path: Symlink loop" in err, err
        assert "Traceback" not in err


def test_a_morphology_kernel_wider_than_any_image_is_refused() -> None:
    # --open-px 1000000000 ran registration, then died of MemoryError in OpenCV.
    from chisel.change import ChangeConfig

    for name in ("open_px", "close_px"):
        with pytest.raises(InvalidInputError, match=rf"{name}: must be at most 16384 px"):
            ChangeConfig(**{name: 10**9})
    assert ChangeConfig(open_px=16384).open_px == 16384


def test_a_seed_range_of_a_trillion_is_refused_before_it_fills_memory() -> None:
    from chisel.core.config import MAX_SEEDS
    from sim.dataset import parse_seeds
    from sim.errors import ConfigError

    with pytest.raises(ConfigError, match="over the limit") as info:
        parse_seeds("0-999999999999")
    assert info.value.source == "--seeds"
    assert len(parse_seeds(f"0-{MAX_SEEDS - 1}")) == MAX_SEEDS
