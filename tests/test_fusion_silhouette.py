"""The lateral bound on free space beside a silhouette (the rim of a bite)."""

import cv2
import numpy as np

from chisel.core.geometry import Camera
from chisel.fusion import integrate
from chisel.mesh import extract_mesh
from chisel.model import TsdfModel


def _wall_with_hole(lateral: bool) -> tuple[TsdfModel, float]:
    """A wall at z = 10 mm carved by a hole whose edge is at x = 0 (x > 0 removed)."""
    cam = Camera.from_fov(160, 120, 70)
    model = TsdfModel.empty(np.array([-6.0, -4.0, 6.0]), np.array([6.0, 4.0, 16.0]), 0.25, 1.0)
    T = np.eye(4)
    wall = np.full(cam.shape, 10.0, np.float32)
    integrate(model, cam, T, wall)  # preop: a solid wall seen head-on
    rays = cam.rays_cam()
    hole = rays[..., 0] > 0.0  # pixels looking through the removed part of the wall
    depth = np.where(hole, 30.0, 10.0).astype(np.float32)
    reset = np.zeros(model.shape, np.uint8)
    lat = cv2.distanceTransform(hole.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    integrate(
        model, cam, T, depth, pixel_weight=hole, reset=reset, lateral_px=lat if lateral else None
    )
    mesh = extract_mesh(model)
    # The rim: the hole's side face runs through the wall (10 < z < 11); its x is where
    # marching cubes puts the zero crossing between the last wall voxel and the carved one.
    v = np.asarray(mesh.vertices)
    side = v[(v[:, 2] > 10.1) & (v[:, 2] < 10.9) & (np.abs(v[:, 1]) < 2.0)]
    rim_x = float(np.median(side[np.abs(side[:, 0]) < 0.5][:, 0]))
    return model, rim_x


def test_lateral_bound_keeps_the_rim_in_place() -> None:
    _, rim_bounded = _wall_with_hole(lateral=True)
    _, rim_projective = _wall_with_hole(lateral=False)
    # True rim at x = 0 (voxel 0.25 mm). The projective distance (+1 beside the rim)
    # pulls the rim back by most of a voxel; the bounded distance keeps it within a fifth.
    assert abs(rim_bounded) < 0.05, rim_bounded
    assert rim_projective < -0.1, rim_projective


def test_lateral_bound_never_creates_surface() -> None:
    model, _ = _wall_with_hole(lateral=True)
    # Every voxel in front of the hole's far depth along the hole rays is free (> 0).
    i = model.tsdf[model.weight > 0]
    assert np.all(np.isfinite(i)) and i.min() >= -1.0 and i.max() <= 1.0
