"""Camera paths (clearance, smoothness, seeding), tracked-pose noise, phantom/mesh input checks."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from chisel.core.errors import PoseError
from chisel.core.geometry import invert_rigid, transform_points
from sim.collision import TissueDistance
from sim.config import PathConfig, SimConfig, TrackingConfig
from sim.errors import MeshError, PathError, PathInTissueError, PhantomError
from sim.paths import PathTarget, check_clearance, eval_poses, intraop_path, preop_sweep
from sim.phantom import load_mesh, load_phantom
from sim.pipeline import path_target
from sim.synthetic import toy_meshes, write_toy_phantom
from sim.tracking import handeye_error, pose_error, tracked_poses


@pytest.fixture(scope="module")
def toy(tmp_path_factory: pytest.TempPathFactory):
    d = write_toy_phantom(tmp_path_factory.mktemp("paths") / "toy", n_bites=1)
    ph = load_phantom(d)
    mesh = load_mesh(ph.steps[0].mesh_path)
    return ph, mesh, TissueDistance(mesh)


def _step_sizes(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return pose_error(poses[:-1], poses[1:])


def test_preop_sweep_clear_smooth_and_ends_on_target(toy) -> None:
    ph, _, tissue = toy
    cfg = PathConfig()
    poses = preop_sweep(ph.airway_path_mm, ph.target_center_mm, tissue, 40, cfg)
    assert poses.shape == (40, 4, 4)
    d = tissue.signed_distance(poses[:, :3, 3])
    assert d.min() >= cfg.clearance_mm
    dt, dr = _step_sizes(poses)
    assert dt.max() < 3 * np.median(dt) + 1e-6  # evenly spaced along the airway
    assert dr.max() < 10.0  # no jumps in orientation
    # Early frames look ahead along the tunnel (+x), the last one at the target.
    assert poses[0, :3, 2] @ np.array([1.0, 0.0, 0.0]) > 0.95
    to_target = ph.target_center_mm - poses[-1, :3, 3]
    cos = poses[-1, :3, 2] @ to_target / np.linalg.norm(to_target)
    assert cos > math.cos(math.radians(2.0))


def test_intraop_path_is_clear_seeded_and_views_the_target(toy) -> None:
    ph, _, tissue = toy
    cfg = PathConfig()
    target = path_target(ph)
    a = intraop_path(target, tissue, 70, seed=3, cfg=cfg)
    b = intraop_path(target, tissue, 70, seed=3, cfg=cfg)
    c = intraop_path(target, tissue, 70, seed=4, cfg=cfg)
    assert a.shape == (70, 4, 4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    # Clearance along the whole path, checked densely between frames too.
    check_clearance(a[:, :3, 3], tissue, cfg.clearance_mm, "test")
    seg = np.linspace(a[:-1, :3, 3], a[1:, :3, 3], 5).reshape(-1, 3)
    assert tissue.signed_distance(seg).min() >= cfg.clearance_mm * 0.99
    dt, dr = _step_sizes(a)
    assert dr.max() < 15.0 and dt.max() < 2.0
    # The target centre is in front of the camera and near the optical axis in every frame.
    p_cam = np.einsum(
        "nij,nj->ni", invert_rigid(a), np.append(ph.target_center_mm, 1.0)[None].repeat(70, 0)
    )
    assert (p_cam[:, 2] > 0).all()
    off_axis = np.degrees(np.arctan2(np.linalg.norm(p_cam[:, :2], axis=1), p_cam[:, 2]))
    assert off_axis.max() < 25.0
    dist = np.linalg.norm(a[:, :3, 3] - ph.target_center_mm, axis=1)
    assert dist.min() > 4.0 and dist.max() < 20.0


def test_eval_poses_fixed_and_clear(toy) -> None:
    ph, _, tissue = toy
    target = path_target(ph)
    a = eval_poses(target, tissue, 6, seed=0, cfg=PathConfig())
    np.testing.assert_array_equal(a, eval_poses(target, tissue, 6, seed=0, cfg=PathConfig()))
    assert a.shape == (6, 4, 4)
    assert tissue.signed_distance(a[:, :3, 3]).min() >= 2.0
    # The bitten mesh only lost tissue: the same poses stay clear on it.
    bitten = TissueDistance(load_mesh(ph.steps[1].mesh_path))
    check_clearance(a[:, :3, 3], bitten, 2.0, "eval on step 1")


def test_path_starting_inside_tissue_is_refused(toy) -> None:
    ph, _, tissue = toy
    airway = ph.airway_path_mm.copy()
    airway[0] = [5.0, 12.0, 0.0]  # inside the tissue block, beside the tunnel
    with pytest.raises(PathInTissueError, match="starts inside tissue"):
        preop_sweep(airway, ph.target_center_mm, tissue, 10, PathConfig())
    target = PathTarget(
        ph.target_center_mm, ph.target_normal, ph.roi_box_mm, np.array([5.0, 12.0, 0.0])
    )
    with pytest.raises(PathInTissueError):
        intraop_path(target, tissue, 10, seed=0, cfg=PathConfig())


def test_check_clearance_errors(toy) -> None:
    _, _, tissue = toy
    with pytest.raises(PathError, match="expected >= 2.0 mm"):
        check_clearance(np.array([[20.0, 4.0, 0.0]]), tissue, 2.0, "close")  # 1 mm from the wall
    with pytest.raises(PathInTissueError, match="runs"):
        check_clearance(np.array([[20.0, 0.0, 0.0], [20.0, 10.0, 0.0]]), tissue, 2.0, "inside")


def test_too_tight_space_raises_path_error(toy) -> None:
    ph, _, tissue = toy
    # A normal pointing into the tissue and an approach point too far away: no viewpoint works.
    target = PathTarget(
        ph.target_center_mm, -ph.target_normal, ph.roi_box_mm, np.array([20.0, 0, 0])
    )
    cfg = PathConfig(viewpoint_spread_mm=0.0, max_tries=3)
    with pytest.raises(PathError, match="no collision-free path"):
        intraop_path(target, tissue, 10, seed=0, cfg=cfg)
    with pytest.raises(PathError, match="valid evaluation viewpoints"):
        eval_poses(target, tissue, 3, seed=0, cfg=cfg)


# -- tracking -------------------------------------------------------------------------------


def _true_poses(n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(scale=20.0, size=(n, 3))
    return T


def test_zero_noise_tracking_is_exact() -> None:
    T = _true_poses(20)
    cfg = TrackingConfig(jitter_mm=0, jitter_deg=0, handeye_mm=0, handeye_deg=0)
    np.testing.assert_array_equal(tracked_poses(T, cfg, seed=5), T)


def test_handeye_error_has_exact_magnitude() -> None:
    T = _true_poses(10)
    cfg = TrackingConfig(jitter_mm=0, jitter_deg=0, handeye_mm=0.7, handeye_deg=1.5)
    tr = tracked_poses(T, cfg, seed=1)
    dt, dr = pose_error(T, tr)
    np.testing.assert_allclose(dt, 0.7, atol=1e-9)
    np.testing.assert_allclose(dr, 1.5, atol=1e-6)
    # Constant in the camera frame: T_true^-1 T_tracked is the same E for every frame.
    E = invert_rigid(T) @ tr
    np.testing.assert_allclose(E, np.broadcast_to(handeye_error(cfg, 1), E.shape), atol=1e-9)


def test_jitter_statistics_latency_and_seeding() -> None:
    T = _true_poses(2000)
    cfg = TrackingConfig(jitter_mm=0.3, jitter_deg=0.2, handeye_mm=0, handeye_deg=0)
    tr = tracked_poses(T, cfg, seed=2)
    J = invert_rigid(T) @ tr
    np.testing.assert_allclose(J[:, :3, 3].std(axis=0), 0.3, rtol=0.1)
    rot_deg = pose_error(T, tr)[1]
    # |rotvec| of a 3-D isotropic Gaussian: RMS = sqrt(3) sigma.
    np.testing.assert_allclose(np.sqrt(np.mean(rot_deg**2)), math.sqrt(3) * 0.2, rtol=0.1)
    np.testing.assert_array_equal(tr, tracked_poses(T, cfg, seed=2))
    assert not np.allclose(tr, tracked_poses(T, cfg, seed=3))
    lag = tracked_poses(T[:10], TrackingConfig(0, 0, 0, 0, latency_frames=3), seed=0)
    np.testing.assert_array_equal(lag[3:], T[:7])
    np.testing.assert_array_equal(lag[:3], np.broadcast_to(T[0], (3, 4, 4)))


def test_tracking_refuses_bad_poses() -> None:
    T = _true_poses(3)
    T[1, 0, 0] = np.nan
    with pytest.raises(PoseError, match="non-finite"):
        tracked_poses(T, TrackingConfig(), seed=0)
    T = _true_poses(3)
    T[2, :3, :3] *= 2.0
    with pytest.raises(PoseError, match="not rigid"):
        tracked_poses(T, TrackingConfig(), seed=0)


# -- phantom and mesh input -----------------------------------------------------------------


def test_phantom_and_mesh_errors(tmp_path: Path) -> None:
    with pytest.raises(PhantomError, match="does not exist"):
        load_phantom(tmp_path / "nope")
    with pytest.raises(PhantomError, match="phantom.json is missing"):
        load_phantom(tmp_path)
    d = write_toy_phantom(tmp_path / "toy", n_bites=1)
    manifest = json.loads((d / "phantom.json").read_text())
    bad = dict(manifest, format="something-else")
    (d / "phantom.json").write_text(json.dumps(bad))
    with pytest.raises(PhantomError, match="format"):
        load_phantom(d)
    bad = dict(manifest, roi_box_mm=[[0, 0, 0], [1, 1]])
    (d / "phantom.json").write_text(json.dumps(bad))
    with pytest.raises(PhantomError, match="roi_box_mm"):
        load_phantom(d)
    bad = {k: v for k, v in manifest.items() if k != "airway_path_mm"}
    (d / "phantom.json").write_text(json.dumps(bad))
    with pytest.raises(PhantomError, match="airway_path_mm"):
        load_phantom(d)
    with pytest.raises(MeshError, match="does not exist"):
        load_mesh(tmp_path / "missing.ply")
    open_box = trimesh.creation.box(extents=[10, 10, 10])
    open_box.update_faces(np.arange(len(open_box.faces)) > 1)  # drop two triangles: a hole
    open_box.export(tmp_path / "open.ply")
    with pytest.raises(MeshError, match="not watertight"):
        load_mesh(tmp_path / "open.ply")
    (tmp_path / "garbage.ply").write_text("not a mesh")
    with pytest.raises(MeshError):
        load_mesh(tmp_path / "garbage.ply")


def test_signed_distance_sign_convention() -> None:
    mesh = toy_meshes(0)[0]
    tissue = TissueDistance(mesh)
    d = tissue.signed_distance(np.array([[20.0, 0.0, 0.0], [20.0, 10.0, 0.0], [38.0, 0.0, 0.0]]))
    np.testing.assert_allclose(d, [5.0, -5.0, 9.0], atol=0.05)
    assert SimConfig().paths.clearance_mm == 2.0
    p = tissue.push_to_clearance(np.array([[20.0, 4.0, 0.0]]), 2.0)
    assert tissue.signed_distance(p)[0] >= 2.0
    np.testing.assert_allclose(transform_points(np.eye(4), p), p)
