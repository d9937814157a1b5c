"""Bad sequence folders: one error naming the file and the problem, inputs and outputs kept.

Cases found by trying to break ``chisel.io.sequence.Sequence``, ``sim export-nerfstudio`` and
``sim retrack``: an output folder that is, holds or lies inside the input sequence (which
the atomic write would have deleted), hand-edited ``sequence.json`` headers that crashed
with a traceback or were accepted, missing pose files, and frames that are missing,
corrupt or of another size (export copied them without looking).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from small_sequences import CAM, write_small_sequence

import chisel.io.sequence as seqmod
from chisel.core.errors import CameraError, InvalidInputError, OutputError, PoseError
from chisel.io.sequence import Sequence
from sim.cli import main
from sim.config import TrackingConfig
from sim.nerfstudio import export_nerfstudio
from sim.retrack import retrack_sequence


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def leftovers(folder: Path) -> list[str]:
    """Temporary folders an atomic write left behind (there must be none)."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.fixture
def seq(tmp_path: Path) -> Path:
    return write_small_sequence(tmp_path / "render" / "preop")


# --- 1. an output over the input --------------------------------------------------------


def _export(seq: Path, out: Path) -> None:
    export_nerfstudio(seq, out)


def _retrack(seq: Path, out: Path) -> None:
    retrack_sequence(seq, out, TrackingConfig(), 0)


@pytest.mark.parametrize("write", [_export, _retrack], ids=["export", "retrack"])
@pytest.mark.parametrize(
    ("where", "why"),
    [
        ("seq", "would replace the input"),
        ("holder", "would replace the input"),
        ("inside", "lies inside the input"),
    ],
)
def test_output_over_the_input_sequence_is_refused(
    seq: Path, write: Callable[[Path, Path], None], where: str, why: str
) -> None:
    render = seq.parent
    out = {"seq": seq, "holder": render, "inside": seq / "ns"}[where]
    before = tree(render)
    with pytest.raises(InvalidInputError, match=why) as info:
        write(seq, out)
    assert info.value.source == str(out)
    assert tree(render) == before
    assert leftovers(render) == [] and leftovers(render.parent) == []


@pytest.mark.parametrize("command", ["export-nerfstudio", "retrack"])
def test_cli_refuses_an_output_holding_the_sequence_in_one_line(
    seq: Path, command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    render = seq.parent
    before = tree(render)
    rc = main([command, "--sequence", str(seq), "--out", str(render)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"{render}: the output folder would replace the input {seq}" in err
    assert tree(render) == before


# --- 2. a malformed sequence.json -------------------------------------------------------


HEADER_CASES: list[tuple[str, Callable[[dict[str, Any]], object], type[Exception], str]] = [
    ("no camera", lambda h: h.pop("camera"), InvalidInputError, "required field 'camera'"),
    ("no num_frames", lambda h: h.pop("num_frames"), InvalidInputError, "'num_frames' is missing"),
    (
        "num_frames text",
        lambda h: h.update(num_frames="three"),
        InvalidInputError,
        "num_frames must be a positive integer, got 'three'",
    ),
    (
        "num_frames zero",
        lambda h: h.update(num_frames=0),
        InvalidInputError,
        "num_frames must be a positive integer, got 0",
    ),
    (
        "camera array",
        lambda h: h.update(camera=[1, 2]),
        CameraError,
        "camera must be an object .* got an array",
    ),
    (
        "K text",
        lambda h: h["camera"].update(K="abc"),
        CameraError,
        r"camera K \(3x3\) and dist \(5\) must be numbers",
    ),
    (
        "width text",
        lambda h: h["camera"].update(width="32"),
        CameraError,
        "camera width must be an integer, got '32'",
    ),
    (
        "no K",
        lambda h: h["camera"].pop("K"),
        CameraError,
        "missing camera field 'K'",
    ),
    (
        "principal point outside",
        lambda h: h["camera"]["K"][0].__setitem__(2, 160.0),
        CameraError,
        r"principal point \(160, .*32x24 image: the intrinsics do not match the image size",
    ),
    (
        "principal point below",
        lambda h: h["camera"]["K"][1].__setitem__(2, -3.0),
        CameraError,
        "intrinsics do not match the image size",
    ),
    (
        "quoted flag",
        lambda h: h.update(has_rgb="false"),
        InvalidInputError,
        "has_rgb must be true or false, got 'false'",
    ),
    ("meta array", lambda h: h.update(meta=[1]), InvalidInputError, "meta must be an object"),
    (
        "units metres",
        lambda h: h.update(units="m"),
        InvalidInputError,
        "units is 'm'; poses and depth must be in mm",
    ),
]


@pytest.mark.parametrize(
    ("change", "error", "message"),
    [case[1:] for case in HEADER_CASES],
    ids=[case[0] for case in HEADER_CASES],
)
def test_malformed_header_is_one_error_naming_sequence_json(
    seq: Path,
    change: Callable[[dict[str, Any]], object],
    error: type[Exception],
    message: str,
) -> None:
    header_path = seq / "sequence.json"
    header = json.loads(header_path.read_text())
    change(header)
    header_path.write_text(json.dumps(header))
    with pytest.raises(error, match=message) as info:
        Sequence(seq)
    assert info.value.source == str(header_path)  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"[1]", "expected a JSON object, got an array"),
        (b'"text"', "expected a JSON object, got a string"),
        (b'\xff\xfe{"format": 1}', "not a text file"),
        (b"{not json", "invalid JSON"),
    ],
    ids=["array", "string", "non-utf8", "not-json"],
)
def test_unreadable_header_is_one_error_naming_sequence_json(
    seq: Path, content: bytes, message: str
) -> None:
    (seq / "sequence.json").write_bytes(content)
    with pytest.raises(InvalidInputError, match=message) as info:
        Sequence(seq)
    assert info.value.source == str(seq / "sequence.json")


