"""Frame-to-frame odometry and its fusion with the tracker: the measured motion of two
textured frames against the motion they were rendered with, and the pose graph against
what least squares must give in closed form (exact motions average the jitter out;
motions equal to the tracked ones move nothing)."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_shading import _bumpy_surface

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, invert_rigid
from chisel.core.raycast import MeshRaycaster
from chisel.odometry import OdometryConfig, frame_motions, fuse_poses
from chisel.shading import DISPLAY_GAMMA

RNG_SEED = 11


def _rigid(t_mm: np.ndarray, rotvec_deg: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = t_mm
    return T


def _errors(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(translation mm, rotation deg) of A^-1 B."""
    E = invert_rigid(A) @ B
    return float(np.linalg.norm(E[:3, 3])), float(
        np.degrees(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()))
    )


def _textured_frame(mesh: trimesh.Trimesh, cam: Camera, T: np.ndarray) -> np.ndarray:
    """8-bit frame of a matte, textured surface lit from the lens, traced with trimesh
    along the camera's own (distorted) rays: mucosa-like albedo blobs times cos / r^2."""
    d_cam = cam.rays_cam().reshape(-1, 3)
    d_world = d_cam @ T[:3, :3].T
    origins = np.broadcast_to(T[:3, 3], d_world.shape)
    loc, ray, tri = mesh.ray.intersects_location(origins, d_world, multiple_hits=False)
    v = loc - T[:3, 3]
    r = np.linalg.norm(v, axis=1)
    cos = np.abs((mesh.face_normals[tri] * v).sum(1)) / r
    x, y = loc[:, 0], loc[:, 1]
    albedo = 0.55 + 0.25 * np.sin(2.1 * x + 1.3 * np.sin(1.7 * y)) * np.cos(1.9 * y - 0.7 * x)
    radiance = np.zeros(len(d_cam))
    radiance[ray] = albedo * cos / r**2
    linear = radiance / radiance.max()
    rgb = (255 * linear ** (1 / DISPLAY_GAMMA)).reshape(cam.height, cam.width, 1)
    return np.round(np.repeat(rgb, 3, -1)).astype(np.uint8)


@pytest.mark.parametrize("distorted", [False, True])
def test_the_motion_between_two_textured_frames_is_measured(distorted: bool) -> None:
    mesh = _bumpy_surface()  # a bumpy wall ~14 mm ahead
    dist = np.array([-0.18, 0.04, 0.0004, -0.0003, 0.0]) if distorted else None
    cam = Camera.from_fov(192, 160, 80, dist=dist)
    T0 = np.eye(4)
    T1 = T0 @ _rigid(np.array([0.3, -0.2, 0.1]), np.array([0.2, -0.1, 0.15]))
    # The tracker's view of them: jitter of the benchmark's size in each.
    T0_tr = T0 @ _rigid(np.array([0.2, -0.25, 0.1]), np.array([0.1, 0.05, -0.1]))
    T1_tr = T1 @ _rigid(np.array([-0.25, 0.15, -0.1]), np.array([-0.1, 0.1, 0.05]))
    rc = MeshRaycaster(mesh.vertices, mesh.faces)
    # As in the updater: each frame's depth is the model rendered at its tracked pose.
    depths = [rc.render_depth(cam, T) for T in (T0_tr, T1_tr)]
    rgbs = [_textured_frame(mesh, cam, T) for T in (T0, T1)]
    motions = frame_motions(rgbs, [None, None], depths, [T0_tr, T1_tr], cam)
    true_motion = invert_rigid(T0) @ T1
    # Judged by where it moves the wall's points in the image (what two frames determine:
    # a small turn and a sideways shift move the image nearly alike, so each alone is
    # known less well: 0.04-0.08 mm and 0.14-0.27 deg here).
    D0 = rc.render_depth(cam, T0)
    v, u = np.nonzero(np.isfinite(D0))
    P = cam.backproject(D0)[v, u]

    def flow_error_px(M: np.ndarray) -> float:
        A, B = invert_rigid(true_motion), invert_rigid(M)
        ua, _ = cam.project(P @ A[:3, :3].T + A[:3, 3])
        ub, _ = cam.project(P @ B[:3, :3].T + B[:3, 3])
        return float(np.median(np.linalg.norm(ua - ub, axis=1)))

    assert flow_error_px(invert_rigid(T0_tr) @ T1_tr) > 5.0
    assert flow_error_px(motions[0]) < 0.3, flow_error_px(motions[0])
    t_err, r_err = _errors(true_motion, motions[0])
    assert t_err < 0.12 and r_err < 0.4, (t_err, r_err)


