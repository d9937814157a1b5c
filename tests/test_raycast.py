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
