"""Bad input, round two (issue 17): each case is refused with one of the project's errors
naming the file, and earlier outputs are kept."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import trimesh
from test_import_scene import FIELD_STOP, RAW_CAMERA, make_scene

from chisel.cli import main as chisel_main
from chisel.core.errors import InvalidInputError, OutsideManifestError
from chisel.core.geometry import Camera
from chisel.io.import_reference import import_reference
from chisel.io.undistort import circle_mask
from sim.phantom import load_phantom
from sim.synthetic import write_toy_phantom


@pytest.fixture(scope="module")
def scene():
    return make_scene(3)


# ----------------------------------------------------- item 1: files a manifest names


def _reference_dataset(root: Path, scene: Any) -> dict[str, Any]:
    """A one-part reference layout under ``root``; returns its input.json content."""
    base = root / "preop"
    (base / "images").mkdir(parents=True)
    for k in range(3):
        cv2.imwrite(str(base / "images" / f"{k:06d}.jpg"), scene.raw_rgb[k])
    np.save(base / "trajectories.npy", scene.poses[:3])
    mask = circle_mask(RAW_CAMERA.shape, FIELD_STOP)
    cv2.imwrite(str(base / "undistorted_mask.bmp"), np.where(mask, 255, 0).astype(np.uint8))
    trimesh.creation.box(extents=(10.0, 20.0, 30.0)).export(base / "seg.ply")
    cam = Camera(96, 80, RAW_CAMERA.K)
    args = {
        "intrinsics": f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}",
        "preop_data": {"base_dir": "preop", "seg": "seg.ply"},
        "steps": 0,
    }
    (root / "input.json").write_text(json.dumps(args))
    return args


def _with(root: Path, args: dict[str, Any], **part: Any) -> Path:
    changed = json.loads(json.dumps(args))
    changed["preop_data"].update(part)
    (root / "input.json").write_text(json.dumps(changed))
    return root / "input.json"


def test_reference_manifest_may_not_name_a_file_outside_its_folder(scene, tmp_path) -> None:
    root = tmp_path / "ds"
    args = _reference_dataset(root, scene)
    secret = tmp_path / "secret.ply"
    secret.write_text("root:x:0:0:secret\n")
    out = tmp_path / "out"
    for where in ("../../secret.ply", str(secret)):
        with pytest.raises(OutsideManifestError) as info:
            import_reference(_with(root, args, seg=where), out)
        assert info.value.source == str(root / "input.json")
        assert "preop_data.seg" in info.value.problem or "preop.seg" in info.value.problem
        assert "--allow-outside-manifest" in info.value.problem
    # A link inside the folder that points out is followed before the check.
    (root / "preop" / "link.ply").symlink_to(secret)
    with pytest.raises(OutsideManifestError, match="outside the manifest's folder"):
        import_reference(_with(root, args, seg="link.ply"), out)
    # Poses and base folders likewise.
    np.save(tmp_path / "traj.npy", scene.poses[:3])
    with pytest.raises(OutsideManifestError, match=r"preop\.poses names '\.\./\.\./traj\.npy'"):
        import_reference(_with(root, args, poses="../../traj.npy"), out)
    with pytest.raises(OutsideManifestError, match=r"preop\.base_dir"):
        import_reference(_with(root, args, base_dir="/etc"), out)
    # An image inside the accepted folder that links out.
    (root / "preop" / "images" / "000001.jpg").unlink()
    (root / "preop" / "images" / "000001.jpg").symlink_to(tmp_path / "elsewhere.jpg")
    cv2.imwrite(str(tmp_path / "elsewhere.jpg"), scene.raw_rgb[1])
    with pytest.raises(OutsideManifestError, match=r"000001\.jpg"):
        import_reference(_with(root, args), out)
    assert not out.exists()
    # Allowed explicitly, the file is still read as its kind: the "mesh" is not one.
    with pytest.raises(
        InvalidInputError,
        match=r"secret\.ply: .*not a readable preop\.seg mesh|secret\.ply: .*no triangle",
    ):
        import_reference(_with(root, args, seg=str(secret)), out, allow_outside_manifest=True)
    assert not out.exists()
    result = import_reference(
        _with(root, args, poses="../../traj.npy"), out, allow_outside_manifest=True
    )
    assert result.parts[0].num_frames == 3
    assert secret.read_text() not in "".join(
        p.read_text(errors="replace") for p in out.rglob("*") if p.is_file() and p.suffix != ".png"
    )


def test_reference_seg_that_is_not_a_mesh_is_refused_not_copied(scene, tmp_path) -> None:
    root = tmp_path / "ds"
    args = _reference_dataset(root, scene)
    (root / "preop" / "notes.ply").write_text("patient name: Jane Doe\n")
    with pytest.raises(InvalidInputError, match=r"notes\.ply: not a readable preop\.seg mesh"):
        import_reference(_with(root, args, seg="notes.ply"), tmp_path / "out")
    (root / "preop" / "notes.txt").write_text("patient name: Jane Doe\n")
    with pytest.raises(InvalidInputError, match=r"notes\.txt: preop\.seg mesh must be one of"):
        import_reference(_with(root, args, seg="notes.txt"), tmp_path / "out")
    (root / "preop" / "poses.bin").write_bytes(b"\x00" * 64)
    with pytest.raises(InvalidInputError, match=r"poses\.bin: poses must be a \.npy"):
        import_reference(_with(root, args, poses="poses.bin"), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_cli_names_the_option_and_prints_one_line(scene, tmp_path, capsys) -> None:
    root = tmp_path / "ds"
    args = _reference_dataset(root, scene)
    (tmp_path / "shadow").write_text("secret")
    manifest = _with(root, args, seg="../../../../../../../../" + str(tmp_path / "shadow"))
    rc = chisel_main(["import", "reference", str(manifest), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and "--allow-outside-manifest" in err
    assert "Traceback" not in err and not (tmp_path / "out").exists()
    with pytest.raises(SystemExit):
        chisel_main(["import", "reference", "--help"])
    assert "--allow-outside-manifest" in capsys.readouterr().out


@pytest.fixture(scope="module")
def toy_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_toy_phantom(tmp_path_factory.mktemp("round2") / "toy", n_bites=1)


def test_phantom_json_may_not_name_another_phantoms_mesh(toy_dir: Path, tmp_path: Path) -> None:
    shutil.copytree(toy_dir, tmp_path / "other")
    d = tmp_path / "ph"
    shutil.copytree(toy_dir, d)
    manifest = json.loads((d / "phantom.json").read_text())
    manifest["steps"][1]["mesh"] = "../other/meshes/step_01.ply"
    (d / "phantom.json").write_text(json.dumps(manifest))
    with pytest.raises(OutsideManifestError) as info:
        load_phantom(d)
    assert info.value.source == str(d / "phantom.json")
    assert "steps[1].mesh" in info.value.problem and "--allow-outside-phantom" in info.value.problem
    ph = load_phantom(d, allow_outside=True)
    assert ph.steps[1].mesh_path == (tmp_path / "other" / "meshes" / "step_01.ply").resolve()
    # A link inside the folder to the other phantom is resolved first.
    manifest["steps"][1]["mesh"] = "meshes/link.ply"
    (d / "meshes" / "link.ply").symlink_to(tmp_path / "other" / "meshes" / "step_01.ply")
    (d / "phantom.json").write_text(json.dumps(manifest))
    with pytest.raises(OutsideManifestError):
        load_phantom(d)
    manifest["steps"][1]["mesh"] = "phantom.json"
    (d / "phantom.json").write_text(json.dumps(manifest))
    with pytest.raises(InvalidInputError, match=r"steps\[1\]\.mesh: expected a PLY/STL/OBJ mesh"):
        load_phantom(d)


def test_deep_or_odd_phantom_json_is_one_error(toy_dir: Path, tmp_path: Path) -> None:
    d = tmp_path / "ph"
    shutil.copytree(toy_dir, d)
    for text in ("[" * 100000 + "]" * 100000, '{"seed": NaN}', '{"a": 1e999999}x'):
        (d / "phantom.json").write_text(text)
        with pytest.raises(InvalidInputError) as info:
            load_phantom(d)
        assert info.value.source == str(d / "phantom.json")


# ------------------------------------------- items 2-4: what the sequence reader accepts

CAM = Camera.from_fov(32, 24, 80)


def _small_sequence(path: Path) -> Path:
    from chisel.core.geometry import look_at
    from chisel.io.sequence import Frame, write_sequence

    rng = np.random.default_rng(0)
    frames = [
        Frame(
            i,
            look_at([i, 0.0, 0.0], [i, 0.0, 30.0], up=[0, -1, 0]),
            rng.integers(0, 255, (*CAM.shape, 3), dtype=np.uint8),
            rng.uniform(5, 20, CAM.shape).astype(np.float32),
            rng.random(CAM.shape) > 0.2,
        )
        for i in range(2)
    ]
    return write_sequence(path, CAM, frames)


def test_a_path_that_is_not_utf8_is_read_not_a_segfault(tmp_path: Path) -> None:
    """cv2.imread crashed (exit 139) on such a name: run in a child so a crash is a failure."""
    import subprocess
    import sys

    seq = Path(os.fsdecode(os.fsencode(str(tmp_path)) + b"/seq\xff"))
    _small_sequence(seq)  # the writer, too, must not hand the name to OpenCV
    images = Path(os.fsdecode(os.fsencode(str(tmp_path)) + b"/img\xfe"))
    images.mkdir()
    shutil.copy(seq / "rgb" / "000000.png", images / os.fsdecode(b"f\xff.png"))
    code = (
        "import os, sys\n"
        "from chisel.io.sequence import Sequence\n"
        "from chisel.io.import_common import read_rgb\n"
        "s = Sequence(os.fsdecode(sys.argv[1].encode('latin-1')))\n"
        "assert s.rgb(1).shape == (24, 32, 3) and s.mask(0).any()\n"
        "d = os.fsdecode(sys.argv[2].encode('latin-1'))\n"
        "print(read_rgb(os.path.join(d, os.listdir(d)[0])).shape)\n"
    )
    as_latin = [os.fsencode(str(p)).decode("latin-1") for p in (seq, images)]
    proc = subprocess.run(
        [sys.executable, "-c", code, *as_latin], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "(24, 32, 3)" in proc.stdout


def _jpeg(rgb: np.ndarray, cut: int = 0) -> bytes:
    data = cv2.imencode(".jpg", rgb)[1].tobytes()
    return data[: len(data) - cut] if cut else data


def test_truncated_jpeg_and_grey_masks_in_a_sequence_are_refused(tmp_path: Path) -> None:
    from chisel.io.sequence import Sequence

    seq = _small_sequence(tmp_path / "seq")
    rgb1 = seq / "rgb" / "000001.png"
    rgb1.write_bytes(_jpeg(np.full((24, 32, 3), 90, np.uint8), cut=200))
    s = Sequence(seq)
    with pytest.raises(InvalidInputError, match=r"000001\.png: not a PNG file"):
        s.rgb(1)
    # Truncated PNG bytes name the truncation.
    good = (seq / "rgb" / "000000.png").read_bytes()
    rgb1.write_bytes(good[:-30])
    with pytest.raises(InvalidInputError, match=r"000001\.png: truncated PNG"):
        s.rgb(1)
    # A grey 128 in a mask (a resized or re-encoded mask) was read as "use".
    mask = np.where(np.arange(32)[None, :] < 16, 255, 0).astype(np.uint8).repeat(24, 0)
    mask[3, 3] = 128
    (seq / "mask" / "000000.png").write_bytes(cv2.imencode(".png", mask)[1].tobytes())
    with pytest.raises(InvalidInputError, match=r"000000\.png: mask holds 1 pixel\(s\) .*\[128\]"):
        s.mask(0)
    mask[3, 3] = 255
    (seq / "mask" / "000000.png").write_bytes(cv2.imencode(".png", mask)[1].tobytes())
    np.testing.assert_array_equal(s.mask(0), mask == 255)


def _edit_header(seq: Path, **changes: Any) -> None:
    header = json.loads((seq / "sequence.json").read_text())
    for key, value in changes.items():
        if key.startswith("camera."):
            header["camera"][key.split(".", 1)[1]] = value
        else:
            header[key] = value
    (seq / "sequence.json").write_text(json.dumps(header))


def test_ray_depth_and_skew_are_refused_not_ignored(tmp_path: Path) -> None:
    from chisel.core.errors import CameraError
    from chisel.io.sequence import Sequence, SequenceWriter

    seq = _small_sequence(tmp_path / "seq")
    _edit_header(seq, depth_kind="ray")
    with pytest.raises(InvalidInputError, match=r"sequence\.json: depth_kind is 'ray'; .*'z'"):
        Sequence(seq)
    _edit_header(seq, depth_kind="z")
    K = CAM.K.copy()
    K[0, 1] = 3.0
    _edit_header(seq, **{"camera.K": K.tolist()})
    with pytest.raises(
        CameraError, match=r"sequence\.json: camera matrix has skew K\[0\]\[1\] = 3"
    ):
        Sequence(seq)
    skewed = Camera(32, 24, K)
    with pytest.raises(CameraError, match="skew"), SequenceWriter(tmp_path / "out", skewed):
        pass
    assert not (tmp_path / "out").exists()


def test_the_reader_runs_the_importers_units_and_lens_checks(tmp_path: Path) -> None:
    from chisel.core.errors import CameraError, DepthUnitsError
    from chisel.io.sequence import Sequence

    seq = _small_sequence(tmp_path / "seq")
    # A lens that turns back inside the image (k1 = -0.5 on an 80 degree field).
    _edit_header(seq, **{"camera.dist": [-0.5, 0.0, 0.0, 0.0, 0.0]})
    with pytest.raises(CameraError, match=r"sequence\.json: the distortion model .* turns back"):
        Sequence(seq)
    _edit_header(seq, **{"camera.dist": [0.0] * 5})
    np.save(seq / "depth" / "000001.npy", np.full((24, 32), 0.012, np.float32))
    with pytest.raises(DepthUnitsError, match=r"000001\.npy: median depth is 0\.012.*metres"):
        Sequence(seq).depth_mm(1)


# ------------------------------------------------- item 7: networks with NaN weights


def test_checkpoints_with_nan_weights_are_refused_naming_the_file(tmp_path: Path) -> None:
    import torch
    from test_depth import TINY

    from chisel.depth.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
    from chisel.depth.infer import load_depth_source
    from chisel.depth.network import DepthNet, DepthPredictor

    net = DepthNet(TINY)
    good = save_checkpoint(tmp_path / "good.pt", net)
    payload = torch.load(good, weights_only=True)
    name = next(k for k, v in payload["state_dict"].items() if v.is_floating_point())
    payload["state_dict"][name][...] = float("nan")
    torch.save(payload, tmp_path / "nan.pt")  # as a diverged run wrote it before
    for load in (load_checkpoint, load_depth_source):
        with pytest.raises(CheckpointError) as info:
            load(tmp_path / "nan.pt")
        assert info.value.source == str(tmp_path / "nan.pt")
        assert "hold NaN/inf" in info.value.problem and name in info.value.problem
    # An exported TorchScript model likewise.
    with torch.no_grad():
        dict(net.named_parameters())[name].fill_(float("nan"))
    torch.jit.save(torch.jit.script(DepthPredictor(net).eval()), str(tmp_path / "nan.ts"))
    with pytest.raises(CheckpointError, match=r"nan\.ts: 1 weight tensor\(s\) hold NaN/inf"):
        load_depth_source(tmp_path / "nan.ts")
    # And such a network is not saved in the first place.
    with pytest.raises(CheckpointError, match=r"bad\.pt: refusing to save .*NaN/inf"):
        save_checkpoint(tmp_path / "bad.pt", net)
    assert not (tmp_path / "bad.pt").exists()


def test_diverging_finetune_stops_with_an_error_and_keeps_the_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from test_depth import TINY, make_sequence

    from chisel.depth.checkpoint import save_checkpoint
    from chisel.depth.network import DepthNet

    seq = make_sequence(tmp_path / "s", 1000, frames=4, with_mask=False)
    parent = save_checkpoint(tmp_path / "parent.pt", DepthNet(TINY))
    out = tmp_path / "tuned.pt"
    out.write_bytes(b"an earlier fine-tuned checkpoint")
    argv = ["depth", "finetune", "--checkpoint", str(parent), "--sequence", str(seq)]
    argv += ["--out", str(out), "--epochs", "2", "--batch-size", "2", "--threads", "1"]
    rc = chisel_main([*argv, "--lr", "1e6", "--no-augment"])
    err = capsys.readouterr().err
    assert rc == 1 and "training diverged at epoch 1" in err and "Traceback" not in err
    assert out.read_bytes() == b"an earlier fine-tuned checkpoint"


# ------------------------------------------------------ item 6: bounds on model fields


def _model_npz(path: Path, **fields: Any) -> Path:
    base: dict[str, Any] = {
        "format": np.array("endoscopic-chisel/model"),
        "version": np.array(1),
        "tsdf": np.zeros((4, 4, 4), np.float32),
        "weight": np.zeros((4, 4, 4), np.float32),
        "T_world_from_voxel": np.diag([0.5, 0.5, 0.5, 1.0]),
        "voxel_size_mm": np.array(0.5),
        "trunc_mm": np.array(2.0),
        "step": np.array(0),
    }
    base.update(fields)
    np.savez(path, **base)
    return path


def _placed(origin_mm: float, voxel_mm: float) -> np.ndarray:
    T = np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    T[:3, 3] = origin_mm
    return T


@pytest.mark.parametrize(
    ("fields", "problem"),
    [
        ({"T_world_from_voxel": _placed(1e300, 0.5)}, "T_world_from_voxel: the grid spans"),
        (
            {
                "T_world_from_voxel": _placed(0.0, 1e-300),
                "voxel_size_mm": np.array(1e-300),
                "trunc_mm": np.array(1e-300),
            },
            "voxel_size_mm: must be within [0.001, 1000.0] mm, got 1e-300",
        ),
        (
            {
                "T_world_from_voxel": _placed(0.0, 1e5),
                "voxel_size_mm": np.array(1e5),
                "trunc_mm": np.array(1e5),
            },
            "voxel_size_mm: must be within",
        ),
        ({"trunc_mm": np.array(1e200)}, "trunc_mm: must be at most 10000.0 mm"),
    ],
)
def test_model_fields_out_of_bounds_are_refused(
    tmp_path: Path, fields: dict[str, Any], problem: str
) -> None:
    from chisel.model import TsdfModel

    path = _model_npz(tmp_path / "m.npz", **fields)
    with pytest.raises(InvalidInputError) as info:
        TsdfModel.load(path)
    assert info.value.source == str(path) and problem in info.value.problem


def _npy_header_only(shape: tuple[int, ...]) -> bytes:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f4", "fortran_order": False, "shape": shape}
    )
    return buf.getvalue()


def test_arrays_declared_past_the_limits_are_refused_before_allocation(tmp_path: Path) -> None:
    """A few bytes can declare a terabyte array: refused from the header, never allocated."""
    import zipfile

    from chisel.core.errors import ResourceLimitError
    from chisel.io.import_common import load_npy
    from chisel.model import TsdfModel

    bomb = tmp_path / "m.npz"
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("tsdf.npy", _npy_header_only((100000, 100000, 100000)))
    with pytest.raises(ResourceLimitError, match=r"m\.npz member tsdf\.npy: array of shape"):
        TsdfModel.load(bomb)
    short = tmp_path / "d.npy"
    short.write_bytes(_npy_header_only((4000, 4000)))  # declares 64 MB, holds none
    with pytest.raises(InvalidInputError, match=r"d\.npy: array of shape .* file holds 0"):
        load_npy(short)
    # A PNG header declaring 100000 x 100000 pixels.
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", 100000, 100000, 8, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    png = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk
    png += struct.pack(">I", zlib.crc32(chunk)) + b"\x00\x00\x00\x00IEND\xaeB`\x82"
    (tmp_path / "huge.png").write_bytes(png)
    from chisel.io.import_common import read_rgb

    with pytest.raises(ResourceLimitError, match=r"huge\.png: image declares 100000x100000"):
        read_rgb(tmp_path / "huge.png")


# --------------------------------------- a depth source whose frames are not the sequence's


def test_depth_source_of_other_frames_is_refused(tmp_path: Path) -> None:
    from chisel.depth_source import depth_source_from_spec
    from chisel.io.sequence import Sequence

    seq = _small_sequence(tmp_path / "seq")
    same = shutil.copytree(seq, tmp_path / "same")
    depth_source_from_spec(f"sequence:{same}", Sequence(seq))  # its own frames: fine
    other = shutil.copytree(seq, tmp_path / "other_poses")
    poses = np.loadtxt(other / "poses.txt")
    poses[1, 3] += 2.0  # frame 1 moved 2 mm
    np.savetxt(other / "poses.txt", poses)
    with pytest.raises(
        InvalidInputError, match=r"other_poses/poses\.txt: 1 pose\(s\) differ .*frame 1, by 2"
    ):
        depth_source_from_spec(f"sequence:{other}", Sequence(seq))
    cam = shutil.copytree(seq, tmp_path / "other_camera")
    _edit_header(cam, **{"camera.K": (CAM.K * [[1.1], [1.1], [1.0]]).tolist()})
    with pytest.raises(
        InvalidInputError, match=r"other_camera/sequence\.json: depth-source camera"
    ):
        depth_source_from_spec(f"sequence:{cam}", Sequence(seq))
