"""TSDF fusion and mesh extraction against analytic truth and a brute-force reference."""

import numpy as np
import pytest
import trimesh

from chisel.core.errors import EmptyResultError, InvalidInputError, PoseError
from chisel.core.geometry import Camera, invert_rigid, look_at
from chisel.core.raycast import MeshRaycaster
from chisel.fusion import check_pose_in_model, integrate
from chisel.mesh import extract_mesh
from chisel.model import TsdfModel

R_MM = 12.0


def _sphere_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        up = np.cross(d, rng.normal(size=3))
        out.append(look_at(rng.normal(size=3) * 1.5, d * 8.0, up))
    return np.stack(out)


@pytest.fixture(scope="module")
def sphere_model() -> TsdfModel:
    """A spherical cavity of radius 12 mm seen from inside, through a distorted lens."""
    cam = Camera.from_fov(64, 48, 80.0, dist=np.array([-0.08, 0.01, 0.001, -0.001, 0.0]))
    rc = MeshRaycaster.from_trimesh(trimesh.creation.icosphere(subdivisions=6, radius=R_MM))
    m = TsdfModel.empty([-14.25, -14.0, -13.75], [14.0, 14.0, 14.0], 0.5, 1.5)
    for T in _sphere_poses(60, seed=1):
        integrate(m, cam, T, rc.render_depth(cam, T))
    return m


def _voxel_centres(m: TsdfModel) -> np.ndarray:
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in m.shape], indexing="ij"), axis=-1)
    return ijk * m.voxel_size_mm + m.origin_mm


def test_sphere_tsdf_matches_analytic_distance(sphere_model: TsdfModel) -> None:
    m = sphere_model
    sd = R_MM - np.linalg.norm(_voxel_centres(m), axis=-1)  # + inside the cavity (free)
    near = (m.weight > 0) & (np.abs(sd) < 1.0)
    assert near.sum() > 10_000  # the shell is observed all round
    err = np.abs(m.tsdf[near] * m.trunc_mm - sd[near])
    assert err.max() < 0.5 * m.voxel_size_mm
    # Free space in front of the surface beyond the truncation is carved to +1.
    free = (m.weight > 0) & (sd > m.trunc_mm + 0.5)
    assert free.sum() > 10_000 and np.all(m.tsdf[free] == 1.0)
    # Voxels far behind the surface are never touched (nearest-pixel lookup at grazing
    # views can reach a little beyond the truncation, never two voxels beyond it).
    assert np.all(m.weight[sd < -(m.trunc_mm + 2 * m.voxel_size_mm)] == 0)


def test_sphere_mesh_in_world_mm(sphere_model: TsdfModel) -> None:
    mesh = extract_mesh(sphere_model)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - R_MM).max() < sphere_model.voxel_size_mm / 2
    # Normals point into free space (the cavity): towards the centre.
    inward = np.einsum("ij,ij->i", mesh.face_normals, -mesh.triangles_center) > 0
    assert inward.mean() > 0.99


def _reference_integrate(m: TsdfModel, cam: Camera, T: np.ndarray, depth: np.ndarray) -> None:
    """Brute force over every voxel with the camera's own projection (independent code)."""
    pc = _voxel_centres(m).reshape(-1, 3) @ invert_rigid(T)[:3, :3].T + invert_rigid(T)[:3, 3]
    uv, z = cam.project(pc)
    rays = cam.rays_cam()
    r2max = (rays[..., 0] ** 2 + rays[..., 1] ** 2).max() * 1.02
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = (pc[:, 0] / z) ** 2 + (pc[:, 1] / z) ** 2
    u = np.floor(uv[:, 0] + 0.5)
    v = np.floor(uv[:, 1] + 0.5)
    ok = (z > 1e-3) & (r2 <= r2max) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
    idx = np.flatnonzero(ok)
    dm = depth[v[idx].astype(int), u[idx].astype(int)]
    good = np.isfinite(dm)
    idx, dm = idx[good], dm[good]
    sd = dm - z[idx]
    keep = sd >= -m.trunc_mm
    idx, d = idx[keep], np.minimum(1.0, sd[keep] / m.trunc_mm)
    t, w = m.tsdf.reshape(-1), m.weight.reshape(-1)
    t[idx] = (w[idx] * t[idx] + d) / (w[idx] + 1.0)
    w[idx] += 1.0


