import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from chisel.core.errors import CameraError, PoseError
from chisel.core.geometry import (
    Camera,
    check_rigid,
    invert_rigid,
    look_at,
    make_transform,
    transform_points,
)


def random_pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_transform(Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 50, 3))


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_invert_round_trip(seed: int) -> None:
    T_world_from_cam = random_pose(seed)
    T_cam_from_world = invert_rigid(T_world_from_cam)
    np.testing.assert_allclose(T_world_from_cam @ T_cam_from_world, np.eye(4), atol=1e-9)
    p = np.random.default_rng(seed).normal(0, 10, (20, 3))
    back = transform_points(T_world_from_cam, transform_points(T_cam_from_world, p))
    np.testing.assert_allclose(back, p, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_project_backproject_round_trip(seed: int) -> None:
    rng = np.random.default_rng(seed)
    dist = np.array([rng.uniform(-0.15, 0.05), rng.uniform(0.0, 0.02), 1e-3, -1e-3, 0.0])
    cam = Camera.from_fov(
        64, 48, float(rng.uniform(60, 80)), (float(rng.uniform(-5, 5)), 2.0), dist
    )
    depth = rng.uniform(3, 40, cam.shape).astype(np.float32)
    pts = cam.backproject(depth)
    uv, z = cam.project(pts)
    u, v = cam.pixel_grid()
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-5)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-5)
    np.testing.assert_allclose(z, depth, rtol=1e-6)


def test_look_at_axes_are_opencv() -> None:
    T = look_at([0, 0, 0], [0, 0, 10], up=[0, -1, 0])
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-12)  # +z forward, +y down
    T = look_at([1, 2, 3], [11, 2, 3], up=[0, 0, 1])
    assert check_rigid(T).shape == (4, 4)
    # image up (-y) should point to world +z
    np.testing.assert_allclose(-T[:3, 1], [0, 0, 1], atol=1e-12)


def test_check_rigid_errors() -> None:
    with pytest.raises(PoseError, match="4x4"):
        check_rigid(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = np.nan
    with pytest.raises(PoseError, match="non-finite"):
        check_rigid(bad)
    scaled = np.eye(4)
    scaled[:3, :3] *= 1.1
    with pytest.raises(PoseError, match="not rigid"):
        check_rigid(scaled)
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(PoseError, match="not rigid"):
        check_rigid(mirror)


def test_camera_errors() -> None:
    with pytest.raises(CameraError):
        Camera(0, 10, np.eye(3))
    with pytest.raises(CameraError):
        Camera(10, 10, np.diag([-1.0, 1.0, 1.0]))
    cam = Camera.from_fov(32, 24, 80)
    with pytest.raises(CameraError, match="32x24"):
        cam.check_image(np.zeros((10, 10)), "img")
    with pytest.raises(CameraError):
        Camera.from_fov(32, 24, 200)


def test_projection_matches_opencv() -> None:
    cam = Camera.from_fov(64, 48, 85, (3.0, -2.0), np.array([-0.25, 0.05, 1e-3, 2e-3, -0.01]))
    pts = np.random.default_rng(1).uniform([-5, -5, 5], [5, 5, 30], (100, 3))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    uv, z = cam.project(pts)
    np.testing.assert_allclose(uv, ref[:, 0, :], atol=1e-9)
    np.testing.assert_allclose(z, pts[:, 2])
