import numpy as np
import trimesh

from chisel.geometry import Camera, look_at
from chisel.raycast import MeshRaycaster


def test_plane_depth_is_z_depth() -> None:
    # A large plane at z = 20 mm seen head-on: z-depth is 20 everywhere (ray length is not).
    plane = trimesh.creation.box(extents=[400, 400, 1.0])
    plane.apply_translation([0, 0, 20.5])
    cam = Camera.from_fov(64, 48, 80, dist=np.array([-0.1, 0.01, 0, 0, 0]))
    depth = MeshRaycaster.from_trimesh(plane).render_depth(cam, np.eye(4))
    np.testing.assert_allclose(depth, 20.0, atol=1e-4)


def test_sphere_from_inside_and_miss() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=15.0)
    cam = Camera.from_fov(64, 48, 80)
    rc = MeshRaycaster.from_trimesh(sphere)
    T = look_at([0, 0, 0], [0, 0, 1], up=[0, -1, 0])
    pts = cam.backproject(rc.render_depth(cam, T))
    np.testing.assert_allclose(np.linalg.norm(pts, axis=-1), 15.0, atol=0.02)
    T_away = look_at([0, 0, 100], [0, 0, 200], up=[0, -1, 0])
    assert np.isnan(rc.render_depth(cam, T_away)).all()


def test_batched_render_equals_single_renders() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=15.0)
    cam = Camera.from_fov(40, 32, 80, dist=np.array([-0.1, 0.01, 0.001, 0, 0]))
    rc = MeshRaycaster.from_trimesh(sphere)
    rng = np.random.default_rng(0)
    poses = np.stack(
        [look_at(rng.uniform(-5, 5, 3), rng.uniform(-5, 5, 3) + [0, 0, 20], [0, -1, 0])
         for _ in range(5)]
        + [look_at([0, 0, 100], [0, 0, 200], up=[0, -1, 0])]  # misses everything
    )  # fmt: skip
    many = rc.render_depths(cam, poses, batch=4)  # 2 calls, the last one partial
    assert many.shape == (6, 32, 40) and many.dtype == np.float32
    for T, d in zip(poses, many, strict=True):
        np.testing.assert_array_equal(d, rc.render_depth(cam, T))
    assert np.isnan(many[-1]).all() and np.isfinite(many[0]).all()
