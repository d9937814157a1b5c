"""A smooth endoscope path through the airway, from the nostril to a view of the target.

The path is found on a 1 mm grid of the airway: voxels with at least ``clearance_mm``
(+0.5 mm) to every tissue surface are free; a Dijkstra search (scipy) over free voxels,
weighted towards the airway's middle, joins the nostril to a viewpoint 8-15 mm in front
of the target. The polyline is then smoothed and resampled at 1 mm; every point of the
result is checked against the exact distance to the mesh (Open3D), retrying with less
smoothing / more margin until all points keep ``clearance_mm``.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import gaussian_filter1d
from scipy.sparse.csgraph import dijkstra

from phantoms.bites import Target
from phantoms.ct import SurfaceDistance
from phantoms.errors import AnatomyError

VIEW_DISTANCE_MM = (8.0, 15.0)
"""Range of the viewpoint's distance from the target centre."""
VIEW_MAX_ANGLE_DEG = 70.0
"""Largest angle between (viewpoint - target) and the target normal."""


def _hemisphere_dirs(normal: np.ndarray, max_angle_deg: float, n: int = 800) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1.0 - 2.0 * i / n)
    theta = math.pi * (1.0 + 5.0**0.5) * i
    d = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    keep = d @ normal >= math.cos(math.radians(max_angle_deg))
    return d[keep]


def clearance(surface: SurfaceDistance, points_mm: np.ndarray) -> np.ndarray:
    """Signed clearance of points from the tissue, mm: distance in air, negative inside.

    points_mm : (N, 3) float, mm. Returns (N,) float32.
    """
    d = surface.distance(points_mm)
    return np.where(surface.inside(points_mm), -d, d).astype(np.float32)


def find_viewpoint(
    surface: SurfaceDistance, target: Target, clearance_mm: float, reachable
) -> tuple[np.ndarray, float]:
    """Viewpoint 8-15 mm in front of the target with the target in direct sight.

    ``reachable(points) -> bool mask`` tells which candidates the path search can reach.
    Prefers the smallest angle to the target normal (in 10° bins), then the largest
    clearance. Returns the (3,) point in mm and its clearance.
    """
    c = np.asarray(target.center_mm)
    n = np.asarray(target.normal)
    dirs = _hemisphere_dirs(n, VIEW_MAX_ANGLE_DEG)
    dists = np.arange(VIEW_DISTANCE_MM[0], VIEW_DISTANCE_MM[1] + 1e-9, 1.0)
    cand = (c[None, None] + dists[None, :, None] * dirs[:, None, :]).reshape(-1, 3)
    cl = clearance(surface, cand)
    ok = cl >= clearance_mm + 0.5
    if ok.any():
        idx = np.flatnonzero(ok)
        # line of sight: the first hit from the candidate towards the target is the target
        t_hit = surface.first_hit(cand[idx], c - cand[idx])
        seen = t_hit >= 1.0 - 0.3 / np.linalg.norm(c - cand[idx], axis=1)
        idx = idx[seen]
        idx = idx[reachable(cand[idx])] if len(idx) else idx
        if len(idx):
            angle = np.degrees(
                np.arccos(
                    np.clip((cand[idx] - c) @ n / np.linalg.norm(cand[idx] - c, axis=1), -1, 1)
                )
            )
            order = np.lexsort((-cl[idx], np.floor(angle / 10.0)))
            best = idx[order[0]]
            return cand[best], float(cl[best])
    raise AnatomyError(
        "airway_path",
        f"no viewpoint {VIEW_DISTANCE_MM[0]:g}-{VIEW_DISTANCE_MM[1]:g} mm in front of the {target.name} "
        f"(within {VIEW_MAX_ANGLE_DEG:g} deg of its normal) keeps {clearance_mm:g} mm clearance with the target in sight",
    )


def _resample(poly: np.ndarray, step_mm: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(math.ceil(s[-1] / step_mm)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(t, s, poly[:, i]) for i in range(3)], axis=1)


