"""Filling a sweep-only model's never-observed voxels where other views confirm the depth
(``UpdateConfig.fill_confirmed``, :mod:`chisel.fill`).

Scene (world mm): a tissue block with one air chamber (|x|, |y| <= 10, z -12..10) and a
plate (a lamella: |x|, |y| <= 3, z 4..6) standing in it in front of the back wall. The
cameras stand in the chamber and look at the back wall. The preoperative model is the
paper's, fused from a sweep, of the chamber without the plate; the plate's box (and a
voxel around it) is then marked never observed. That is what a sweep leaves where it
never looked (outside every frustum of it), made here without building those frusta: the
model shows the back wall through the plate, no estimate is deeper than that render, so no
change is measured there, and the unseen fill (where the model shows nothing) skips it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from test_updater_scenes import LearntExactDepth

from chisel.batch import update_step
from chisel.build import BuildConfig, build_preop_model
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, look_at, transform_points
from chisel.core.raycast import MeshRaycaster
from chisel.depth_source import CallableDepth, GroundTruthDepth
from chisel.fill import depth_edges, estimate_support, near_unobserved, occluded_frames
from chisel.io.sequence import Frame
from chisel.mesh import extract_mesh
from chisel.model import TsdfModel
from chisel.update_config import UpdateConfig

VOXEL_MM = 0.5
CAM = Camera.from_fov(96, 80, 70.0)


def _chamber() -> trimesh.Trimesh:
    block = trimesh.creation.box(extents=[28.0, 28.0, 40.0])
    block.apply_translation([0.0, 0.0, 4.0])
    air = trimesh.creation.box(extents=[20.0, 20.0, 22.0])
    air.apply_translation([0.0, 0.0, -1.0])
    return block.difference(air, engine="manifold")


def _poses(n: int, seed: int, spread_mm: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        eye = np.array([0.0, 0.0, -6.0]) + rng.uniform(-spread_mm, spread_mm, 3) * [1, 1, 0.5]
        target = np.array([0.0, 0.0, 10.0]) + rng.uniform(-6.0, 6.0, 3) * [1, 1, 0]
        out.append(look_at(eye, target, np.array([0.0, -1.0, 0.0]) + rng.normal(0, 0.2, 3)))
    return np.stack(out)


PLATE_LO, PLATE_HI = np.array([-3.0, -3.0, 4.0]), np.array([3.0, 3.0, 6.0])


def _plate() -> trimesh.Trimesh:
    plate = trimesh.creation.box(extents=PLATE_HI - PLATE_LO)
    plate.apply_translation((PLATE_HI + PLATE_LO) / 2.0)
    return plate


def _sweep_model(swept: trimesh.Trimesh) -> tuple[TsdfModel, np.ndarray]:
    """The paper's preoperative model of ``swept`` and its voxel centres (X, Y, Z, 3), mm."""
    model = build_preop_model(
        swept, CAM, _poses(16, seed=1, spread_mm=5.0), BuildConfig(VOXEL_MM, 2.0)
    )
    centres = transform_points(
        model.T_world_from_voxel, np.argwhere(np.ones(model.shape, bool)).astype(float)
    ).reshape(*model.shape, 3)
    return model, centres


def _step_frames(mesh: trimesh.Trimesh) -> list[Frame]:
    rc = MeshRaycaster.from_trimesh(mesh)
    return [
        Frame(index=i, T_world_from_cam=T, depth_mm=rc.render_depth(CAM, T))
        for i, T in enumerate(_poses(16, seed=2, spread_mm=5.0))
    ]


@pytest.fixture(scope="module")
def scene() -> dict:
    chamber, plate = _chamber(), _plate()
    mesh = trimesh.util.concatenate([chamber, plate])
    model, centres = _sweep_model(chamber)
    box = np.all((centres > PLATE_LO - VOXEL_MM) & (centres < PLATE_HI + VOXEL_MM), axis=-1)
    model.tsdf[box], model.weight[box] = 1.0, 0.0
    return {"mesh": mesh, "model": model, "frames": _step_frames(mesh), "plate": plate}


def _written(before: TsdfModel, after: TsdfModel) -> np.ndarray:
    return (before.weight == 0) & (after.weight > 0)


