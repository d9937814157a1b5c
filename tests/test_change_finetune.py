"""Per-patient fine-tuning of the change-aware network (`chisel depth finetune --kind
change-aware`): which surface becomes the prior. Tiny images, seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from chisel.cli import cmd_change_aware
from chisel.cli import main as chisel_main
from chisel.core.geometry import Camera
from chisel.depth.change_aware import ChangeNet, ChangeNetConfig, save_change_checkpoint
from chisel.io.sequence import Frame, SequenceWriter
from chisel.model import TsdfModel

H, W = 24, 32
PLANE_Z_MM = 20.25  # between voxel centres: the model's surface is interpolated, not a sample
TRACKED_Z_MM = 0.3  # the tracked camera sits 0.3 mm in front of the true one


def _plane_model(z_mm: float, voxel_mm: float = 0.5, trunc_mm: float = 2.0) -> TsdfModel:
    """TSDF of the plane z = z_mm, tissue behind it (+ in front, toward the camera)."""
    n = (161, 161, 21)
    lo = np.array([-40.0, -40.0, 15.0])
    T = np.diag([voxel_mm] * 3 + [1.0])
    T[:3, 3] = lo
    z = lo[2] + voxel_mm * np.arange(n[2], dtype=np.float64)
    sdf = np.broadcast_to(z_mm - z, n)
    return TsdfModel(
        tsdf=np.clip(sdf / trunc_mm, -1, 1).astype(np.float32),
        weight=np.ones(n, np.float32),
        T_world_from_voxel=T,
        voxel_size_mm=voxel_mm,
        trunc_mm=trunc_mm,
    )


def _scene(tmp_path: Path) -> dict[str, Path]:
    cam = Camera(W, H, np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]]))
    tracked = np.eye(4)
    tracked[2, 3] = TRACKED_Z_MM
    rng = np.random.default_rng(0)
    with SequenceWriter(tmp_path / "preop", cam, meta={"pose_units_checked": False}) as w:
        for i in range(3):
            rgb = rng.integers(60, 200, (H, W, 3), dtype=np.uint8)
            w.add(Frame(i, tracked, rgb=rgb, depth_mm=np.full((H, W), PLANE_Z_MM, np.float32),
                        T_world_from_cam_true=np.eye(4)))  # fmt: skip
    model = tmp_path / "preop_model.npz"
    _plane_model(PLANE_Z_MM).save(model)
    v = np.array([[-50, -50, 20.0], [50, -50, 20.0], [50, 50, 20.0], [-50, 50, 20.0]])
    mesh = tmp_path / "ct_surface.ply"
    trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False).export(mesh)
    ck = save_change_checkpoint(
        tmp_path / "base.pt", ChangeNet(ChangeNetConfig(widths=(8, 12), input_scale=1.0)), {}
    )
    return {"preop": tmp_path / "preop", "model": model, "mesh": mesh, "ck": ck}


def _finetune(paths: dict[str, Path], out: Path, *prior: str) -> int:
    return chisel_main([
        "depth", "finetune", "--kind", "change-aware", "--checkpoint", str(paths["ck"]),
        "--sequence", str(paths["preop"]), *prior, "--steps", "2", "--batch-size", "2",
        "--synthetic-removal", "0", "--threads", "1", "--out", str(out),
    ])  # fmt: skip


@pytest.mark.parametrize(("flag", "surface_z_mm"), [("--model", PLANE_Z_MM), ("--mesh", 20.0)])
def test_prior_is_the_given_surface_at_the_tracked_pose(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, flag: str, surface_z_mm: float
) -> None:
    """--model: the preop model's surface (a TSDF plane between voxel centres); --mesh: the CT
    surface mesh. Either is rendered at the tracked pose, and the target is the same render."""
    paths = _scene(tmp_path)
    seen = {}
    train = cmd_change_aware.train_change_aware

    def spy(pairs, cfg, **kw):  # noqa: ANN001, ANN003, ANN202
        seen["pairs"] = pairs
        return train(pairs, cfg, **kw)

    monkeypatch.setattr(cmd_change_aware, "train_change_aware", spy)
    out = tmp_path / "ft.pt"
    src = paths["model"] if flag == "--model" else paths["mesh"]
    assert _finetune(paths, out, flag, str(src)) == 0
    prior = seen["pairs"].prior_mm.numpy()
    assert prior.shape == (3, H, W) and np.isfinite(prior).all()
    assert np.allclose(prior, surface_z_mm - TRACKED_Z_MM, atol=1e-3)
    assert np.array_equal(seen["pairs"].target_mm.numpy(), prior)
    info = json.loads(out.with_suffix(".json").read_text())["info"]
    assert f"{flag} {src}" in info["command"]
    surface = "model" if flag == "--model" else "ct"
    assert info["target"] == [f"{surface}-render-tracked-pose"]


def test_exactly_one_prior_and_change_aware_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    paths = _scene(tmp_path)
    out = tmp_path / "ft.pt"
    both = ["--model", str(paths["model"]), "--mesh", str(paths["mesh"])]
    for prior in ([], both):
        assert _finetune(paths, out, *prior) == 1
        assert "--mesh/--model: change-aware fine-tuning needs exactly one prior" in (
            capsys.readouterr().err
        )
    mono = ["depth", "finetune", "--checkpoint", str(paths["ck"]), "--sequence",
            str(paths["preop"]), "--model", str(paths["model"]), "--out", str(out)]  # fmt: skip
    assert chisel_main(mono) == 1
    assert "--model: is an option of --kind change-aware only" in capsys.readouterr().err
    assert not out.exists()
