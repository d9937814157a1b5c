"""Bad input, round two (issue 17): each case is refused with one of the project's errors
naming the file, and earlier outputs are kept."""

from __future__ import annotations

import json
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
from chisel.io.importers import import_reference
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