def test_support_counts_the_views_that_put_the_surface_there() -> None:
    """Cameras side by side looking along +z at a plane 30 mm away: every pixel's point is
    supported by exactly the other cameras whose image it falls in (counted here with the
    camera's own projection); a view that sees deeper contradicts it, a nearer one is
    occluded and does not count."""
    offsets = [(-4.0, 0.0), (0.0, 0.0), (4.0, 0.0), (0.0, 5.0), (3.0, -3.0)]
    poses = []
    for x, y in offsets:
        T = np.eye(4)
        T[:2, 3] = (x, y)
        poses.append(T)
    P = np.stack(poses)
    N = len(P)
    est = np.full((N, *CAM.shape), 30.0, np.float32)
    cands = np.zeros(est.shape, bool)
    cands[0] = True
    used = np.ones(N, bool)
    sup, obs = estimate_support(cands, est, CAM, P, used, 1.0)
    # Frame 0's points in the world, then in every other camera.
    pts_cam0 = CAM.rays_cam().reshape(-1, 3) * 30.0
    world = transform_points(P[0], pts_cam0)
    inside = []
    for j in range(1, N):
        uv, z = CAM.project(transform_points(np.linalg.inv(P[j]), world))
        u, v = np.floor(uv[:, 0] + 0.5), np.floor(uv[:, 1] + 0.5)
        inside.append((z > 0) & (u >= 0) & (u < CAM.width) & (v >= 0) & (v < CAM.height))
    expected = np.sum(inside, axis=0).reshape(CAM.shape)
    assert expected.max() == N - 1 and expected.min() < N - 1
    np.testing.assert_array_equal(sup[0], expected)
    np.testing.assert_array_equal(obs[0], expected)
    assert not sup[1:].any() and not obs[1:].any()  # not candidates
    seen_by_1 = inside[0].reshape(CAM.shape)
    deeper, nearer = est.copy(), est.copy()
    deeper[1], nearer[1] = 35.0, 25.0
    sup_d, obs_d = estimate_support(cands, deeper, CAM, P, used, 1.0)
    np.testing.assert_array_equal(sup_d[0], expected - seen_by_1)
    np.testing.assert_array_equal(obs_d[0], expected)
    sup_n, obs_n = estimate_support(cands, nearer, CAM, P, used, 1.0)
    np.testing.assert_array_equal(sup_n[0], expected - seen_by_1)
    np.testing.assert_array_equal(obs_n[0], expected - seen_by_1)
    # An unused frame neither supports nor observes.
    sup_u, _ = estimate_support(cands, est, CAM, P, np.array([1, 0, 1, 1, 1], bool), 1.0)
    np.testing.assert_array_equal(sup_u[0], expected - seen_by_1)
    # Two occluded frames do not count for each other; one occluded frame counts as any.
    both = np.array([1, 1, 0, 0, 0], bool)
    sup_o, obs_o = estimate_support(cands, est, CAM, P, used, 1.0, occluded=both)
    np.testing.assert_array_equal(sup_o[0], expected - seen_by_1)
    np.testing.assert_array_equal(obs_o[0], expected - seen_by_1)
    one = np.array([0, 1, 0, 0, 0], bool)
    sup_1, obs_1 = estimate_support(cands, est, CAM, P, used, 1.0, occluded=one)
    np.testing.assert_array_equal(sup_1[0], expected)
    np.testing.assert_array_equal(obs_1[0], expected)
    with pytest.raises(InvalidInputError, match="occluded"):
        estimate_support(cands, est, CAM, P, used, 1.0, occluded=np.ones(N + 1, bool))
    with pytest.raises(InvalidInputError, match="tol_mm"):
        estimate_support(cands, est, CAM, P, used, 0.0)
    with pytest.raises(InvalidInputError, match="estimates_mm"):
        estimate_support(cands, est[:, :10], CAM, P, used, 1.0)


def test_depth_edges_are_silhouettes_and_holes() -> None:
    d = np.full((20, 20), 10.0, np.float32)
    d[:, 10:] = 20.0  # a step of 10 mm between columns 9 and 10
    d[5, 5] = np.nan
    e = depth_edges(d, 2.0)
    assert e[:, 9:11].all() and not e[:, [2, 12, 17]].any()
    assert e[4:7, 4:7].all() and not e[8, 5]
    assert not depth_edges(d, 20.0)[:, 9:11].any()  # a jump below the tolerance
    ramp = np.tile(np.linspace(10.0, 12.0, 20, dtype=np.float32), (20, 1))  # 0.1 mm/px
    assert not depth_edges(ramp, 0.5).any()


def test_near_unobserved_finds_the_sweeps_holes(scene: dict) -> None:
    model, f = scene["model"], scene["frames"][0]
    near = near_unobserved(model, CAM, f.T_world_from_cam, f.depth_mm)
    # The sweep saw the back wall's middle: the middle of this frame's wall is observed
    # around its depth, its edges are not.
    assert 0.05 < near.mean() < 0.95
    empty = TsdfModel.empty(model.bounds_mm[0], model.bounds_mm[1], VOXEL_MM, 2.0)
    assert near_unobserved(empty, CAM, f.T_world_from_cam, f.depth_mm)[
        np.isfinite(f.depth_mm)
    ].all()
    with pytest.raises(InvalidInputError, match="depth_mm"):
        near_unobserved(model, CAM, f.T_world_from_cam, f.depth_mm[:10])


