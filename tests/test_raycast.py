import numpy as np
import pytest
import trimesh

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, look_at
from chisel.core.mitsuba_variant import jit_mitsuba
from chisel.core.raycast import MeshRaycaster

BACKENDS = ["open3d", "mitsuba"] if jit_mitsuba() is not None else ["open3d"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_plane_depth_is_z_depth(backend: str) -> None:
    # A large plane at z = 20 mm seen head-on: z-depth is 20 everywhere (ray length is not).
    # Shifted sideways so that no pixel ray runs exactly along the diagonal edge of the
    # front face: Mitsuba's Embree scene is not built robust, so such a ray can slip
    # between the two triangles (test_backends_agree measures how rarely that happens).
    plane = trimesh.creation.box(extents=[400, 400, 1.0])
    plane.apply_translation([0.0137, 0.0071, 20.5])
    cam = Camera.from_fov(64, 48, 80, dist=np.array([-0.1, 0.01, 0, 0, 0]))
    depth = MeshRaycaster.from_trimesh(plane, backend).render_depth(cam, np.eye(4))
    np.testing.assert_allclose(depth, 20.0, atol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sphere_from_inside_and_miss(backend: str) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=15.0)
    cam = Camera.from_fov(64, 48, 80)
    rc = MeshRaycaster.from_trimesh(sphere, backend)
    T = look_at([0, 0, 0], [0, 0, 1], up=[0, -1, 0])
    pts = cam.backproject(rc.render_depth(cam, T))
    np.testing.assert_allclose(np.linalg.norm(pts, axis=-1), 15.0, atol=0.02)
    T_away = look_at([0, 0, 100], [0, 0, 200], up=[0, -1, 0])
    assert np.isnan(rc.render_depth(cam, T_away)).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_render_equals_single_renders(backend: str) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=15.0)
    cam = Camera.from_fov(40, 32, 80, dist=np.array([-0.1, 0.01, 0.001, 0, 0]))
    rc = MeshRaycaster.from_trimesh(sphere, backend)
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


@pytest.mark.skipif(len(BACKENDS) < 2, reason="no Mitsuba JIT variant works here")
def test_backends_agree() -> None:
    # A bumpy closed surface (displaced sphere, 20k faces) seen from inside along a path,
    # with distortion: both back ends trace float32 rays against the same triangles.
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=15.0)
    v = mesh.vertices
    mesh = trimesh.Trimesh(
        v * (1 + 0.08 * np.sin(3 * v[:, :1]) * np.cos(2 * v[:, 1:2])), mesh.faces
    )
    cam = Camera.from_fov(160, 128, 85, dist=np.array([-0.2, 0.03, 0.001, -0.001, 0]))
    rng = np.random.default_rng(3)
    poses = np.stack(
        [look_at(rng.uniform(-4, 4, 3), rng.uniform(-6, 6, 3) + [0, 0, 10], [0, -1, 0])
         for _ in range(12)]
    )  # fmt: skip
    a = MeshRaycaster.from_trimesh(mesh, "mitsuba").render_depths(cam, poses)
    b = MeshRaycaster.from_trimesh(mesh, "open3d").render_depths(cam, poses)
    both = np.isfinite(a) & np.isfinite(b)
    assert both.mean() > 0.99
    # Misses that one back end reports alone: rays through an edge shared by two faces.
    assert (np.isfinite(a) != np.isfinite(b)).mean() < 1e-4
    diff = np.abs(a - b)[both]
    assert np.median(diff) < 1e-5 and np.quantile(diff, 0.9999) < 1e-3


def test_backend_choice() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=15.0)
    rc = MeshRaycaster.from_trimesh(sphere)
    assert rc.backend == ("mitsuba" if jit_mitsuba() is not None else "open3d")
    assert MeshRaycaster.from_trimesh(sphere, "open3d").backend == "open3d"
    with pytest.raises(InvalidInputError, match="backend"):
        MeshRaycaster.from_trimesh(sphere, "embree")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="out of range"):
        MeshRaycaster(sphere.vertices, sphere.faces + len(sphere.vertices))