def test_kernel_matches_brute_force_reference() -> None:
    cam = Camera.from_fov(40, 30, 75.0, dist=np.array([-0.1, 0.02, 0.0, 0.0, 0.0]))
    rc = MeshRaycaster.from_trimesh(trimesh.creation.icosphere(subdivisions=5, radius=9.0))
    a = TsdfModel.empty([-10, -10, -10], [10, 10, 10], 0.5, 1.25)
    b = a.copy()
    for T in _sphere_poses(6, seed=4):
        depth = rc.render_depth(cam, T)
        depth[::7, ::5] = np.nan  # holes must be skipped
        integrate(a, cam, T, depth)
        _reference_integrate(b, cam, T, depth)
    # Voxel centres that fall exactly on a pixel boundary may round differently.
    differ = (a.weight != b.weight).mean()
    assert differ < 1e-3
    same = a.weight == b.weight
    np.testing.assert_allclose(a.tsdf[same], b.tsdf[same], atol=1e-5)


def test_zero_mask_leaves_model_bit_identical(sphere_model: TsdfModel) -> None:
    m = sphere_model.copy()
    cam = Camera.from_fov(64, 48, 80.0)
    T = _sphere_poses(1, seed=9)[0]
    depth = np.full(cam.shape, 5.0, np.float32)
    reset = np.zeros(m.shape, np.uint8)
    n = integrate(m, cam, T, depth, pixel_weight=np.zeros(cam.shape, bool), reset=reset)
    assert n == 0
    assert m.tsdf.tobytes() == sphere_model.tsdf.tobytes()
    assert m.weight.tobytes() == sphere_model.weight.tobytes()
    assert not reset.any()


def test_masked_update_resets_weight_and_takes_new_depth() -> None:
    # A plane at z = 10 fused 5 times; then a changed pixel sees it at z = 14.
    cam = Camera.from_fov(32, 24, 60.0)
    m = TsdfModel.empty([-8, -8, 0.25], [8, 8, 20], 0.5, 1.5)
    for _ in range(5):
        integrate(m, cam, np.eye(4), np.full(cam.shape, 10.0, np.float32))
    reset = np.zeros(m.shape, np.uint8)
    mask = np.zeros(cam.shape, bool)
    mask[8:16, 12:20] = True
    before = m.copy()
    integrate(m, cam, np.eye(4), np.full(cam.shape, 14.0, np.float32), mask, reset=reset)
    touched = reset.astype(bool)
    assert touched.any()
    # Touched voxels: weight reset then one observation -> W = 1, D = the new distance.
    assert np.all(m.weight[touched] == 1.0)
    z = _voxel_centres(m)[..., 2]
    expect = np.minimum(1.0, (14.0 - z) / 1.5)
    np.testing.assert_allclose(m.tsdf[touched], expect[touched], atol=1e-5)
    # The old wall (z = 10) inside the changed pixels became free space.
    assert np.all(m.tsdf[touched & (np.abs(z - 10.0) < 0.3)] == 1.0)
    # Untouched voxels are bit-identical.
    assert m.tsdf[~touched].tobytes() == before.tsdf[~touched].tobytes()
    assert m.weight[~touched].tobytes() == before.weight[~touched].tobytes()
    # A second changed frame in the same step averages instead of resetting again.
    integrate(m, cam, np.eye(4), np.full(cam.shape, 14.0, np.float32), mask, reset=reset)
    assert np.all(m.weight[touched] == 2.0)