def _plate_vertices(model: TsdfModel) -> int:
    v = extract_mesh(model).vertices
    return int(np.all((v > PLATE_LO - VOXEL_MM) & (v < PLATE_HI + VOXEL_MM), axis=1).sum())


def test_confirmed_fill_adds_the_lamella_the_sweep_never_saw(scene: dict) -> None:
    model, fr, mesh = scene["model"], scene["frames"], scene["mesh"]
    assert _plate_vertices(model) == 0  # the sweep never observed the plate
    unseen_only, _ = update_step(
        model, CAM, fr, GroundTruthDepth(), UpdateConfig(fill_confirmed=False)
    )
    confirmed, _ = update_step(model, CAM, fr, GroundTruthDepth())
    assert UpdateConfig().fill_confirmed
    # The unseen fill cannot reach the plate: the model shows the wall behind it.
    assert _plate_vertices(unseen_only) < 20
    assert _plate_vertices(confirmed) > 300
    assert _written(model, confirmed).sum() > _written(model, unseen_only).sum()
    # Every voxel the sweep observed is as it was (nothing changed in the scene).
    seen = model.weight > 0
    assert confirmed.tsdf[seen].tobytes() == model.tsdf[seen].tobytes()
    assert confirmed.weight[seen].tobytes() == model.weight[seen].tobytes()
    # The surface it adds is the scene's: within a voxel of the true mesh everywhere.
    v = extract_mesh(confirmed).vertices
    _, dist, _ = trimesh.proximity.closest_point(mesh, v)
    assert len(v) > 1000 and dist.max() < VOXEL_MM
    # A whole-CT model's never-observed voxels lie outside the CT: left to the unseen fill.
    as_ct = replace(model, build="ct")
    ct_confirmed, _ = update_step(as_ct, CAM, fr, GroundTruthDepth())
    assert ct_confirmed.tsdf.tobytes() == unseen_only.tsdf.tobytes()
    assert ct_confirmed.weight.tobytes() == unseen_only.weight.tobytes()


def test_occluded_frames_hide_tissue_the_other_frames_see() -> None:
    """A field stop shared by every frame occludes nothing; a frame that also hides a
    block of tissue the others keep (an instrument) is occluded once the block passes 2 %
    of the view; a block where the model shows no surface (a ray that meets no tissue) is
    no occluder; a frame without a mask hides nothing."""
    stop = np.zeros((40, 50), bool)
    stop[5:35, 5:45] = True  # 1200 px of view
    tool, speck, void = stop.copy(), stop.copy(), stop.copy()
    tool[5:15, 5:15] = False  # 100 px hidden: 8 %
    speck[5:9, 5:9] = False  # 16 px: under 2 % of 1200
    void[25:35, 35:45] = False  # 100 px where the model shows nothing
    renders = np.full((6, 40, 50), 20.0, np.float32)
    renders[5, 25:35, 35:45] = np.nan
    got = occluded_frames([stop, tool, stop, None, speck, void], renders)
    np.testing.assert_array_equal(got, [False, True, False, False, False, False])
    renders[5] = 20.0  # the same block with tissue behind it
    assert occluded_frames([stop, tool, stop, None, speck, void], renders)[5]
    assert not occluded_frames([None, None], renders[:2]).any()
    assert not occluded_frames([stop, stop], renders[:2]).any()
    with pytest.raises(InvalidInputError, match="renders_mm"):
        occluded_frames([stop, stop], renders)


def test_occluded_frames_do_not_confirm_each_other(scene: dict) -> None:
    """Every frame of the step hides a block of wall in one of four places (an instrument
    in every view, 9 % of it): no two frames count for each other and the plate is not
    filled; with the instrument in half of the frames the others still confirm it."""
    model, fr = scene["model"], scene["frames"]
    H, W = CAM.shape
    blocks = [(slice(8, 32), slice(8, 32)), (slice(8, 32), slice(W - 32, W - 8)),
              (slice(H - 32, H - 8), slice(8, 32)),
              (slice(H - 32, H - 8), slice(W - 32, W - 8))]  # fmt: skip

    def hidden(f: Frame) -> Frame:
        m = np.ones(CAM.shape, bool)
        m[blocks[f.index % 4]] = False
        return replace(f, mask=m)

    every = [hidden(f) for f in fr]
    half = [hidden(f) if f.index % 2 else f for f in fr]
    none_filled, _ = update_step(model, CAM, every, GroundTruthDepth())
    half_filled, _ = update_step(model, CAM, half, GroundTruthDepth())
    assert _plate_vertices(none_filled) < 20
    assert _plate_vertices(half_filled) > 300


