"""UpdateConfig.hand_eye_estimator = "joint": one camera-side correction F solved from
every frame's points at once (chisel.icp.icp_hand_eye), against analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
import test_updater_scenes as sc
from scipy.spatial.transform import Rotation

from chisel.batch import update_step
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import rotation_angle_deg
from chisel.depth_source import CallableDepth
from chisel.icp import SurfaceIndex, icp_hand_eye, icp_similarity
from chisel.registration import RegistrationConfig, robust_mean_transform
from chisel.update_config import UpdateConfig

F_TRUE = np.eye(4)
F_TRUE[:3, :3] = Rotation.from_rotvec(np.deg2rad(0.8) * np.array([0.6, -0.64, 0.48])).as_matrix()
F_TRUE[:3, 3] = [0.4, -0.3, 0.5]


def _corner() -> SurfaceIndex:
    """The three walls x = 0, y = 0, z = 0 of a box corner, 40 mm, every 0.25 mm."""
    g = np.arange(0.0, 40.0, 0.25)
    a, b = (x.ravel() for x in np.meshgrid(g, g))
    z = np.zeros_like(a)
    walls = [np.stack(p, axis=1) for p in ((z, a, b), (a, z, b), (a, b, z))]
    normals = [np.tile(n, (len(a), 1)) for n in np.eye(3)]
    return SurfaceIndex(np.concatenate(walls), np.concatenate(normals).astype(np.float64))


def _looking_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def _seen(points: np.ndarray, T_tracked: np.ndarray) -> np.ndarray:
    """About 800 of ``points`` in the true camera's 30 deg half-angle cone, in its frame
    (mm): the tracked pose is off by F_TRUE (``T_true = T_tracked F_TRUE``)."""
    true_cam = T_tracked @ F_TRUE
    pc = (points - true_cam[:3, 3]) @ true_cam[:3, :3]
    seen = (pc[:, 2] > 1.0) & (np.hypot(pc[:, 0], pc[:, 1]) < 0.58 * pc[:, 2])
    return pc[seen][:: max(1, int(seen.sum()) // 800)]


def _one_wall_views(surface: SurfaceIndex) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Nine tracked poses, three on each wall, looking at it 20-35 deg off square and
    rolled apart, and each true camera's points of its wall within a 30 deg half-angle
    cone (camera mm): every frame sees one plane, which fixes 3 of F's 6 degrees of
    freedom, each frame other ones."""
    clouds, tracked = [], []
    for axis in range(3):
        for k in range(3):
            target = np.full(3, 20.0)
            target[axis] = 0.0
            tilt, azimuth = np.deg2rad(20.0 + 7.5 * k), 2.1 * k + axis
            direction = np.zeros(3)  # from the target to the eye
            direction[axis] = np.cos(tilt)
            direction[(axis + 1) % 3] = np.sin(tilt) * np.cos(azimuth)
            direction[(axis + 2) % 3] = np.sin(tilt) * np.sin(azimuth)
            up = np.eye(3)[(axis + 1 + k) % 3]
            T = _looking_at(target + 16.0 * direction, target, up)
            clouds.append(_seen(surface.points[surface.normals[:, axis] == 1.0], T))
            tracked.append(T)
    return clouds, tracked


def test_the_joint_solve_finds_a_correction_no_single_view_determines() -> None:
    surface = _corner()
    clouds, tracked = _one_wall_views(surface)
    cfg = RegistrationConfig()
    F, scales, fitness = icp_hand_eye(clouds, tracked, surface, np.eye(4), cfg, False)
    left = np.linalg.inv(F_TRUE) @ F
    assert rotation_angle_deg(left[:3, :3]) < 0.02
    assert np.linalg.norm(left[:3, 3]) < 0.02
    assert np.all(scales == 1.0) and fitness > 0.99
    # A view of one wall fixes 3 of F's 6 degrees of freedom; the median of the frames'
    # own corrections leaves the rest where the tracker put them.
    Fs = []
    for pc, T in zip(clouds, tracked, strict=True):
        world = pc @ T[:3, :3].T + T[:3, 3]
        sim = icp_similarity(world, T[:3, 3], surface, np.eye(4), cfg, estimate_scale=False)
        Fs.append(np.linalg.inv(T) @ sim.T_model_from_est @ T)
    off = np.linalg.inv(F_TRUE) @ robust_mean_transform(Fs)
    assert np.linalg.norm(off[:3, 3]) > 0.2


def _corner_views(surface: SurfaceIndex) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Eight tracked poses inside the box looking into its corner (two or three walls in
    view), and each true camera's points within a 30 deg half-angle cone (camera mm)."""
    rng = np.random.default_rng(4)
    clouds, tracked = [], []
    for _ in range(8):
        eye = rng.uniform(12.0, 20.0, 3)
        T = _looking_at(eye, rng.uniform(2.0, 6.0, 3), rng.normal(size=3))
        clouds.append(_seen(surface.points, T))
        tracked.append(T)
    return clouds, tracked


def test_each_frame_keeps_a_scale_of_its_own() -> None:
    surface = _corner()
    clouds, tracked = _corner_views(surface)
    # A relative estimate: each frame's points off by a scale of its own (3-10 %).
    truth = np.linspace(1.03, 1.10, len(clouds))
    scaled = [pc / s for pc, s in zip(clouds, truth, strict=True)]
    F, scales, _ = icp_hand_eye(scaled, tracked, surface, np.eye(4), RegistrationConfig(), True)
    left = np.linalg.inv(F_TRUE) @ F
    assert rotation_angle_deg(left[:3, :3]) < 0.02
    assert np.linalg.norm(left[:3, 3]) < 0.02
    np.testing.assert_allclose(scales, truth, rtol=1e-3)


def test_a_step_reports_the_joint_estimator_and_still_undoes_the_error() -> None:
    s = sc.hand_eye_step()
    relative = CallableDepth(lambda f: f.depth_mm * 0.037)
    cfg = UpdateConfig(hand_eye_estimator="joint")
    _, rep = update_step(s["model"], s["cam"], s["frames"], relative, cfg)
    he = rep.sequence_registration["hand_eye"]
    assert he["estimator"] == "joint" and "rejected" not in rep.sequence_registration
    F = np.array(he["T_cam_from_corrected_cam"])
    assert rotation_angle_deg(F @ s["E"]) < 0.2


def test_an_unknown_estimator_is_named() -> None:
    with pytest.raises(InvalidInputError, match="hand_eye_estimator"):
        UpdateConfig(hand_eye_estimator="mean")  # type: ignore[arg-type]
