"""The updater's CLI on sequence folders and model files, and CT surfaces from NIfTI."""

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import trimesh
from test_updater_scenes import bitten_mesh, camera, poses, preop_poses, tissue_mesh

from chisel.cli import main
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.raycast import MeshRaycaster
from chisel.io.ct import load_ct_surface, surface_from_volume
from chisel.io.sequence import Frame, Sequence, write_sequence
from chisel.model import TsdfModel


def _write(path: Path, mesh: trimesh.Trimesh, P: np.ndarray, scale: float = 1.0) -> Path:
    cam = camera(64, 48)
    rc = MeshRaycaster.from_trimesh(mesh)
    rng = np.random.default_rng(0)
    frames = [
        Frame(
            index=i,
            T_world_from_cam=T,
            rgb=rng.integers(0, 255, (*cam.shape, 3), dtype=np.uint8),
            depth_mm=rc.render_depth(cam, T) * scale,
            T_world_from_cam_true=T,
        )
        for i, T in enumerate(P)
    ]
    return write_sequence(path, cam, frames)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = tmp_path_factory.mktemp("cli")
    tissue = tissue_mesh()
    tissue.export(d / "tissue.ply")
    _write(d / "preop", tissue, preop_poses(20, seed=1))
    _write(d / "step_01", bitten_mesh(tissue), poses(6, seed=2))
    assert main(["build", "--surface", str(d / "tissue.ply"), "--sequence", str(d / "preop"),
                 "--out", str(d / "m0.npz"), "--color", "--no-progress"]) == 0  # fmt: skip
    return {"dir": d}


def test_build_update_mesh_render(files: dict) -> None:
    d = files["dir"]
    m0 = TsdfModel.load(d / "m0.npz")
    assert m0.step == 0 and m0.color is not None and m0.voxel_size_mm == 0.5
    rc = main(["update", "--model", str(d / "m0.npz"), "--sequence", str(d / "step_01"),
               "--out", str(d / "m1.npz"), "--masks", str(d / "masks.npz"), "--no-progress"])  # fmt: skip
    assert rc == 0
    rep = json.loads((d / "m1.json").read_text())
    assert rep["step"] == 1 and rep["frames_used"] == list(range(6))
    assert rep["frames_skipped"] == [] and rep["depth_source"] == "gt"
    assert 0 < rep["changed_pixel_fraction_mean"] < 0.5
    assert rep["sequence_registration"]["ok"]
    f0 = rep["frames"][0]["registration"]
    assert np.asarray(f0["T_model_from_est"]).shape == (4, 4) and f0["fitness"] > 0.5
    with np.load(d / "masks.npz") as z:
        assert z["masks"].shape == (6, 48, 64) and z["masks"].any() and z["used"].all()
        # Each mask is stored with the pose whose image it lies in: the tracked one.
        assert np.array_equal(z["T_world_from_cam"], Sequence(d / "step_01").poses)
    assert TsdfModel.load(d / "m1.npz").step == 1
    assert main(["mesh", "--model", str(d / "m1.npz"), "--out", str(d / "m1.ply")]) == 0
    mesh = trimesh.load(d / "m1.ply")
    assert len(mesh.faces) > 1000
    assert main(["render-depth", "--model", str(d / "m1.npz"), "--sequence", str(d / "step_01"),
                 "--out", str(d / "rd")]) == 0  # fmt: skip
    seq, ref = Sequence(d / "rd"), Sequence(d / "step_01")
    assert seq.has_rgb and seq.has_depth and len(seq) == 6
    err = np.abs(seq.depth_mm(0) - ref.depth_mm(0))
    assert np.nanmedian(err) < 0.1
    assert main(["render-depth", "--mesh", str(d / "tissue.ply"), "--sequence", str(d / "step_01"),
                 "--out", str(d / "rd_ct")]) == 0  # fmt: skip
    # Ablation switches and options parse and run.
    rc = main(["update", "--model", str(d / "m0.npz"), "--sequence", str(d / "step_01"),
               "--out", str(d / "m1_noreg.npz"), "--no-registration", "--threshold-mm", "2.0",
               "--max-frames", "3", "--depth-noise-mm", "0.05", "--no-progress"])  # fmt: skip
    assert rc == 0
    rep = json.loads((d / "m1_noreg.json").read_text())
    assert rep["num_frames"] == 3 and rep["config"]["register"] is False
    assert rep["config"]["change"]["threshold_mm"] == 2.0


def _update(d: Path, seq: Path, out: Path, *extra: str) -> int:
    return main(["update", "--model", str(d / "m0.npz"), "--sequence", str(seq),
                 "--out", str(out), "--no-progress", *extra])  # fmt: skip