def test_surface_queries_match_the_analytic_sphere() -> None:
    """Open3D's scene queries through SurfaceQueries against a sphere's closed forms."""
    from chisel.core.raycast import SurfaceQueries

    R = 10.0
    sphere = trimesh.creation.icosphere(5, radius=R)  # chord error < 0.01 mm
    q = SurfaceQueries.from_trimesh(sphere)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(500, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = rng.uniform(2.0, 18.0, size=500)
    pts = dirs * radii[:, None]
    np.testing.assert_allclose(q.distance(pts), np.abs(radii - R), atol=0.02)
    np.testing.assert_allclose(q.signed_distance(pts), radii - R, atol=0.02)
    np.testing.assert_array_equal(q.inside(pts), radii < R)
    np.testing.assert_allclose(np.linalg.norm(q.closest_points(pts), axis=1), R, atol=0.02)
    np.testing.assert_allclose(q.first_hit(np.zeros((500, 3)), dirs), R, atol=0.02)
    faces = q.first_hit_face(np.zeros((500, 3)), dirs)
    centroids = sphere.triangles_center[faces]
    assert np.all(np.degrees(np.arccos(np.clip(np.sum(centroids / R * dirs, 1), -1, 1))) < 2.0)
    away = q.first_hit(np.full((1, 3), 30.0), np.array([[1.0, 0, 0]]))
    assert np.isinf(away[0])
    assert q.first_hit_face(np.full((1, 3), 30.0), np.array([[1.0, 0, 0]]))[0] == -1
    assert q.distance(np.zeros((0, 3))).shape == (0,)


def test_mesh_arrays_refuse_bad_meshes() -> None:
    from chisel.core.errors import InvalidInputError
    from chisel.core.raycast import mesh_arrays

    v = np.zeros((3, 3))
    with pytest.raises(InvalidInputError, match="m.ply: face index 3 out of range for 3"):
        mesh_arrays(v, np.array([[0, 1, 3]]), "m.ply")
    with pytest.raises(InvalidInputError, match="face index -1 out of range"):
        mesh_arrays(v, np.array([[0, 1, -1]]))
    with pytest.raises(InvalidInputError, match="NaN/inf"):
        mesh_arrays(np.full((3, 3), np.nan), np.array([[0, 1, 2]]))
    with pytest.raises(InvalidInputError, match=r"\(F>0, 3\) faces"):
        mesh_arrays(v, np.zeros((0, 3), int))


def test_surface_hits_match_analytic_spheres_and_trimesh() -> None:
    """Every crossing along a ray: two disjoint spheres in closed form, and a torus against
    trimesh's own ray-triangle intersector (an independent implementation)."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    from chisel.core.raycast import SurfaceQueries

    a = trimesh.creation.icosphere(5, radius=5.0)
    b = trimesh.creation.icosphere(5, radius=3.0)
    b.apply_translation([20.0, 0.0, 0.0])
    q = SurfaceQueries.from_trimesh(trimesh.util.concatenate([a, b]))
    # Along +x from x = -20, through a vertex-free line: spheres at [-5, 5] and [17, 23].
    h = q.hits(np.array([[-20.0, 1e-3, 2e-3]]), np.array([[1.0, 0.0, 0.0]]), 5)
    np.testing.assert_allclose(h[0, :4], [15.0, 25.0, 37.0, 43.0], atol=0.02)
    assert np.isinf(h[0, 4])
    # From inside the first sphere: its back face, then the second sphere.
    h = q.hits(np.array([[0.0, 1e-3, 2e-3]]), np.array([[1.0, 0.0, 0.0]]), 2)
    np.testing.assert_allclose(h[0], [5.0, 17.0], atol=0.02)

    torus = trimesh.creation.torus(major_radius=10.0, minor_radius=3.0)
    q = SurfaceQueries.from_trimesh(torus)
    rng = np.random.default_rng(1)
    origins = np.column_stack([rng.uniform(-2, 2, 200), rng.uniform(-2, 2, 200),
                               np.full(200, 0.3)])  # fmt: skip
    dirs = rng.normal(size=(200, 3)) * [1.0, 1.0, 0.15]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ours = q.hits(origins, dirs, 4)
    locs, ray_idx, _ = RayMeshIntersector(torus).intersects_location(
        origins, dirs, multiple_hits=True
    )
    for i in range(200):
        t = np.sort(np.linalg.norm(locs[ray_idx == i] - origins[i], axis=1))
        t = t[np.diff(t, prepend=-1.0) > 1e-4][:4]
        np.testing.assert_allclose(ours[i, : len(t)], t, atol=1e-3)
        assert np.all(np.isinf(ours[i, len(t) :]))
    assert (np.isfinite(ours).sum(axis=1) >= 2).sum() > 150  # most rays cross the ring
    with pytest.raises(InvalidInputError, match="n"):
        q.hits(origins, dirs, 0)
