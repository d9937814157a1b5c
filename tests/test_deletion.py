"""Deletion-first carving on a wall with a window, and a step that cannot collapse.

Scene (world mm): a tissue block with two air chambers along z, A (z -12..10, the camera's)
and B (z 12..20), separated by a 2 mm wall (z 10..12). Surgery cuts a 6 x 6 mm window
through the wall (|x|, |y| <= 3). The preoperative model is the whole CT (closed mesh), so
B's walls are in the model although no camera in A sees them. Walls are flat: the case
where a scale-solving ICP without a prior collapsed (issue 19).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from test_updater_scenes import LearntExactDepth

from chisel.batch import update_step
from chisel.build import BuildConfig, build_preop_model
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, look_at, transform_points
from chisel.core.raycast import MeshRaycaster
from chisel.ct_model import ct_from_mesh
from chisel.depth_source import CallableDepth, GroundTruthDepth
from chisel.io.sequence import Frame
from chisel.model import TsdfModel
from chisel.update_config import UpdateConfig

VOXEL_MM = 0.5
WINDOW_MM = 3.0
"""Half-width of the window, mm."""
WALL_Z = (10.0, 12.0)


def _box(lo, hi) -> trimesh.Trimesh:  # noqa: ANN001
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    b = trimesh.creation.box(extents=hi - lo)
    b.apply_translation((hi + lo) / 2.0)
    return b


def _scene() -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    block = _box([-14.0, -14.0, -16.0], [14.0, 14.0, 24.0])
    solid = block.difference(_box([-10, -10, -12], [10, 10, WALL_Z[0]]), engine="manifold")
    solid = solid.difference(_box([-10, -10, WALL_Z[1]], [10, 10, 20]), engine="manifold")
    window = _box([-WINDOW_MM, -WINDOW_MM, 9.0], [WINDOW_MM, WINDOW_MM, 13.0])
    return solid, solid.difference(window, engine="manifold")


CAM = Camera.from_fov(96, 80, 70.0)


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        eye = np.array([0.0, 0.0, -2.0]) + rng.uniform(-4.0, 4.0, 3) * [1, 1, 0.5]
        target = np.array([0.0, 0.0, 11.0]) + rng.uniform(-3.0, 3.0, 3) * [1, 1, 0]
        out.append(look_at(eye, target, np.array([0.0, -1.0, 0.0]) + rng.normal(0, 0.2, 3)))
    return np.stack(out)


def _hand_eye_error(shift_mm: float, angle_deg: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(angle_deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    F = np.eye(4)
    F[:3, :3] = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    t = rng.normal(size=3)
    F[:3, 3] = t / np.linalg.norm(t) * shift_mm
    return F


def _frames(mesh: trimesh.Trimesh, true: np.ndarray, tracked: np.ndarray) -> list[Frame]:
    rc = MeshRaycaster.from_trimesh(mesh)
    return [
        Frame(index=i, T_world_from_cam=tracked[i], depth_mm=rc.render_depth(CAM, true[i]))
        for i in range(len(true))
    ]


@pytest.fixture(scope="module")
def scene() -> dict:
    before, after = _scene()
    preop = _poses(24, seed=1)
    model = build_preop_model(None, CAM, preop, BuildConfig(VOXEL_MM, 2.0), ct=ct_from_mesh(before))
    return {"before": before, "after": after, "model": model}


def _points(model: TsdfModel) -> np.ndarray:
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in model.shape], indexing="ij"), axis=-1)
    return transform_points(model.T_world_from_voxel, ijk.reshape(-1, 3).astype(float)).reshape(
        *model.shape, 3
    )


def _check_window(model: TsdfModel, new: TsdfModel, tol_mm: float) -> None:
    P = _points(model)
    r = np.max(np.abs(P[..., :2]), axis=-1)  # square "radius" about the window's axis
    z = P[..., 2]
    core = (z > WALL_Z[0] + 0.3) & (z < WALL_Z[1] - 0.3) & (r < 9.5)  # inside the wall
    assert np.all(model.tsdf[core & (r < 9.0)] < 0)  # the preop model holds the wall
    opened = core & (new.tsdf > 0)
    # The window opens to its true size within tol_mm: all of it inside, nothing beyond.
    assert np.all(new.tsdf[core & (r < WINDOW_MM - tol_mm)] > 0), "window not fully open"
    assert r[opened].max() <= WINDOW_MM + tol_mm, f"opened to {r[opened].max():.2f} mm"
    # The far chamber's walls are untouched: B's back wall (z = 20) and side walls.
    far = ((z > WALL_Z[1] + 2.5) | (r > 9.0)) & ~core
    changed = far & (new.tsdf != model.tsdf)
    assert not changed.any(), f"{int(changed.sum())} voxels changed away from the window"


def test_deletion_opens_the_window_and_stops_at_the_next_surface(scene: dict) -> None:
    true = _poses(30, seed=2)
    fr = _frames(scene["after"], true, true)
    new, rep = update_step(scene["model"], CAM, fr, GroundTruthDepth())
    d = rep.to_dict()
    assert sum(f["deleted_px"] for f in d["frames"]) > 0
    _check_window(scene["model"], new, VOXEL_MM)


def test_paper_carving_writes_the_estimate_instead(scene: dict) -> None:
    # The paper's masked update (no deletion) fuses the estimate's depth at every changed
    # pixel; with exact depth it also opens the window, and it never deletes.
    true = _poses(30, seed=2)
    fr = _frames(scene["after"], true, true)
    new, rep = update_step(scene["model"], CAM, fr, GroundTruthDepth(), UpdateConfig(carve="paper"))
    assert all(f["deleted_px"] == 0 for f in rep.to_dict()["frames"])
    P = _points(new)
    r = np.max(np.abs(P[..., :2]), axis=-1)
    mid = (np.abs(P[..., 2] - 11.0) < 0.3) & (r <= WINDOW_MM - VOXEL_MM)
    assert np.all(new.tsdf[mid] > 0)


@pytest.mark.parametrize("relative_hand_eye", ["step", "frame"])
def test_noisy_relative_depth_with_hand_eye_error_registers_or_falls_back(
    scene: dict, relative_hand_eye: str
) -> None:
    # Relative depth (unknown scale, 5 % per-frame scale error), 0.5 mm noise, and a
    # 1 mm / 1 deg hand-eye error on the tracked poses: the step must not fail, and the
    # window is carved to within two voxels, whether the step's correction places every
    # frame or each frame is registered on its own.
    true = _poses(30, seed=3)
    F = _hand_eye_error(1.0, 1.0, seed=4)
    tracked = np.stack([T @ np.linalg.inv(F) for T in true])
    fr = _frames(scene["after"], true, tracked)
    rng = np.random.default_rng(5)
    scale_err = 1.0 + rng.uniform(-0.05, 0.05, len(fr))
    noise = {f.index: rng.normal(0.0, 0.5, f.depth_mm.shape) for f in fr}

    def relative(f: Frame) -> np.ndarray:
        return (0.037 * scale_err[f.index] * (f.depth_mm + noise[f.index])).astype(np.float32)

    cfg = UpdateConfig(relative_hand_eye=relative_hand_eye)
    new, rep = update_step(scene["model"], CAM, fr, CallableDepth(relative), cfg)
    d = rep.to_dict()
    assert len(d["frames_used"]) == len(fr)  # a frame that does not register falls back
    for f in d["frames"]:
        reg = f["registration"] or {}
        assert reg.get("ok", True) or "fallback" in reg, f
        # The scale is anchored to the render: never collapses.
        assert 0.037 * 0.8 < 1.0 / f["scale"] < 0.037 * 1.25
    _check_window(scene["model"], new, 2 * VOXEL_MM)


def test_a_lamella_thinner_than_the_threshold_is_not_deleted_where_it_still_stands() -> None:
    """A changed pixel whose estimate still lies on a thin lamella (the mask's closing, or a
    noisy threshold, put it in the mask) deletes nothing: the estimate must see past the
    layer's back face, not only past its front by the threshold."""
    from chisel.carve import CARVE_DELETED, carve_first_layer

    block = _box([-14.0, -14.0, -16.0], [14.0, 14.0, 24.0])
    solid = block.difference(_box([-10, -10, -12], [10, 10, 10.0]), engine="manifold")
    solid = solid.difference(_box([-10, -10, 10.8], [10, 10, 20]), engine="manifold")  # 0.8 mm
    preop = _poses(8, seed=1)
    model = build_preop_model(None, CAM, preop, BuildConfig(0.25, 1.0), ct=ct_from_mesh(solid))
    T = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 10.0]), np.array([0.0, -1.0, 0.0]))
    depth = MeshRaycaster.from_trimesh(solid).render_depth(CAM, T)
    before = model.tsdf.copy()
    status, n = carve_first_layer(
        model, CAM, T, depth, depth, np.ones(depth.shape, bool), tol_mm=1.0
    )
    assert n == 0 and not (status == CARVE_DELETED).any()
    np.testing.assert_array_equal(model.tsdf, before)
    # The same lamella with the estimate on the next surface (it was removed) is deleted.
    behind = MeshRaycaster.from_trimesh(
        solid.difference(_box([-3, -3, 9.0], [3, 3, 12.0]), engine="manifold")
    ).render_depth(CAM, T)
    status, n = carve_first_layer(model, CAM, T, depth, behind, behind > depth + 1.0, tol_mm=1.0)
    assert n > 0 and (status == CARVE_DELETED).any()


