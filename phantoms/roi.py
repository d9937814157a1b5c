"""The change box: the region of interest around the largest change (the last step).

The paper fixes "a 3D box around the largest change (last step)" and scores every step
inside it. The change of a removal is not only the tissue that went: it is also the
surface that the removal reveals, the surface behind the opening that the endoscope now
sees where it saw the removed tissue before. :func:`change_box` is the box around both:

1. the removed tissue: the exact bounds of ``preop - last`` (every step's removal);
2. the revealed surface: rays are cast from the endoscope's side (the end of the airway
   path and points 6-16 mm in front of the target along its normal, each also moved
   ±3 mm sideways: the places the evaluation poses are drawn around) through sample
   points of the removed tissue. A ray's hit on the last step's mesh is a revealed point
   when the ray reaches the sample point in air (the removal opened it), the preoperative
   surface along the same ray lay at least ``MIN_CHANGE_MM`` in front of it (the point
   was hidden), and it lies at most ``REVEAL_DEPTH_MM`` behind the preoperative surface;

then grown by the margin. Pure geometry on Open3D's ``RaycastingScene``; same inputs,
same box (no random numbers).
"""

from __future__ import annotations

import manifold3d as m3d
import numpy as np
import open3d as o3d

from phantoms.anatomy import arrays_from_manifold

REVEAL_DEPTH_MM = 25.0
"""A revealed point counts up to this far behind the preoperative surface along its ray."""
MIN_CHANGE_MM = 1.0
"""The paper's change threshold: depth must grow by more than this along the ray."""
VIEW_DISTANCES_MM = (6.0, 11.0, 16.0)
"""Distances in front of the target (along its normal) of the ray origins."""
SIDE_OFFSET_MM = 3.0
"""Each origin is also moved this far sideways (four directions)."""
CLEARANCE_MM = 2.0
"""Ray origins closer than this to the preoperative tissue are dropped."""
MAX_SAMPLES = 4000
"""At most this many sample points of the removed tissue (evenly strided)."""


def raycasting_scene(v: np.ndarray, f: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """Open3D's ray-casting scene of one triangle mesh (vertices (V, 3) mm, faces (F, 3))."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(v, np.float32)),
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(f, np.uint32)),
    )
    return scene


def removed_samples(removed: m3d.Manifold, max_samples: int = MAX_SAMPLES) -> np.ndarray:
    """(N, 3) points just inside the removed solid: its face centroids moved 0.05 mm
    inwards (at most ``max_samples``, evenly strided)."""
    v, f = arrays_from_manifold(removed)
    tri = v[f]
    cen = tri.mean(axis=1)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-12
    cen, nrm = cen[ok], nrm[ok] / ln[ok, None]
    pts = cen - 0.05 * nrm
    stride = max(1, int(np.ceil(len(pts) / max_samples)))
    return pts[::stride]


def ray_origins(
    approach_mm: np.ndarray, target_center_mm: np.ndarray, target_normal: np.ndarray
) -> np.ndarray:
    """(M, 3) ray origins on the endoscope's side: the airway path's end and points in
    front of the target, each also moved ±``SIDE_OFFSET_MM`` in two directions."""
    n = np.asarray(target_normal, float)
    n = n / np.linalg.norm(n)
    helper = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    centres = [np.asarray(approach_mm, float)]
    centres += [np.asarray(target_center_mm, float) + d * n for d in VIEW_DISTANCES_MM]
    offsets = [np.zeros(3), SIDE_OFFSET_MM * e1, -SIDE_OFFSET_MM * e1]
    offsets += [SIDE_OFFSET_MM * e2, -SIDE_OFFSET_MM * e2]
    return np.array([c + o for c in centres for o in offsets])


def revealed_points(
    preop: tuple[np.ndarray, np.ndarray],
    last: tuple[np.ndarray, np.ndarray],
    samples_mm: np.ndarray,
    origins_mm: np.ndarray,
    max_depth_mm: float = REVEAL_DEPTH_MM,
) -> np.ndarray:
    """(K, 3) points of the last step's surface that the removal reveals (see module doc).

    preop, last : (vertices (V, 3) mm, faces (F, 3)) of the preoperative and the last
    step's mesh. samples_mm : (N, 3) points inside the removed tissue. origins_mm : (M, 3)
    ray origins in the airway.
    """
    pre_scene, last_scene = raycasting_scene(*preop), raycasting_scene(*last)
    o = np.asarray(origins_mm, np.float32)
    sd = pre_scene.compute_signed_distance(
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(o))
    ).numpy()
    # signed distance is negative inside a closed mesh; the airway is outside the tissue
    o = o[sd >= CLEARANCE_MM]
    if len(o) == 0 or len(samples_mm) == 0:
        return np.zeros((0, 3))
    s = np.asarray(samples_mm, np.float32)
    eo = np.repeat(o, len(s), axis=0)
    d = np.tile(s, (len(o), 1)) - eo
    dist = np.linalg.norm(d, axis=1)
    d /= np.maximum(dist, 1e-9)[:, None]
    rays = o3d.core.Tensor.from_numpy(np.concatenate([eo, d], axis=1).astype(np.float32))
    t_last = last_scene.cast_rays(rays)["t_hit"].numpy()
    t_pre = pre_scene.cast_rays(rays)["t_hit"].numpy()
    keep = (
        np.isfinite(t_last)
        & (t_last > dist)  # the ray reaches the removed sample in air: through the opening
        & (t_last - t_pre > MIN_CHANGE_MM)  # the preop surface hid the point
        & (t_last - t_pre <= max_depth_mm)
    )
    return (eo[keep] + d[keep] * t_last[keep, None]).astype(np.float64)


def change_box(
    preop: m3d.Manifold,
    last: m3d.Manifold,
    approach_mm: np.ndarray,
    target_center_mm: np.ndarray,
    target_normal: np.ndarray,
    margin_mm: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The change box ``(min (3,), max (3,), n_revealed)`` in world mm: the removed tissue
    (``preop - last``) and the surface its removal reveals, grown by ``margin_mm``."""
    removed = preop - last
    box = np.asarray(removed.bounding_box(), float)
    lo, hi = box[:3].copy(), box[3:].copy()
    pts = revealed_points(
        arrays_from_manifold(preop),
        arrays_from_manifold(last),
        removed_samples(removed),
        ray_origins(approach_mm, target_center_mm, target_normal),
    )
    if len(pts):
        lo = np.minimum(lo, pts.min(axis=0))
        hi = np.maximum(hi, pts.max(axis=0))
    return lo - margin_mm, hi + margin_mm, len(pts)
