"""Hostile field values in calibration, pose, checkpoint and model files.

Each bad value is refused with an :class:`InvalidInputError` subclass naming the file and
the field (docs/bad-inputs.md), never a raw ``ValueError`` / ``TypeError`` /
``OverflowError`` / ``ZeroDivisionError`` / ``AttributeError`` from inside a reader.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from chisel.core.errors import (
    CameraError,
    InvalidInputError,
    PoseError,
    ResourceLimitError,
)
from chisel.io.calibration import read_calibration

W, H = 64, 48
GOOD = {"width": W, "height": H, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5}


def _calib_json(tmp_path: Path, **changes: Any) -> Path:
    path = tmp_path / "c.json"
    path.write_text(json.dumps({**GOOD, **changes}))  # inf / NaN written as Infinity / NaN
    return path


# ----------------------------------------------------------------- calibration


@pytest.mark.parametrize(
    "changes, key",
    [
        ({"width": "abc"}, "width"),  # was ValueError
        ({"width": [64]}, "width"),  # was TypeError
        ({"width": float("inf")}, "width"),  # was OverflowError
        ({"height": float("nan")}, "height"),  # was ValueError
        ({"width": 64.5}, "width"),  # was silently truncated to 64
        ({"width": True}, "width"),  # was 1 px
        ({"width": -64, "height": -48}, "width"),
        ({"fx": "fifty"}, "fx"),  # was ValueError
        ({"fx": [50]}, "fx"),  # was ValueError
        ({"fy": -50.0}, "fy"),  # was refused as "K is not a pinhole intrinsic matrix"
        ({"cx": float("nan")}, "cx"),  # was refused as "K must be a finite 3x3 matrix"
        ({"cy": {"a": 1}}, "cy"),  # was TypeError
    ],
)
def test_calibration_field_of_the_wrong_kind(tmp_path: Path, changes: dict, key: str) -> None:
    path = _calib_json(tmp_path, **changes)
    with pytest.raises(CameraError, match=rf"c\.json: {key} must be"):
        read_calibration(path).camera_for(W, H)


def test_calibration_of_zero_size_with_rescale(tmp_path: Path) -> None:
    # was ZeroDivisionError in camera_for: 0x0 has "the same aspect ratio" as any frame
    path = _calib_json(tmp_path, width=0, height=0)
    with pytest.raises(CameraError, match=r"c\.json: width must be a positive whole number"):
        read_calibration(path).camera_for(W, H, rescale=True)


def test_calibration_size_past_the_image_limit(tmp_path: Path) -> None:
    path = _calib_json(tmp_path, width=10**6, height=750_000)
    with pytest.raises(ResourceLimitError, match=r"c\.json: width is 1000000 px, over the limit"):
        read_calibration(path)


def test_calibration_camera_matrix_with_nan_names_the_matrix(tmp_path: Path) -> None:
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"K": [[50, 0, float("nan")], [0, 50, 23.5], [0, 0, 1]]}))
    with pytest.raises(CameraError, match=r"c\.json: camera matrix entries must be finite"):
        read_calibration(path)


def test_calibration_fields_accepted_as_before(tmp_path: Path) -> None:
    """Positive control: integral floats and numeric strings were read before and still are."""
    cam = read_calibration(_calib_json(tmp_path)).camera_for(W, H)
    assert (cam.width, cam.height, cam.fx, cam.cy) == (W, H, 50.0, 23.5)
    calib = read_calibration(_calib_json(tmp_path, width=64.0, height="48", fx="50"))
    assert calib.size == (W, H) and calib.K[0, 0] == 50.0
    scaled = read_calibration(_calib_json(tmp_path, width=128, height=96, fx=100, fy=100))
    assert scaled.camera_for(W, H, rescale=True).fx == pytest.approx(50.0)


_OPENCV_YAML = """%YAML:1.0
---
image_width: {width}
image_height: 48
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 50., 0., 31.5, 0., 50., 23.5, 0., 0., 1. ]
"""


@pytest.mark.parametrize("width", [".Nan", ".Inf", "abc", "[64]", "0", "64.5"])
def test_opencv_yaml_image_width_of_the_wrong_kind(tmp_path: Path, width: str) -> None:
    # .Nan was ValueError; "abc" and [64] read as DBL_MAX px; 0 divided by zero on rescale
    path = tmp_path / "c.yaml"
    path.write_text(_OPENCV_YAML.format(width=width))
    with pytest.raises(CameraError, match=r"c\.yaml: image_width must be a positive whole"):
        read_calibration(path).camera_for(W, H, rescale=True)


def test_opencv_yaml_image_width_accepted(tmp_path: Path) -> None:
    for width in ("64", "64.0"):
        path = tmp_path / "c.yaml"
        path.write_text(_OPENCV_YAML.format(width=width))
        assert read_calibration(path).size == (W, H)


def test_ros_yaml_width_of_the_wrong_kind(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(
        "image_width: abc\nimage_height: 48\n"
        "camera_matrix: {rows: 3, cols: 3, data: [50, 0, 31.5, 0, 50, 23.5, 0, 0, 1]}\n"
    )
    with pytest.raises(CameraError, match=r"c\.yaml: image_width must be a positive whole"):
        read_calibration(path)


# ----------------------------------------------------------------- pose and time files


def test_pose_file_that_is_not_utf8(tmp_path: Path) -> None:
    from chisel.io.import_poses import read_pose_file

    path = tmp_path / "poses.txt"
    path.write_bytes(b"\xff\xfe" + " ".join(["1"] * 16).encode())  # was UnicodeDecodeError
    with pytest.raises(PoseError, match=r"poses\.txt: cannot parse pose file: not UTF-8"):
        read_pose_file(path)
    path.write_text(" ".join(str(v) for v in np.eye(4).ravel()) + "\n")
    assert read_pose_file(path).poses.shape == (1, 4, 4)  # positive control


def test_frame_time_file_that_is_not_utf8(tmp_path: Path) -> None:
    from chisel.io.import_poses import read_frame_times

    path = tmp_path / "times.csv"
    path.write_bytes(b"t\n0.0\n\xff0.1\n")  # was UnicodeDecodeError
    with pytest.raises(
        InvalidInputError, match=r"times\.csv: cannot parse frame-time file: not UTF-8"
    ):
        read_frame_times(path)
    path.write_text("t\n0.0\n0.1\n")
    assert read_frame_times(path).tolist() == [0.0, 0.1]  # positive control


def test_transform_file_that_is_not_utf8(tmp_path: Path) -> None:
    from chisel.io.import_poses import read_transform

    path = tmp_path / "handeye.txt"
    path.write_bytes(b"\xff" * 16)  # was UnicodeDecodeError
    with pytest.raises(PoseError, match=r"handeye\.txt: cannot parse T_marker_from_cam file"):
        read_transform(path, "T_marker_from_cam")


def test_pose_file_over_the_text_size_limit(tmp_path: Path, monkeypatch) -> None:
    from chisel.io import limits
    from chisel.io.import_poses import read_frame_times, read_pose_file

    monkeypatch.setattr(limits, "MAX_TEXT_BYTES", 64)  # was read whole, whatever its size
    poses, times = tmp_path / "poses.txt", tmp_path / "times.csv"
    poses.write_text((" ".join(str(v) for v in np.eye(4).ravel()) + "\n") * 4)
    times.write_text("\n".join(f"{0.1 * i:.1f}" for i in range(40)))
    with pytest.raises(ResourceLimitError, match=r"poses\.txt: pose file is \d+ bytes, over"):
        read_pose_file(poses)
    with pytest.raises(ResourceLimitError, match=r"times\.csv: frame-time file is \d+ bytes"):
        read_frame_times(times)


def test_pose_npy_of_strings_or_complex(tmp_path: Path) -> None:
    from chisel.io.import_poses import read_pose_file

    path = tmp_path / "poses.npy"
    np.save(path, np.array([["x"] * 16]))  # was ValueError from astype
    with pytest.raises(PoseError, match=r"poses\.npy: poses must be real numbers, got dtype"):
        read_pose_file(path)
    np.save(path, np.eye(4)[None].astype(np.complex128) * 1j)  # imaginary part was dropped
    with pytest.raises(PoseError, match=r"poses\.npy: poses must be real numbers"):
        read_pose_file(path)


# ----------------------------------------------------------------- depth checkpoints


def _monocular(tmp_path: Path) -> Path:
    from chisel.depth.checkpoint import save_checkpoint
    from chisel.depth.network import DepthNet, DepthNetConfig

    net = DepthNet(DepthNetConfig(widths=(4, 8), blocks=(0, 0)))
    return save_checkpoint(tmp_path / "good.pt", net, {"note": "t"})


def _change_aware(tmp_path: Path) -> Path:
    from chisel.depth.change_aware import ChangeNet, ChangeNetConfig, save_change_checkpoint

    net = ChangeNet(ChangeNetConfig(widths=(8, 12), input_scale=1.0))
    return save_change_checkpoint(tmp_path / "good.pt", net, {"note": "t"})


def _rewrite(good: Path, out: Path, edit: Any) -> Path:
    import torch

    payload = torch.load(good, weights_only=True)
    edit(payload)
    torch.save(payload, out)
    return out


def _set_first_tensor(payload: dict, value: Any) -> None:
    payload["state_dict"][next(iter(payload["state_dict"]))] = value


@pytest.mark.parametrize("kind", ["monocular", "change-aware"])
@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda p: _set_first_tensor(p, 3), r"state_dict\['[\w.]+'\] is int, expected a tensor"),
        (lambda p: p["state_dict"].update({7: p["state_dict"].popitem()[1]}), r"state_dict key 7"),
        (lambda p: p.update(info=[1, 2]), r"info must be a dict \(JSON object\), got list"),
        (lambda p: p.update(info="ab"), r"info must be a dict \(JSON object\), got str"),
        (lambda p: p.update(info=None), r"info must be a dict \(JSON object\), got NoneType"),
    ],
    ids=["int-tensor", "int-key", "info-list", "info-str", "info-null"],
)
def test_checkpoint_with_a_field_of_the_wrong_kind(
    tmp_path: Path, kind: str, edit: Any, match: str
) -> None:
    # were AttributeError ('int' has no 'shape'), TypeError (sorting int and str keys;
    # dict(list)), ValueError (dict("ab"))
    from chisel.depth.change_aware import load_change_checkpoint
    from chisel.depth.checkpoint import CheckpointError, load_checkpoint

    make, load = {
        "monocular": (_monocular, load_checkpoint),
        "change-aware": (_change_aware, load_change_checkpoint),
    }[kind]
    good = make(tmp_path)
    assert load(good)[1] == {"note": "t"}  # positive control
    bad = _rewrite(good, tmp_path / "c.pt", edit)
    with pytest.raises(CheckpointError, match=rf"c\.pt: {match}"):
        load(bad)


def test_checkpoint_without_info_loads(tmp_path: Path) -> None:
    from chisel.depth.checkpoint import load_checkpoint

    bad = _rewrite(_monocular(tmp_path), tmp_path / "c.pt", lambda p: p.pop("info"))
    assert load_checkpoint(bad)[1] == {}  # older files: no info is an empty one


def test_depth_export_of_a_checkpoint_with_a_plain_int(tmp_path: Path, capsys) -> None:
    from chisel.cli import main as chisel_main

    bad = _rewrite(_monocular(tmp_path), tmp_path / "c.pt", lambda p: _set_first_tensor(p, 3))
    out = tmp_path / "e.pt"
    assert chisel_main(["depth", "export", "--checkpoint", str(bad), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "error:" in err and "c.pt: state_dict[" in err and "Traceback" not in err
    assert not out.exists()


# ----------------------------------------------------------------- model files


def _model_fields(tmp_path: Path) -> dict[str, np.ndarray]:
    from chisel.model import TsdfModel

    TsdfModel.empty([0, 0, 0], [4, 4, 4], 1.0, 2.0).save(tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize(
    "key, value, match",
    [
        # numpy's ValueError before
        ("T_world_from_voxel", np.full((4, 4), "x"), r"T_world_from_voxel: expected real numbers"),
        # cast with a ComplexWarning before, the imaginary part dropped
        (
            "T_world_from_voxel",
            np.eye(4, dtype=np.complex128) * (1 + 1j),
            r"T_world_from_voxel: expected real numbers, got dtype complex128",
        ),
        # loaded before; the next save overflowed int64
        (
            "step",
            np.array(2**64 - 1, dtype=np.uint64),
            r"step must be an integer >= 0 and < 2\*\*62",
        ),
        ("step", np.array(2**62, dtype=np.int64), r"step must be an integer >= 0 and < 2\*\*62"),
    ],
    ids=["T-strings", "T-complex", "step-uint64-max", "step-2**62"],
)
def test_model_field_of_the_wrong_kind(tmp_path: Path, key: str, value: Any, match: str) -> None:
    from chisel.model import TsdfModel

    fields = _model_fields(tmp_path)
    assert TsdfModel.load(tmp_path / "good.npz").step == 0  # positive control
    fields[key] = value
    np.savez(tmp_path / "m.npz", **fields)
    with warnings.catch_warnings():
        warnings.simplefilter("error", np.exceptions.ComplexWarning)  # no silent cast
        with pytest.raises(InvalidInputError, match=rf"m\.npz: {match}"):
            TsdfModel.load(tmp_path / "m.npz")


def test_model_fields_accepted(tmp_path: Path) -> None:
    from chisel.model import TsdfModel

    fields = _model_fields(tmp_path)
    fields["step"] = np.array(2**62 - 1, dtype=np.uint64)
    fields["T_world_from_voxel"] = np.eye(4, dtype=np.int32)  # integers: voxel size 1 mm
    np.savez(tmp_path / "m.npz", **fields)
    model = TsdfModel.load(tmp_path / "m.npz")
    assert model.step == 2**62 - 1 and model.T_world_from_voxel.dtype == np.float64
    model.save(tmp_path / "again.npz")  # no overflow
    with pytest.raises(InvalidInputError, match=r"step: must be an integer >= 0 and < 2\*\*62"):
        replace(model, step=model.step + 1)  # what chisel update does, one step too far