def _walls_model(walls: list[tuple[float, float]]) -> TsdfModel:
    """A whole-CT model of a block with air from z -12 to 20 except the given walls (z ranges)."""
    block = _box([-14.0, -14.0, -16.0], [14.0, 14.0, 24.0])
    edges = [-12.0, *[z for w in walls for z in w], 20.0]
    solid = block
    for lo, hi in zip(edges[::2], edges[1::2], strict=True):
        solid = solid.difference(_box([-10, -10, lo], [10, 10, hi]), engine="manifold")
    return build_preop_model(
        None, CAM, _poses(8, seed=1), BuildConfig(0.25, 1.0), ct=ct_from_mesh(solid)
    )


def _carve_at(
    model: TsdfModel, estimate_z_mm: float, precise: bool, **kw: object
) -> tuple[np.ndarray, int]:
    """Carve a frame looking down +z from the origin whose estimate is the plane z = const,
    with every pixel in view of the first wall marked changed."""
    from chisel.carve import carve_first_layer

    T = look_at(np.zeros(3), np.array([0.0, 0.0, 10.0]), np.array([0.0, -1.0, 0.0]))
    m_t = np.full(CAM.shape, 10.0, np.float32)  # the first wall's front, z-depth
    est = np.full(CAM.shape, estimate_z_mm, np.float32)
    mask = np.zeros(CAM.shape, bool)
    mask[30:50, 38:58] = True  # a central patch: its rays stay inside the walls' 20 x 20 mm
    return carve_first_layer(model, CAM, T, m_t, est, mask, tol_mm=1.0, precise=precise, **kw)