def _path(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """A scope moving ~0.3 mm and ~0.2 deg between frames."""
    out = [np.eye(4)]
    for _ in range(n - 1):
        out.append(out[-1] @ _rigid(rng.normal(0.0, 0.3, 3), rng.normal(0.0, 0.2, 3)))
    return out


def _jittered(true: list[np.ndarray], rng: np.random.Generator) -> list[np.ndarray]:
    return [T @ _rigid(rng.normal(0.0, 0.2, 3), rng.normal(0.0, 0.1, 3)) for T in true]


def test_exact_motions_average_the_jitter_out() -> None:
    # With motions known exactly, least squares puts every frame at its true pose moved by
    # the mean of the frames' jitters (carried along the path): of n independent jitters,
    # about 1 / sqrt(n) of one.
    rng = np.random.default_rng(RNG_SEED)
    n = 40
    true = _path(n, rng)
    tracked = _jittered(true, rng)
    motions = {i: invert_rigid(true[i]) @ true[i + 1] for i in range(n - 1)}
    cfg = OdometryConfig(odometry_sigma_mm=1e-4, odometry_sigma_deg=1e-4)
    fused, used = fuse_poses(tracked, motions, cfg)
    assert used == n - 1
    before = np.mean([_errors(a, b)[0] for a, b in zip(true, tracked, strict=True)])
    after = np.mean([_errors(a, b)[0] for a, b in zip(true, fused, strict=True)])
    assert before > 0.25
    assert after < 0.3 * before, (before, after)
    # ... and the frames' relative poses are the motions.
    for i in range(n - 1):
        t, r = _errors(motions[i], invert_rigid(fused[i]) @ fused[i + 1])
        assert t < 1e-3 and r < 1e-3


def test_motions_equal_to_the_tracked_ones_move_nothing() -> None:
    # Zero residual everywhere at x = 0: the least-squares optimum is the tracked poses.
    rng = np.random.default_rng(RNG_SEED + 1)
    tracked = _jittered(_path(12, rng), rng)
    motions = {i: invert_rigid(tracked[i]) @ tracked[i + 1] for i in range(11)}
    fused, used = fuse_poses(tracked, motions, OdometryConfig())
    assert used == 11
    for a, b in zip(tracked, fused, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_a_failed_odometry_is_left_out() -> None:
    rng = np.random.default_rng(RNG_SEED + 2)
    true = _path(10, rng)
    tracked = _jittered(true, rng)
    motions = {i: invert_rigid(true[i]) @ true[i + 1] for i in range(9)}
    motions[4] = motions[4] @ _rigid(np.array([5.0, 0.0, 0.0]), np.zeros(3))  # diverged
    fused, used = fuse_poses(tracked, motions, OdometryConfig())
    assert used == 8
    # without the outlier every frame still moves toward the truth on average
    before = np.mean([_errors(a, b)[0] for a, b in zip(true, tracked, strict=True)])
    after = np.mean([_errors(a, b)[0] for a, b in zip(true, fused, strict=True)])
    assert after < before
    same, none_used = fuse_poses(tracked, {}, OdometryConfig())
    assert none_used == 0 and all(np.array_equal(a, b) for a, b in zip(tracked, same, strict=True))


def test_the_config_names_a_bad_value() -> None:
    with pytest.raises(InvalidInputError, match="odometry.tracker_jitter_mm"):
        OdometryConfig(tracker_jitter_mm=0.0)
    with pytest.raises(InvalidInputError, match="odometry.odometry_gate"):
        OdometryConfig(odometry_gate=-1.0)
    with pytest.raises(InvalidInputError, match="fuse_poses"):
        fuse_poses([np.eye(4), np.eye(4)], {1: np.eye(4)}, OdometryConfig())


def test_a_step_reports_what_the_odometry_did() -> None:
    from test_shading import _frame_at  # noqa: PLC0415
    from test_updater_scenes import camera, poses, preop_model, tissue_mesh  # noqa: PLC0415

    from chisel.batch import plan_step  # noqa: PLC0415
    from chisel.depth_source import GroundTruthDepth  # noqa: PLC0415
    from chisel.io.sequence import Frame  # noqa: PLC0415
    from chisel.shading import ShadingConfig  # noqa: PLC0415
    from chisel.update_config import UpdateConfig  # noqa: PLC0415

    tissue = tissue_mesh()
    cam = camera(96, 80)
    model = preop_model(tissue, cam)
    frames = [
        Frame(i, T, np.round(_frame_at(tissue, cam, T)).astype(np.uint8),
              np.full(cam.shape, 20.0, np.float32))
        for i, T in enumerate(poses(4, seed=5))
    ]  # fmt: skip
    cfg = UpdateConfig(register=False, odometry=OdometryConfig(smooth_by_odometry=True))
    plan = plan_step(model, cam, frames, GroundTruthDepth(), cfg)
    assert plan.pose_correction is not None and plan.pose_correction["by"] == "odometry"
    assert plan.pose_correction["odometry"]["pairs"] == 3
    both = replace(cfg, shading=ShadingConfig(align_by_shading=True))
    plan = plan_step(model, cam, frames, GroundTruthDepth(), both)
    assert plan.pose_correction is not None
    assert plan.pose_correction["by"] in ("odometry+shading", "odometry")
    off = plan_step(model, cam, frames, GroundTruthDepth(), UpdateConfig(register=False))
    assert off.pose_correction is None
    assert all(
        np.array_equal(inp.T_world_from_cam, f.T_world_from_cam)
        for inp, f in zip(off.inputs, frames, strict=True)
    )


def test_the_cli_needs_rgb_for_it_and_reports_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json  # noqa: PLC0415

    from test_shading import _frame_at  # noqa: PLC0415
    from test_updater_scenes import camera, poses, preop_model, tissue_mesh  # noqa: PLC0415

    from chisel.cli import main  # noqa: PLC0415
    from chisel.io.sequence import Frame, write_sequence  # noqa: PLC0415

    tissue = tissue_mesh()
    cam = camera(96, 80)
    rc = MeshRaycaster.from_trimesh(tissue)
    frames = [
        Frame(i, T, np.round(_frame_at(tissue, cam, T)).astype(np.uint8),
              rc.render_depth(cam, T))
        for i, T in enumerate(poses(4, seed=5))
    ]  # fmt: skip
    write_sequence(tmp_path / "seq", cam, frames)
    write_sequence(tmp_path / "grey", cam, [replace(f, rgb=None) for f in frames])
    preop_model(tissue, cam).save(tmp_path / "m0.npz")
    common = ["update", "--model", str(tmp_path / "m0.npz"), "--depth-source", "gt",
              "--no-register", "--smooth-by-odometry", "--no-progress"]  # fmt: skip
    assert main([*common, "--sequence", str(tmp_path / "seq"), "--out",
                 str(tmp_path / "m1.npz"), "--report", str(tmp_path / "r.json")]) == 0  # fmt: skip
    correction = json.loads((tmp_path / "r.json").read_text())["pose_correction"]
    assert correction["by"] == "odometry" and correction["odometry"]["pairs"] == 3
    capsys.readouterr()
    assert main([*common, "--sequence", str(tmp_path / "grey"), "--out",
                 str(tmp_path / "m2.npz")]) == 1  # fmt: skip
    err = capsys.readouterr().err
    assert "grey: update.odometry.smooth_by_odometry needs the frames' RGB" in err
    assert not (tmp_path / "m2.npz").exists()
