"""Small analytic scenes for the updater tests (imported by the other test_updater files).

A "room": a box-shaped air cavity inside a block of tissue, with bumps on the walls so
that registration is well constrained; the camera sits inside the room. A "bite" removes
a block from the far wall (manifold3d boolean), opening a pocket 4 mm deep.
"""

from __future__ import annotations

import numpy as np
import trimesh

from chisel.build import BuildConfig, build_preop_model
from chisel.core.geometry import Camera, look_at, make_transform
from chisel.core.raycast import MeshRaycaster
from chisel.depth_source import GroundTruthDepth
from chisel.io.sequence import Frame
from chisel.model import TsdfModel

ROOM_LO = np.array([-15.0, -12.0, -10.0])
ROOM_HI = np.array([15.0, 12.0, 25.0])
BITE_LO = np.array([-6.0, -6.0, 24.0])
BITE_HI = np.array([0.0, 0.0, 29.0])
"""The cutter box; the far wall is at z = 25, so the pocket is 4 mm deep (z 25 -> 29)."""


class LearntExactDepth(GroundTruthDepth):
    """Exact depth declared a learnt estimate: carved as a noisy frame (deletion votes, one
    thin layer), as a network's depth is, whatever its measured noise."""

    is_estimate = True


def _box(lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    b = trimesh.creation.box(extents=hi - lo)
    b.apply_translation((hi + lo) / 2.0)
    return b


def tissue_mesh() -> trimesh.Trimesh:
    """Closed tissue mesh (world mm): a block minus the room, with bumps into the room."""
    outer = _box(ROOM_LO - 6.0, ROOM_HI + 6.0)
    room = _box(ROOM_LO, ROOM_HI)
    bumps = [
        trimesh.creation.icosphere(subdivisions=3, radius=4.0).apply_translation([6.0, 4.0, 25.0]),
        trimesh.creation.icosphere(subdivisions=3, radius=3.0).apply_translation(
            [-15.0, -3.0, 12.0]
        ),
        trimesh.creation.icosphere(subdivisions=3, radius=3.5).apply_translation([15.0, 5.0, 8.0]),
        _box([-8.0, 10.0, 5.0], [4.0, 12.5, 18.0]),  # a ridge on the floor (+y is down)
        _box([-12.0, -12.5, 14.0], [-4.0, -9.5, 24.5]),  # a shelf on the roof
    ]
    solid = outer.difference(room, engine="manifold")
    for b in bumps:
        solid = solid.union(b, engine="manifold")
    return solid


def bitten_mesh(tissue: trimesh.Trimesh) -> trimesh.Trimesh:
    """The tissue after one bite (the cutter box removed)."""
    return tissue.difference(_box(BITE_LO, BITE_HI), engine="manifold")


def camera(width: int = 96, height: int = 80) -> Camera:
    return Camera.from_fov(width, height, 80.0)


def poses(n: int, seed: int, look_z: float = 25.0, spread_mm: float = 3.0) -> np.ndarray:
    """``n`` camera poses inside the room looking at the far wall around the bite."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        eye = np.array([0.0, 0.0, 2.0]) + rng.uniform(-spread_mm, spread_mm, 3)
        target = np.array([-3.0, -3.0, look_z]) + rng.uniform(-8.0, 8.0, 3) * [1.0, 1.0, 0.0]
        up = np.array([0.0, -1.0, 0.0]) + rng.normal(0.0, 0.3, 3)
        out.append(look_at(eye, target, up))
    return np.stack(out)


def preop_poses(n: int, seed: int) -> np.ndarray:
    """Poses looking at all walls (for the preoperative model)."""
    rng = np.random.default_rng(seed)
    targets = [[0, 0, 25], [-3, -3, 25], [-15, 0, 10], [15, 0, 10], [0, 12, 10], [0, -12, 12]]
    out = []
    for i in range(n):
        eye = np.array([0.0, 0.0, 3.0]) + rng.uniform(-3.0, 3.0, 3)
        target = np.asarray(targets[i % len(targets)], float) + rng.uniform(-4.0, 4.0, 3)
        up = np.array([0.0, -1.0, 0.0]) if abs(target[1]) < 10 else np.array([0.0, 0.0, 1.0])
        out.append(look_at(eye, target, up + rng.normal(0.0, 0.1, 3)))
    return np.stack(out)


def preop_model(tissue: trimesh.Trimesh, cam: Camera) -> TsdfModel:
    """The room's preoperative model: 30 sweep poses (:func:`preop_poses`, seed 1), 0.5 mm
    voxels."""
    return build_preop_model(tissue, cam, preop_poses(30, seed=1), BuildConfig(voxel_size_mm=0.5))


def pose_error(shift_mm: float, angle_deg: float, seed: int) -> np.ndarray:
    """A camera-side rigid error of exactly ``shift_mm`` and ``angle_deg``."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(angle_deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    t = rng.normal(size=3)
    return make_transform(R, t / np.linalg.norm(t) * shift_mm)


def frames(
    mesh: trimesh.Trimesh, cam: Camera, true_poses: np.ndarray, tracked: np.ndarray | None = None
) -> list[Frame]:
    """Frames with exact depth rendered at the true poses, carrying the tracked poses."""
    rc = MeshRaycaster.from_trimesh(mesh)
    tracked = true_poses if tracked is None else tracked
    return [
        Frame(
            index=i,
            T_world_from_cam=tracked[i],
            depth_mm=rc.render_depth(cam, true_poses[i]),
            T_world_from_cam_true=true_poses[i],
        )
        for i in range(len(true_poses))
    ]


def test_bite_removes_the_cutter_volume() -> None:
    tissue = tissue_mesh()
    bitten = bitten_mesh(tissue)
    assert tissue.is_watertight and bitten.is_watertight
    # The pocket is 6 x 6 mm wide and 4 mm deep (the cutter's part inside the wall).
    np.testing.assert_allclose(tissue.volume - bitten.volume, 6 * 6 * 4, rtol=1e-6)


def test_cameras_see_the_far_wall() -> None:
    cam = camera()
    P = poses(4, seed=0)
    for f in frames(tissue_mesh(), cam, P):
        d = f.depth_mm
        assert np.isfinite(d).all() and 5.0 < np.median(d) < 30.0


def hand_eye_step() -> dict:
    """A bitten step of 12 frames whose tracked poses carry one constant camera-side error
    E (1 mm, 1 deg; ``T_tracked = T E``): keys model, cam, frames, tracked, E."""
    tissue, cam = tissue_mesh(), camera()
    P = poses(12, seed=2)
    E = pose_error(1.0, 1.0, seed=10)
    tracked = np.stack([T @ E for T in P])
    return {
        "model": preop_model(tissue, cam),
        "cam": cam,
        "frames": frames(bitten_mesh(tissue), cam, P, tracked),
        "tracked": tracked,
        "E": E,
    }