def test_garbage_depth_is_not_confirmed(scene: dict) -> None:
    """Each frame sees a flat wall at its own random depth (smooth garbage: no silhouette
    gives it away): views do not agree where the surface is, so the confirmed fill adds
    nothing to the unseen fill; with the agreement rule off (one supporting view, any
    share) the same garbage writes into never-observed voxels."""
    model, fr = scene["model"], scene["frames"]
    rng = np.random.default_rng(0)
    depth = {f.index: np.float32(rng.uniform(5.0, 40.0)) for f in fr}
    source = CallableDepth(lambda f: np.full(CAM.shape, depth[f.index]), metric=True)
    cfg = UpdateConfig()
    a, _ = update_step(model, CAM, fr, source, replace(cfg, fill_confirmed=False))
    b, _ = update_step(model, CAM, fr, source, cfg)
    assert a.tsdf.tobytes() == b.tsdf.tobytes() and a.weight.tobytes() == b.weight.tobytes()
    lax = replace(cfg, change=replace(cfg.change, min_views=1, min_agreement=0.0))
    c, _ = update_step(model, CAM, fr, source, replace(lax, fill_confirmed=False))
    d, _ = update_step(model, CAM, fr, source, lax)
    assert _written(c, d).sum() > 100


SHADOW_LO, SHADOW_HI = np.array([-3.5, -3.5, 9.0]), np.array([3.5, 3.5, 14.0])
"""Behind the plate (z 4..6) and its free gap: the air in front of the back wall (z = 10)
and the wall itself."""


def test_confirmed_fill_closes_what_carving_opens() -> None:
    """The sweep saw the plate's front and never what lies behind it; the step removes the
    plate. The sweep also saw the free gap right behind the plate (obliquely), not the
    wall past it. Noisy carving deletes the plate, and since free space the model holds
    follows it, it fuses nothing there (deletion first: the surface behind is the
    model's own); but that free space ends in voxels never observed. The confirmed fill
    then fuses the changed pixels' estimate into those (the change mask's multi-view
    check is their confirmation); without it the model shows a hole where the plate
    was. The wall it adds lies within a voxel of the truth, and nowhere else does the
    model gain a surface off the scene."""
    chamber = _chamber()
    model, centres = _sweep_model(trimesh.util.concatenate([chamber, _plate()]))
    shadow = np.all((centres > SHADOW_LO) & (centres < SHADOW_HI), axis=-1)
    model.tsdf[shadow], model.weight[shadow] = 1.0, 0.0
    # The gap right behind the plate was seen free (obliquely); what lies past it never.
    gap = np.all((centres > [-3.5, -3.5, 6.1]) & (centres < [3.5, 3.5, 9.0]), axis=-1)
    model.tsdf[gap], model.weight[gap] = 1.0, 1.0
    frames = _step_frames(chamber)
    opened, _ = update_step(
        model, CAM, frames, LearntExactDepth(), UpdateConfig(fill_confirmed=False)
    )
    closed, _ = update_step(model, CAM, frames, LearntExactDepth(), UpdateConfig())

    v_open, v_closed = extract_mesh(opened).vertices, extract_mesh(closed).vertices

    def wall_vertices(v: np.ndarray) -> np.ndarray:
        inside = np.all(
            (v > SHADOW_LO + [1.0, 1.0, 0.0]) & (v < SHADOW_HI - [1.0, 1.0, 0.0]), axis=1
        )
        return v[inside]

    assert _plate_vertices(opened) < 20 and _plate_vertices(closed) < 20  # the plate is gone
    assert len(wall_vertices(v_open)) < 20  # a hole where the plate was
    wall = wall_vertices(v_closed)
    assert len(wall) > 100
    _, dist, _ = trimesh.proximity.closest_point(chamber, wall)
    assert dist.max() < VOXEL_MM
    assert np.abs(wall[:, 2] - 10.0).max() < VOXEL_MM
    # No surface anywhere else: the whole model lies on the scene as the hole's did.
    _, d_open, _ = trimesh.proximity.closest_point(chamber, v_open)
    _, d_closed, _ = trimesh.proximity.closest_point(chamber, v_closed)
    assert d_closed.max() <= max(d_open.max(), 0.5 * VOXEL_MM)