def test_unobserved_only_writes_what_was_never_observed_or_rewritten_this_step() -> None:
    # A plane at z = 10 seen by the left half of the image only; then the whole image sees
    # a plane at z = 12, fused only into voxels never observed (or reset in this step).
    cam = Camera.from_fov(32, 24, 60.0)
    m = TsdfModel.empty([-8, -8, 0.25], [8, 8, 20], 0.5, 1.5)
    left = np.zeros(cam.shape, bool)
    left[:, :16] = True
    integrate(m, cam, np.eye(4), np.full(cam.shape, 10.0, np.float32), left)
    before = m.copy()
    seen = m.weight > 0
    reset = np.zeros(m.shape, np.uint8)
    n = integrate(
        m, cam, np.eye(4), np.full(cam.shape, 12.0, np.float32), reset=reset, unobserved_only=True
    )
    assert n > 0
    assert m.tsdf[seen].tobytes() == before.tsdf[seen].tobytes()
    assert m.weight[seen].tobytes() == before.weight[seen].tobytes()
    new = (m.weight > 0) & ~seen
    z = _voxel_centres(m)[..., 2]
    np.testing.assert_allclose(m.tsdf[new], np.minimum(1.0, (12.0 - z[new]) / 1.5), atol=1e-5)
    assert np.all(m.weight[new] == 1.0) and np.array_equal(reset.astype(bool), new)
    # In the same step, a voxel it wrote is averaged again; the observed ones still are not.
    integrate(
        m, cam, np.eye(4), np.full(cam.shape, 12.0, np.float32), reset=reset, unobserved_only=True
    )
    assert np.all(m.weight[new] == 2.0)
    assert m.tsdf[seen].tobytes() == before.tsdf[seen].tobytes()


def test_colour_is_averaged_in_the_band() -> None:
    cam = Camera.from_fov(32, 24, 60.0)
    m = TsdfModel.empty([-8, -8, 0.25], [8, 8, 20], 0.5, 1.5, with_color=True)
    rgb = np.zeros((*cam.shape, 3), np.uint8)
    rgb[..., 0] = 200
    integrate(m, cam, np.eye(4), np.full(cam.shape, 10.0, np.float32), rgb=rgb)
    rgb[..., 0] = 100
    integrate(m, cam, np.eye(4), np.full(cam.shape, 10.0, np.float32), rgb=rgb)
    band = (m.weight > 0) & (np.abs(m.tsdf) < 1)
    assert band.any() and np.all(m.color[band, 0] == 150)
    assert np.all(m.color[(m.weight > 0) & (m.tsdf == 1.0)] == 0)  # free space: no colour
    mesh = extract_mesh(m)
    assert mesh.visual.vertex_colors[:, 0].min() == 150


def test_bad_inputs() -> None:
    cam = Camera.from_fov(32, 24, 60.0)
    m = TsdfModel.empty([-8, -8, 0.25], [8, 8, 20], 0.5, 1.5)
    depth = np.full(cam.shape, 10.0, np.float32)
    with pytest.raises(InvalidInputError, match="camera is 32x24"):
        integrate(m, cam, np.eye(4), depth[:10])
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(PoseError, match="not rigid"):
        integrate(m, cam, bad, depth)
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    with pytest.raises(PoseError, match="non-finite"):
        integrate(m, cam, nan_pose, depth)
    with pytest.raises(InvalidInputError, match="pixel_weight"):
        integrate(m, cam, np.eye(4), depth, pixel_weight=-np.ones(cam.shape))
    with pytest.raises(InvalidInputError, match="reset"):
        integrate(m, cam, np.eye(4), depth, reset=np.zeros((2, 2, 2), np.uint8))
    outside = np.eye(4)
    outside[:3, 3] = [0, 0, -50]
    with pytest.raises(PoseError, match="outside the model"):
        check_pose_in_model(m, outside, "pose")
    assert integrate(m, cam, np.eye(4), np.full(cam.shape, np.nan, np.float32)) == 0


def test_empty_surface_raises() -> None:
    m = TsdfModel.empty([0, 0, 0], [5, 5, 5], 0.5, 1.0)
    with pytest.raises(EmptyResultError, match="nothing to mesh"):
        extract_mesh(m)
    m.weight[...] = 1.0
    m.tsdf[...] = 0.5  # observed, but no zero crossing
    with pytest.raises(EmptyResultError, match="no zero crossing"):
        extract_mesh(m)
