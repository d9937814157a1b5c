"""What a CT-built model holds of a surface (chisel.build.voxel_copies), and the change-aware
network's training on it (``chisel depth train --kind change-aware --prior-surface model``).

Truth is analytic: a sphere's radius, flat faces at known depths, a window's far wall.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from chisel.build import voxel_copies
from chisel.cli import main as chisel_main
from chisel.core.geometry import Camera
from chisel.core.raycast import MeshRaycaster
from chisel.depth.change_aware import ChangeNet, ChangeNetConfig, save_change_checkpoint
from chisel.io.sequence import Frame, SequenceWriter

W, H = 32, 24


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi_a - lo_a, transform=_translation((lo_a + hi_a) / 2))


def _translation(t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def _walls(window: bool) -> trimesh.Trimesh:
    """Tissue: a wall at z 20-24 and one at z 30-34 (x, y in -15..15); ``window`` cuts a
    10 x 10 mm hole through the near wall (manifold3d keeps the faces it does not touch)."""
    near = _box((-15, -15, 20), (15, 15, 24))
    if window:
        near = near.difference(_box((-5, -5, 19), (5, 5, 25)))
    return trimesh.util.concatenate([near, _box((-15, -15, 30), (15, 15, 34))])


def test_a_sphere_is_copied_onto_its_radius() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=6.0)
    (copy,) = voxel_copies([sphere], np.full(3, -9.0), np.full(3, 9.0), 0.5, 2.0)
    r = np.linalg.norm(copy.vertices, axis=1)
    assert len(copy.faces) > 1000
    assert np.abs(r - 6.0).max() < 0.03


def test_successive_steps_equal_each_step_copied_alone() -> None:
    """Only the window's box is computed afresh at step 1; the result is the same mesh as
    the step copied on its own grid, and a step without change repeats its copy."""
    steps = [_walls(False), _walls(True), _walls(True)]
    lo, hi = np.array([-18.0, -18, 16]), np.array([18.0, 18, 37])
    chained = voxel_copies(steps, lo, hi)
    alone = voxel_copies([steps[1]], lo, hi)[0]
    assert np.array_equal(chained[1].vertices, alone.vertices)
    assert np.array_equal(chained[1].faces, alone.faces)
    assert chained[2] is chained[1]
    # Flat faces are linear signed distances: the copy reproduces their depths.
    cam = Camera(W, H, np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]]))
    before, after = (
        MeshRaycaster(m.vertices, m.faces).render_depth(cam, np.eye(4)) for m in chained[:2]
    )
    assert before[H // 2, W // 2] == pytest.approx(20.0, abs=1e-3)
    assert after[H // 2, W // 2] == pytest.approx(30.0, abs=1e-3)


def _dataset(root: Path, cam: Camera) -> Path:
    """A two-step dataset as ``python -m sim dataset`` writes it: the preop sweep and the
    window's step, frames at the true pose, tracked poses 0.2 mm off."""
    data = root / "data"
    phantom = data / "phantoms" / "seed_1000"
    (phantom / "meshes").mkdir(parents=True)
    meshes = [_walls(False), _walls(True)]
    for k, mesh in enumerate(meshes):
        mesh.export(phantom / "meshes" / f"step_{k:02d}.ply")
    steps = [{"step": k, "mesh": f"meshes/step_{k:02d}.ply"} for k in (0, 1)]
    (phantom / "phantom.json").write_text(json.dumps({"steps": steps}))
    entries = []
    for k, mesh in enumerate(meshes):
        rc = MeshRaycaster(mesh.vertices, mesh.faces)
        name = f"seed_1000/step_{k:02d}"
        with SequenceWriter(data / name, cam, meta={"pose_units_checked": False}) as w:
            for i in range(3):
                true = np.eye(4)
                true[0, 3] = i - 1.0
                tracked = true.copy()
                tracked[2, 3] += 0.2
                rgb = np.full((H, W, 3), 60 + 40 * i, np.uint8)
                depth = rc.render_depth(cam, true)
                w.add(Frame(i, tracked, rgb=rgb, depth_mm=depth, T_world_from_cam_true=true))
        entries.append({"path": name, "phantom_seed": 1000, "kind": "step", "step": k})
    (data / "dataset.json").write_text(json.dumps({"sequences": entries}))
    return data


def test_cli_trains_on_the_model_surface_from_a_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cam = Camera(W, H, np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]]))
    data = _dataset(tmp_path, cam)
    init = tmp_path / "init.pt"
    save_change_checkpoint(init, ChangeNet(ChangeNetConfig(widths=(4, 8))), {"kind": "train"})
    out = tmp_path / "ck.pt"
    argv = ["depth", "train", "--kind", "change-aware", "--data", str(data), "--out", str(out)]
    opts = ["--prior-surface", "model", "--init", str(init), "--steps", "2", "--val-fraction", "0"]
    assert chisel_main([*argv, *opts, "--batch-size", "2", "--threads", "1"]) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    info = sidecar["info"]
    assert sidecar["config"]["widths"] == [4, 8]  # the network of --init, not the default
    assert info["prior_surface"] == "model" and info["init"] == str(init)
    assert "--prior-surface model" in info["command"] and info["num_train_frames"] == 6
    # --init keeps its network's widths; both options belong to the change-aware kind.
    capsys.readouterr()
    assert chisel_main([*argv, *opts, "--widths", "8,16"]) == 1
    assert "--widths" in capsys.readouterr().err
    mono = ["depth", "train", "--data", str(data), "--out", str(tmp_path / "m.pt")]
    assert chisel_main([*mono, "--prior-surface", "model"]) == 1
    assert "--prior-surface: is an option of --kind change-aware only" in capsys.readouterr().err