def _smooth(poly: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Gaussian smoothing of a polyline resampled at 0.5 mm, endpoints kept."""
    dense = _resample(poly, 0.5)
    if sigma_mm <= 0 or len(dense) < 5:
        return dense
    out = gaussian_filter1d(dense, sigma_mm / 0.5, axis=0, mode="nearest")
    # blend back to the exact endpoints over ~2 sigma
    n = len(dense)
    ramp = np.clip(np.minimum(np.arange(n), np.arange(n)[::-1]) * 0.5 / (2.0 * sigma_mm), 0.0, 1.0)[
        :, None
    ]
    return ramp * out + (1.0 - ramp) * dense


def airway_path(
    surface: SurfaceDistance,
    nostril_mm: np.ndarray,
    box_min_mm: np.ndarray,
    box_max_mm: np.ndarray,
    target: Target,
    clearance_mm: float = 3.0,
    grid_mm: float = 1.0,
) -> np.ndarray:
    """Smooth polyline from the nostril to a viewpoint in front of the target.

    Parameters
    ----------
    surface : SurfaceDistance
        The preoperative tissue mesh.
    nostril_mm : (3,) float
        Centre of the nostril opening, mm.
    box_min_mm, box_max_mm : (3,) float
        The airway's bounding box, mm (the search grid).
    target : Target
        The first bite's centre and normal.

    Returns
    -------
    (N, 3) float64, mm: points ~1 mm apart, the first at the nostril, the last the
    viewpoint; each at least ``clearance_mm`` from every tissue surface.

    Raises
    ------
    AnatomyError
        If no such path exists.
    """
    lo = np.asarray(box_min_mm, float)
    lo[1] = max(lo[1], float(nostril_mm[1]))
    hi = np.asarray(box_max_mm, float)
    shape = tuple(int(v) for v in np.floor((hi - lo) / grid_mm).astype(int) + 1)
    axes = [lo[i] + grid_mm * np.arange(shape[i]) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    cl_grid = clearance(surface, pts)

    for margin in (0.5, 0.8, 1.2):
        free = cl_grid >= clearance_mm + margin
        if not free.any():
            continue
        node = -np.ones(len(pts), np.int64)
        node[free] = np.arange(free.sum())
        grid_node = node.reshape(shape)
        rows, cols, weights = [], [], []
        for off in _forward_offsets():
            a = grid_node[_slices(off, shape, 0)]
            b = grid_node[_slices(off, shape, 1)]
            both = (a >= 0) & (b >= 0)
            ia, ib = a[both], b[both]
            length = grid_mm * math.sqrt(sum(o * o for o in off))
            cmean = 0.5 * (cl_grid[free][ia] + cl_grid[free][ib])
            rows.append(ia)
            cols.append(ib)
            weights.append(length * (1.0 + 3.0 / cmean))
        n_free = int(free.sum())
        graph = sp.coo_matrix(
            (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
            shape=(n_free, n_free),
        ).tocsr()
        free_pts = pts[free]
        # start: the free node nearest to the nostril centre, within 6 mm of the face
        d0 = np.linalg.norm(free_pts - np.asarray(nostril_mm), axis=1)
        d0[free_pts[:, 1] > nostril_mm[1] + 6.0] = np.inf
        if not np.isfinite(d0.min()):
            continue
        start = int(np.argmin(d0))
        dist, pred = dijkstra(graph, directed=False, indices=start, return_predecessors=True)

        def reachable(q: np.ndarray, dist=dist, node=node) -> np.ndarray:
            ij = np.rint((q - lo) / grid_mm).astype(int)
            ok = np.all((ij >= 0) & (ij < np.asarray(shape)), axis=1)
            out = np.zeros(len(q), bool)
            flat = np.ravel_multi_index(ij[ok].T, shape)
            nid = node[flat]
            out[np.flatnonzero(ok)] = (nid >= 0) & np.isfinite(dist[np.maximum(nid, 0)])
            return out

        try:
            view, _ = find_viewpoint(surface, target, clearance_mm, reachable)
        except AnatomyError:
            continue
        ij = np.rint((view - lo) / grid_mm).astype(int)
        end = int(node[np.ravel_multi_index(ij, shape)])
        chain = [end]
        while chain[-1] != start:
            chain.append(int(pred[chain[-1]]))
        raw = np.vstack([np.asarray(nostril_mm, float)[None], free_pts[chain[::-1]], view[None]])
        for sigma in (4.0, 2.0, 1.0, 0.0):
            path = _resample(_smooth(raw, sigma), 1.0)
            check = _resample(path, 0.25)
            if clearance(surface, check).min() >= clearance_mm:
                return path
    raise AnatomyError(
        "airway_path",
        f"no path from the nostril to a view of the {target.name} keeps {clearance_mm:g} mm from the tissue",
    )


def _forward_offsets() -> list[tuple[int, int, int]]:
    offs = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if (dx, dy, dz) > (0, 0, 0):
                    offs.append((dx, dy, dz))
    return offs


def _slices(off: tuple[int, int, int], shape: tuple[int, ...], which: int) -> tuple[slice, ...]:
    """Slices pairing voxel v (which=0) with v + off (which=1) inside ``shape``."""
    out = []
    for o, n in zip(off, shape, strict=True):
        if o >= 0:
            out.append(slice(0, n - o) if which == 0 else slice(o, n))
        else:
            out.append(slice(-o, n) if which == 0 else slice(0, n + o))
    return tuple(out)