def _freed(before: TsdfModel, after_tsdf: np.ndarray, z_lo: float, z_hi: float) -> int:
    """Voxels inside a wall (z in (z_lo, z_hi), near the axis) that were tissue and are free."""
    P = _points(before)
    sel = (P[..., 2] > z_lo) & (P[..., 2] < z_hi) & (np.max(np.abs(P[..., :2]), axis=-1) < 1.5)
    return int(((before.tsdf < 0) & (after_tsdf > 0) & sel).sum())


def test_a_noisy_estimate_places_no_cut_inside_held_tissue() -> None:
    """An estimate that ends inside a 4 mm wall: precise depth is a partial cut (fused there);
    a noisy estimate (a network's) cannot place one and leaves the wall alone."""
    from chisel.carve import CARVE_FUSE, CARVE_NONE

    model = _walls_model([(10.0, 14.0)])
    for precise, expected in ((True, CARVE_FUSE), (False, CARVE_NONE)):
        m = model.copy()
        status, n = _carve_at(m, 12.0, precise)
        assert n == 0
        assert np.all(status[30:50, 38:58] == expected), (precise, np.unique(status[30:50, 38:58]))


def test_a_noisy_estimate_deletes_one_layer_and_only_past_the_middle_of_the_cavity() -> None:
    # Two 0.8 mm lamellae at z = 10 and z = 14, air behind to z = 20.
    from chisel.carve import CARVE_DELETED, CARVE_NONE

    model = _walls_model([(10.0, 10.8), (14.0, 14.8)])
    # Estimate at z 11.6: past the first lamella's back face, but nearer its front than the
    # next surface (z 14): precise depth deletes the lamella, a noisy estimate does not.
    for precise, expected in ((True, CARVE_DELETED), (False, CARVE_NONE)):
        m = model.copy()
        status, _ = _carve_at(m, 11.6, precise)
        assert np.all(status[30:50, 38:58] == expected), precise
        assert (_freed(model, m.tsdf, 9.8, 11.0) > 0) == precise
    # Estimate at z 20, past both: precise depth deletes both lamellae, a noisy one the first.
    for precise in (True, False):
        m = model.copy()
        status, _ = _carve_at(m, 20.0, precise)
        assert np.all(status[30:50, 38:58] == CARVE_DELETED)
        assert _freed(model, m.tsdf, 9.8, 11.0) > 0
        assert (_freed(model, m.tsdf, 13.8, 15.0) > 0) == precise