def test_failed_update_keeps_previous_files(files: dict, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    d = files["dir"]
    out = tmp_path / "m1.npz"
    out.write_bytes(b"previous step")
    # Depth in metres: refused, nothing written, the old output untouched.
    _write(tmp_path / "metres", bitten_mesh(tissue_mesh()), poses(3, seed=2), scale=1e-3)
    assert _update(d, tmp_path / "metres", out) == 1
    assert "metres" in capsys.readouterr().err
    assert out.read_bytes() == b"previous step" and not (tmp_path / "m1.json").exists()
    # Pose and frame counts differ.
    seq = tmp_path / "short"
    _write(seq, bitten_mesh(tissue_mesh()), poses(3, seed=2))
    lines = (seq / "poses.txt").read_text().splitlines()
    (seq / "poses.txt").write_text("\n".join(lines[:2]) + "\n")
    assert _update(d, seq, out) == 1
    assert "2 poses but sequence.json declares 3 frames" in capsys.readouterr().err
    assert out.read_bytes() == b"previous step"
    # Depth-source specs.
    assert _update(d, d / "step_01", out, "--depth-source", "bogus") == 1
    assert "expected 'gt'" in capsys.readouterr().err
    assert _update(d, d / "step_01", out, "--depth-source", "network:/no/such.pt") == 1
    assert "/no/such.pt" in capsys.readouterr().err
    # A model file from an incompatible version.
    with np.load(d / "m0.npz") as z:
        fields = {k: z[k] for k in z.files}
    fields["version"] = np.array(99)
    with open(tmp_path / "v99.npz", "wb") as fh:
        np.savez(fh, **fields)
    rc = main(["update", "--model", str(tmp_path / "v99.npz"), "--sequence", str(d / "step_01"),
               "--out", str(out), "--no-progress"])  # fmt: skip
    assert rc == 1 and "version 99" in capsys.readouterr().err
    assert out.read_bytes() == b"previous step"


def test_sequence_depth_source(files: dict, tmp_path: Path) -> None:
    d = files["dir"]
    rc = _update(
        d, d / "step_01", tmp_path / "m.npz", "--depth-source", f"sequence:{d / 'step_01'}"
    )
    assert rc == 0
    assert json.loads((tmp_path / "m.json").read_text())["frames_used"] == list(range(6))
    assert (
        _update(d, d / "step_01", tmp_path / "x.npz", "--depth-source", f"sequence:{d / 'preop'}")
        == 1
    )


def _sphere_volume(radius_mm: float, spacing: float, origin: np.ndarray) -> tuple:
    n = 40
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1)
    world = ijk * spacing + origin
    inside = np.linalg.norm(world - (origin + spacing * (n - 1) / 2), axis=-1) < radius_mm
    affine = np.diag([spacing] * 3 + [1.0])
    affine[:3, 3] = origin
    return inside, affine, origin + spacing * (n - 1) / 2


@pytest.mark.parametrize("kind", ["intensity", "label"])
def test_ct_surface_from_nifti(tmp_path: Path, kind: str) -> None:
    origin = np.array([-30.0, 10.0, 5.0])
    air, affine, centre = _sphere_volume(12.0, 0.7, origin)  # an air cavity in tissue
    vol = (
        np.where(air, -1000, 40).astype(np.int16)
        if kind == "intensity"
        else (~air).astype(np.uint8)
    )
    nib.save(nib.Nifti1Image(vol, affine), tmp_path / "ct.nii.gz")
    mesh = load_ct_surface(tmp_path / "ct.nii.gz")
    r = np.linalg.norm(mesh.vertices - centre * [-1, -1, 1], axis=1)  # RAS file -> LPS world
    assert abs(np.median(r) - 12.0) < 0.35 and r.max() - r.min() < 1.5
    assert (
        main(["ct-surface", "--ct", str(tmp_path / "ct.nii.gz"), "--out", str(tmp_path / "s.ply")])
        == 0
    )
    assert len(trimesh.load(tmp_path / "s.ply").faces) == len(mesh.faces)


def test_ct_surface_errors(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match="missing"):
        load_ct_surface(tmp_path / "none.nii.gz")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(InvalidInputError, match="unknown CT segmentation type"):
        load_ct_surface(tmp_path / "x.txt")
    (tmp_path / "bad.nii.gz").write_bytes(b"junk")
    with pytest.raises(InvalidInputError, match="cannot read NIfTI"):
        load_ct_surface(tmp_path / "bad.nii.gz")
    with pytest.raises(EmptyResultError, match="outside the volume's range"):
        surface_from_volume(np.full((5, 5, 5), 40.0), np.eye(4))
    with pytest.raises(InvalidInputError, match="3-D"):
        surface_from_volume(np.zeros((5, 5)), np.eye(4))