def test_principal_point_on_the_image_edge_still_loads(seq: Path) -> None:
    # The bound is the image's extent [-0.5, W - 0.5], not the pixel centres: keep it so.
    header = json.loads((seq / "sequence.json").read_text())
    header["camera"]["K"][0][2] = CAM.width - 0.5
    header["camera"]["K"][1][2] = -0.5
    (seq / "sequence.json").write_text(json.dumps(header))
    assert Sequence(seq).camera.cx == CAM.width - 0.5


def test_header_without_units_reads_as_mm(seq: Path) -> None:
    header = json.loads((seq / "sequence.json").read_text())
    assert header.pop("units") == "mm"  # what the writer stores
    (seq / "sequence.json").write_text(json.dumps(header))
    assert len(Sequence(seq)) == 3


def test_all_black_camera_mask_is_named(seq: Path) -> None:
    # It used to load, and `chisel build` then blamed the CT ("surface not visible").
    cv2.imwrite(str(seq / "camera_mask.png"), np.zeros(CAM.shape, np.uint8))
    with pytest.raises(InvalidInputError, match="camera mask keeps no pixel") as info:
        Sequence(seq)
    assert info.value.source == str(seq / "camera_mask.png")


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("poses.txt", "file is missing"),
        ("poses_true.txt", "file is missing but sequence.json sets has_true_poses"),
    ],
)
def test_missing_pose_file_is_named(seq: Path, name: str, message: str) -> None:
    (seq / name).unlink()
    with pytest.raises(PoseError, match=message) as info:
        Sequence(seq)
    assert info.value.source == str(seq / name)


def test_non_utf8_pose_file_is_named(seq: Path) -> None:
    (seq / "poses.txt").write_bytes(b"\xff\xfe 1 0 0\n")
    with pytest.raises(PoseError, match="cannot parse pose file") as info:
        Sequence(seq)
    assert info.value.source == str(seq / "poses.txt")


# --- 3. bad frames: the accessors and the export ----------------------------------------


def _rm(path: Path) -> None:
    path.unlink()


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:60])


def _small_png(path: Path) -> None:
    assert cv2.imwrite(str(path), np.zeros((10, 10, 3), np.uint8))


def _small_npy(path: Path) -> None:
    np.save(path, np.full((10, 10), 10.0, np.float32))


def _npy_3d(path: Path) -> None:
    np.save(path, np.full((*CAM.shape, 1), 10.0, np.float32))


def _empty(path: Path) -> None:
    path.write_bytes(b"")


def _npz(path: Path) -> None:
    with path.open("wb") as fh:
        np.savez(fh, depth=np.full(CAM.shape, 10.0, np.float32))


FRAME_CASES: list[tuple[str, str, Callable[[Path], None], type[Exception], str]] = [
    ("rgb missing", "rgb/000001.png", _rm, InvalidInputError, "file is missing"),
    (
        "rgb corrupt",
        "rgb/000001.png",
        _truncate,
        InvalidInputError,
        "truncated PNG \\(no IEND chunk\\)",
    ),
    ("rgb 10x10", "rgb/000002.png", _small_png, CameraError, "10x10 .* camera is 32x24"),
    ("depth missing", "depth/000001.npy", _rm, InvalidInputError, "file is missing"),
    ("depth 10x10", "depth/000002.npy", _small_npy, CameraError, "10x10 .* camera is 32x24"),
    ("depth 3-D", "depth/000001.npy", _npy_3d, InvalidInputError, "must be a 2-D"),
    ("depth empty", "depth/000001.npy", _empty, InvalidInputError, "cannot read depth"),
    ("depth npz", "depth/000001.npy", _npz, InvalidInputError, "not an .npz archive"),
    ("mask 10x10", "mask/000000.png", _small_png, CameraError, "10x10 .* camera is 32x24"),
]


@pytest.mark.parametrize("tool", ["export", "retrack"])
@pytest.mark.parametrize(
    ("name", "damage", "error", "message"),
    [case[1:] for case in FRAME_CASES],
    ids=[case[0] for case in FRAME_CASES],
)
def test_bad_frame_is_refused_and_the_earlier_output_is_kept(
    seq: Path,
    tmp_path: Path,
    tool: str,
    name: str,
    damage: Callable[[Path], None],
    error: type[Exception],
    message: str,
) -> None:
    out = tmp_path / "out"

    def run() -> None:
        if tool == "export":
            export_nerfstudio(seq, out)
        else:
            retrack_sequence(seq, out, TrackingConfig(), 0)

    run()
    before = tree(out)
    damage(seq / name)
    with pytest.raises(error, match=message) as info:
        run()
    assert info.value.source == str(seq / name)  # type: ignore[attr-defined]
    assert tree(out) == before
    assert leftovers(tmp_path) == []


def test_export_cli_bad_frame_is_one_line(
    seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (seq / "rgb" / "000001.png").unlink()
    rc = main(["export-nerfstudio", "--sequence", str(seq), "--out", str(tmp_path / "ns")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"{seq / 'rgb' / '000001.png'}: file is missing" in err
    assert not (tmp_path / "ns").exists()


def test_export_mask_write_failure_names_the_mask_and_keeps_the_earlier_export(
    seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "ns"
    export_nerfstudio(seq, out)
    before = tree(out)
    # OpenCV reports a full disk by returning False, not by raising.
    monkeypatch.setattr(seqmod.cv2, "imwrite", lambda *a, **k: False)
    with pytest.raises(OutputError) as info:
        export_nerfstudio(seq, out)
    assert info.value.source == str(out / "masks" / "000000.png")
    assert tree(out) == before
    assert leftovers(tmp_path) == []