def test_a_precise_estimate_frees_held_tissue_in_front_of_it_behind_the_deleted_layer() -> None:
    """Two 0.8 mm lamellae at z = 10 and z = 14; the cut took the first and the front half
    of the second (the estimate is the plane z = 14.4). Layer deletion stops at the next
    surface the model holds (the estimate lies less than the threshold past it), so exact
    depth must free that surface's tissue up to the estimate itself: a cut's rim seen
    obliquely is this case. A noisy estimate does not; nothing beyond the estimate moves."""
    model = _walls_model([(10.0, 10.8), (14.0, 14.8)])
    P = _points(model)
    axis = np.max(np.abs(P[..., :2]), axis=-1) < 1.5
    for precise in (True, False):
        m = model.copy()
        _carve_at(m, 14.4, precise)
        assert _freed(model, m.tsdf, 9.8, 11.0) > 0
        front = _freed(model, m.tsdf, 13.9, 14.3)
        assert (front > 0) == precise, (precise, front)
        beyond = axis & (P[..., 2] > 14.55)
        np.testing.assert_array_equal(m.tsdf[beyond], model.tsdf[beyond])
        if precise:
            # The freed voxels hold their distance to the estimate, not "far from any surface".
            near = axis & (P[..., 2] > 14.0) & (P[..., 2] < 14.4) & (model.tsdf < 0)
            expected = (14.4 - P[..., 2][near]) / model.trunc_mm
            np.testing.assert_allclose(m.tsdf[near], expected, atol=0.05)
    # The estimate on the next surface itself (nothing more was cut): that surface stays.
    m = model.copy()
    _carve_at(m, 14.0, True)
    assert _freed(model, m.tsdf, 13.9, 14.9) == 0


def test_a_precise_estimate_frees_no_more_than_the_threshold_of_a_held_surface() -> None:
    """A silhouette's far depth behind near tissue looks like a deep cut: the estimate at
    z = 17 lies 3 mm inside a 5 mm layer held behind a deleted lamella. The first lamella
    goes, and the held layer loses at most the threshold (1 mm) of its front, not 3 mm."""
    model = _walls_model([(10.0, 10.8), (14.0, 19.0)])
    m = model.copy()
    _carve_at(m, 17.0, True)
    assert _freed(model, m.tsdf, 9.8, 11.0) > 0
    assert _freed(model, m.tsdf, 14.0, 14.8) > 0
    assert _freed(model, m.tsdf, 15.3, 19.0) == 0


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0, 50.0])
def test_the_reach_stops_a_fixed_distance_from_the_estimate_along_its_normal(
    tilt_deg: float,
) -> None:
    """The estimate is a plane tilted about the camera's y axis; a voxel is freed only in
    front of it by more than the margin measured along the plane's normal, which in z is
    margin / |n . ray| (ray with z = 1): analytic, independent of the image gradients."""
    from chisel.carve import _reach_free

    t = np.radians(tilt_deg)
    n = np.array([-np.sin(t), 0.0, np.cos(t)])  # unit normal of z = 20 + x tan(t)
    rays = CAM.rays_cam()
    z = 20.0 / (1.0 - rays[..., 0] * np.tan(t))  # the plane along each ray
    free = _reach_free(z, rays, z.astype(np.float32), 0.1)
    expected = z - 0.1 / np.abs(rays @ n)
    inner = (slice(2, -2), slice(2, -2))  # np.gradient is one-sided at the border
    np.testing.assert_allclose(free[inner], expected[inner], rtol=0, atol=2e-3)
    # A depth edge (a silhouette) has no normal worth the name: it frees nothing near it.
    step = z.astype(np.float32).copy()
    step[:, CAM.shape[1] // 2 :] += 8.0
    free = _reach_free(np.asarray(step, float), rays, step, 0.1)
    edge = free[10:-10, CAM.shape[1] // 2 - 1 : CAM.shape[1] // 2 + 1]
    assert np.all(edge < step[10:-10, CAM.shape[1] // 2 - 1 : CAM.shape[1] // 2 + 1] - 0.5)


def test_a_precise_estimate_takes_the_cuts_edge_the_mask_does_not_see() -> None:
    """A 4 mm wall; the cut took 3 mm in a central patch (the change mask) and 0.7 mm, less
    than the threshold, around it (the edge of the cut; the estimate is 10.7 there and
    beyond). Exact depth frees the edge's tissue in front of the estimate within ``rim_px``
    of the changed patch and nothing deeper, farther out, or when ``rim_px`` is 0; a noisy
    estimate never does."""
    from chisel.carve import CARVE_RIM, carve_first_layer

    model = _walls_model([(10.0, 14.0)])
    T = look_at(np.zeros(3), np.array([0.0, 0.0, 10.0]), np.array([0.0, -1.0, 0.0]))
    m_t = np.full(CAM.shape, 10.0, np.float32)
    est = np.full(CAM.shape, 10.7, np.float32)
    mask = np.zeros(CAM.shape, bool)
    mask[30:50, 38:58] = True
    est[mask] = 13.0
    P = _points(model)
    uv, z = CAM.project(transform_points(np.linalg.inv(T), P.reshape(-1, 3)))
    u, v = np.round(uv[:, 0]).reshape(model.shape), np.round(uv[:, 1]).reshape(model.shape)
    # Pixel distance of each voxel's projection from the changed patch (Chebyshev).
    gap = np.maximum(np.maximum(38 - u, u - 57), np.maximum(30 - v, v - 49))
    for rim_px, precise in ((4, True), (0, True), (4, False)):
        m = model.copy()
        status, _ = carve_first_layer(
            m, CAM, T, m_t, est, mask, tol_mm=1.0, precise=precise, rim_px=rim_px
        )
        freed = (model.tsdf < 0) & (m.tsdf > 0)
        edge = freed & (gap >= 1) & (gap <= 3)
        if rim_px and precise:
            assert (status == CARVE_RIM).any() and edge.sum() > 0
            assert not (freed & (gap >= 1) & (P[..., 2] > 10.7)).any()
        else:
            assert not (status == CARVE_RIM).any() and edge.sum() == 0
        assert not (freed & (gap > rim_px + 1)).any()


def test_a_noisy_estimate_deletes_no_layer_thicker_than_surgery_takes() -> None:
    """FESS takes lamellae 0.4-2 mm thick; a noisy "deeper here" across a 6 mm layer (a
    turbinate) is the estimate's error. Air behind each wall to z = 20, estimate at z 19."""
    from chisel.carve import CARVE_DELETED, CARVE_NONE

    assert UpdateConfig().noisy_layer_mm == 4.0
    for wall, cap, noisy_deletes in (
        ((10.0, 13.0), 4.0, True),  # 3 mm along these near-axial rays: taken
        ((10.0, 16.0), 4.0, False),  # 6 mm: left alone
        ((10.0, 16.0), 6.5, True),  # unless the cap allows it
    ):
        model = _walls_model([wall])
        m = model.copy()
        status, _ = _carve_at(m, 19.0, precise=False, noisy_layer_mm=cap)
        expected = CARVE_DELETED if noisy_deletes else CARVE_NONE
        assert np.all(status[30:50, 38:58] == expected), (wall, cap)
        assert (_freed(model, m.tsdf, wall[0] - 0.2, wall[1] + 0.2) > 0) == noisy_deletes
        m = model.copy()  # exact depth deletes any thickness
        status, _ = _carve_at(m, 19.0, precise=True, noisy_layer_mm=cap)
        assert np.all(status[30:50, 38:58] == CARVE_DELETED)
    for bad in (0.0, -1.0):
        with pytest.raises(InvalidInputError, match="noisy_layer_mm"):
            UpdateConfig(noisy_layer_mm=bad)


def test_a_noisy_estimate_leaves_a_surface_beyond_its_depth_cap_alone() -> None:
    """A 0.8 mm lamella whose front lies 10 mm from the camera, air behind to z = 20, the
    estimate at z 19: a noisy frame deletes it within the cap and leaves it alone beyond."""
    from chisel.carve import CARVE_DELETED, CARVE_NONE

    assert UpdateConfig().noisy_max_depth_mm == 20.0
    model = _walls_model([(10.0, 10.8)])
    for cap, precise, expected in (
        (20.0, False, CARVE_DELETED),
        (9.5, False, CARVE_NONE),
        (9.5, True, CARVE_DELETED),  # exact depth carves at any depth
    ):
        m = model.copy()
        status, _ = _carve_at(m, 19.0, precise=precise, noisy_max_depth_mm=cap)
        assert np.all(status[30:50, 38:58] == expected), (cap, precise)
        assert (_freed(model, m.tsdf, 9.8, 11.0) > 0) == (expected == CARVE_DELETED)
    for bad in (0.0, -5.0):
        with pytest.raises(InvalidInputError, match="noisy_max_depth_mm"):
            UpdateConfig(noisy_max_depth_mm=bad)


def test_noisy_frames_delete_a_voxel_only_at_its_third_vote_and_exact_depth_at_once() -> None:
    # A 0.8 mm lamella at z = 10, air behind it to z = 20; every frame's estimate says z 18.
    from chisel.carve import CARVE_DELETED

    model = _walls_model([(10.0, 10.8)])
    m = model.copy()
    votes = np.zeros(m.shape, np.uint8)
    for frame in range(1, 4):
        status, n = _carve_at(m, 18.0, precise=False, votes=votes, noisy_votes=3)
        assert np.all(status[30:50, 38:58] == CARVE_DELETED)  # the frame's own verdict
        freed = _freed(model, m.tsdf, 9.8, 11.0)
        if frame < 3:
            assert n == 0 and freed == 0, (frame, n, freed)
        else:  # the third vote frees exactly the voxels the first two voted for
            assert n > 0 and freed > 0
            assert n == int(((votes >= 1) & (model.tsdf < 0) & (m.tsdf > 0)).sum())
    # Exact depth (precise) deletes at the first frame, votes or not.
    m = model.copy()
    votes = np.zeros(m.shape, np.uint8)
    _carve_at(m, 18.0, precise=True, votes=votes, noisy_votes=3)
    assert _freed(model, m.tsdf, 9.8, 11.0) > 0 and not votes.any()
    # A wrong votes grid is refused, naming it.
    with pytest.raises(InvalidInputError, match="votes"):
        _carve_at(model.copy(), 18.0, precise=False, votes=np.zeros(3, np.uint8), noisy_votes=3)


def test_noisy_votes_is_checked() -> None:
    assert UpdateConfig().noisy_votes == 3
    for bad in (0, 256):
        with pytest.raises(InvalidInputError, match="noisy_votes"):
            UpdateConfig(noisy_votes=bad)


def test_a_learnt_estimate_is_carved_as_noisy_whatever_its_measured_noise(scene: dict) -> None:
    # Exact depth measures no noise, so it carves as precise; declared a learnt estimate
    # (is_estimate), its frames only vote: two frames that see the window free nothing,
    # while two frames of plain exact depth already open it (multi-view confirmation off,
    # so that two frames may carve at all).
    from chisel.change import ChangeConfig
    from chisel.updater import ChiselUpdater

    true = _poses(30, seed=2)
    fr = _frames(scene["after"], true, true)
    cfg = UpdateConfig(register=False, noisy_votes=3, change=ChangeConfig(min_views=0))
    plain, _ = update_step(scene["model"], CAM, fr[:2], GroundTruthDepth(), cfg)
    learnt, rep = update_step(scene["model"], CAM, fr[:2], LearntExactDepth(), cfg)
    opened = (scene["model"].tsdf < 0) & (plain.tsdf > 0)
    assert opened.sum() > 20
    assert not ((scene["model"].tsdf < 0) & (learnt.tsdf > 0)).any()
    assert sum(f["deleted_px"] for f in rep.to_dict()["frames"]) > 0  # they voted
    three, _ = update_step(scene["model"], CAM, fr[:3], LearntExactDepth(), cfg)
    assert ((scene["model"].tsdf < 0) & (three.tsdf > 0)).sum() > 20  # the third vote
    # With every frame (confirmation back on) the window opens to within two voxels.
    every = UpdateConfig(register=False, noisy_votes=3)
    learnt, _ = update_step(scene["model"], CAM, fr, LearntExactDepth(), every)
    _check_window(scene["model"], learnt, 2 * VOXEL_MM)
    up = ChiselUpdater(scene["model"].copy(), CAM, LearntExactDepth(), cfg)
    up.begin_step()
    for f in fr[:2]:
        up.process(f)
    assert not ((scene["model"].tsdf < 0) & (up.model.tsdf > 0)).any()


def test_a_per_pixel_precise_map_carves_each_pixel_by_its_own_rule() -> None:
    """``precise`` as an (H, W) map (a learnt estimate's reliable pixels): inside a 4 mm
    wall the reliable pixels place a partial cut (fused), the others leave the wall alone;
    through a lamella the reliable pixels delete at once, the others only vote."""
    from chisel.carve import CARVE_FUSE, CARVE_NONE, carve_first_layer

    reliable = np.zeros(CAM.shape, bool)
    reliable[:, :48] = True  # the left half of the image (the patch is columns 38-57)
    status, n = _carve_at(_walls_model([(10.0, 14.0)]), 12.0, reliable)
    assert n == 0
    assert np.all(status[30:50, 38:48] == CARVE_FUSE) and np.all(status[30:50, 48:58] == CARVE_NONE)

    model = _walls_model([(10.0, 10.8)])
    m = model.copy()
    votes = np.zeros(m.shape, np.uint8)
    _, n = _carve_at(m, 18.0, reliable, votes=votes, noisy_votes=3)
    freed = (model.tsdf < 0) & (m.tsdf > 0)
    assert n == int(freed.sum()) > 0
    # What was freed projects to the reliable pixels; the others' voxels only got a vote.
    T = look_at(np.zeros(3), np.array([0.0, 0.0, 10.0]), np.array([0.0, -1.0, 0.0]))
    uv, _ = CAM.project(transform_points(np.linalg.inv(T), _points(model)[freed]))
    assert np.round(uv[:, 0]).max() <= 48
    assert (votes == 1).sum() > 0 and not (votes.astype(bool) & freed).any()
    # A map of another size is refused, naming it.
    with pytest.raises(InvalidInputError, match="precise"):
        carve_first_layer(
            model.copy(), CAM, T, np.full(CAM.shape, 10.0, np.float32),
            np.full(CAM.shape, 18.0, np.float32), np.ones(CAM.shape, bool), tol_mm=1.0,
            precise=np.ones((3, 3), bool),
        )  # fmt: skip


class _DeclaredReliable(GroundTruthDepth):
    """Exact depth declared a learnt estimate that says every pixel is reliable."""

    is_estimate = True

    def __init__(self, shape: tuple[int, int] | None = None) -> None:
        self.shape = shape
        self.last_reliable_px: np.ndarray | None = None

    def __call__(self, frame: Frame) -> np.ndarray:
        d = super().__call__(frame)
        self.last_reliable_px = np.ones(self.shape or d.shape, bool)
        return d


def test_an_estimate_reliable_everywhere_carves_as_exact_depth(scene: dict) -> None:
    """The updater carves a learnt estimate's declared reliable pixels as precise: declared
    reliable everywhere, exact depth gives exact depth's model, in batch and streaming;
    declared an estimate without a map, it gives another (the noisy carving's)."""
    from chisel.updater import ChiselUpdater

    true = _poses(30, seed=2)
    fr = _frames(scene["after"], true, true)
    exact, _ = update_step(scene["model"], CAM, fr, GroundTruthDepth())
    declared, _ = update_step(scene["model"], CAM, fr, _DeclaredReliable())
    np.testing.assert_array_equal(declared.tsdf, exact.tsdf)
    streamed = []
    for source in (GroundTruthDepth(), _DeclaredReliable()):
        upd = ChiselUpdater(scene["model"], CAM, source)
        upd.begin_step()
        list(upd.process_stream(fr))
        upd.end_step()
        streamed.append(upd.model.tsdf)
    # To the last float bit but for a few voxels: streaming varies there from run to run
    # through the registration (tests/test_updater.py, the streaming test).
    np.testing.assert_allclose(streamed[1], streamed[0], rtol=0, atol=1e-6)

    noisy, _ = update_step(scene["model"], CAM, fr, LearntExactDepth())
    assert (noisy.tsdf != exact.tsdf).any()
    with pytest.raises(InvalidInputError, match=r"reliable pixels.*\(3, 3\)"):
        update_step(scene["model"], CAM, fr, _DeclaredReliable((3, 3)))


def test_fill_unseen_fuses_depth_where_a_sweep_only_model_shows_nothing(scene: dict) -> None:
    """A model built from a sweep that saw only the middle of the wall (the paper's build)
    shows no surface around it; the paper's masked update never fills that (no change is
    measured against nothing). With ``fill_unseen`` exact depth fills it, on the true wall,
    and never rewrites a voxel the sweep observed."""
    from chisel.render import ModelRenderer

    before = scene["before"]
    preop = _poses(8, seed=1)
    centre = np.zeros(CAM.shape, bool)
    centre[30:50, 38:58] = True
    rc = MeshRaycaster.from_trimesh(before)
    model = build_preop_model(
        before, CAM, preop, BuildConfig(VOXEL_MM, 2.0), masks=[centre] * len(preop)
    )
    true = _poses(20, seed=2)
    fr = _frames(before, true, true)  # no surgery: exact depth of the same scene

    def missing(m: TsdfModel) -> float:
        r = ModelRenderer(m)
        return float(np.mean([np.isnan(r.render(CAM, T)).mean() for T in true]))

    assert UpdateConfig().fill_unseen
    kept, _ = update_step(model, CAM, fr, GroundTruthDepth(), UpdateConfig(fill_unseen=False))
    filled, _ = update_step(model, CAM, fr, GroundTruthDepth())
    assert missing(model) > 0.3
    assert missing(kept) == pytest.approx(missing(model))
    assert missing(filled) < 0.05
    # The new surface is the wall's: every filled render lies on the truth within a voxel.
    r = ModelRenderer(filled)
    for T in true[:5]:
        d, t = r.render(CAM, T), rc.render_depth(CAM, T)
        ok = np.isfinite(d) & np.isfinite(t)
        assert (
            np.median(np.abs(d[ok] - t[ok])) < 0.1
            and np.mean(np.abs(d[ok] - t[ok]) < VOXEL_MM) > 0.95
        )
    # Nothing changed, so nothing was carved: every voxel the sweep observed is as it was.
    seen = model.weight > 0
    np.testing.assert_array_equal(filled.tsdf[seen], model.tsdf[seen])
    np.testing.assert_array_equal(filled.weight[seen], model.weight[seen])
    assert (filled.weight > 0).sum() > seen.sum()
