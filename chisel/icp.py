"""Per-frame robust ICP that also solves the monocular depth scale (7 DoF), against the
model surface indexed once per step (numba, CPU).

Each pass uses nearest-neighbour correspondences within a distance and Tukey weights on
the point-to-plane residual, so points on removed tissue (deeper than the model) carry no
weight; the scale acts about the camera centre and stays within a bounded factor of the
scale anchored to the render (see :class:`chisel.registration.RegistrationConfig`). The
global Open3D stages live in :mod:`chisel.registration`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from chisel.core.errors import InvalidInputError
from chisel.registration import RegistrationConfig


class SurfaceIndex:
    """Model surface points with normals and a k-d tree, built once per step.

    points_mm : (N, 3) float64 world mm (mesh vertices); normals : (N, 3) unit.
    grid : optional ``(origin_mm (3,), voxel_mm, shape (3,))`` of a voxel grid over the
    surface. With it, :meth:`query` memoises the nearest vertex of each voxel centre the
    first time a point falls in that voxel, so ICP iterations (and later frames) cost an
    array lookup instead of a tree search. The answer is the vertex nearest to the
    voxel's centre (at most half a voxel diagonal from the exact nearest neighbour),
    which point-to-plane residuals tolerate.
    """

    def __init__(
        self,
        points_mm: np.ndarray,
        normals: np.ndarray,
        grid: tuple[np.ndarray, float, tuple[int, int, int]] | None = None,
        max_dist_mm: float = 4.0,
    ) -> None:
        self.points = np.asarray(points_mm, dtype=np.float64)
        self.normals = np.asarray(normals, dtype=np.float64)
        if len(self.points) < 10 or self.normals.shape != self.points.shape:
            raise InvalidInputError(
                "surface", f"need >= 10 points with normals, got {self.points.shape}"
            )
        self.tree = cKDTree(self.points)
        self.max_dist_mm = float(max_dist_mm)
        self._grid = None
        if grid is not None:
            origin, voxel, shape = grid
            self._grid = (
                np.asarray(origin, np.float64),
                float(voxel),
                tuple(int(x) for x in shape),
            )
            self._cache = np.full(int(np.prod(shape)), -2, dtype=np.int32)  # -2 = not looked up

    @property
    def grid(self) -> tuple[np.ndarray, float, np.ndarray, np.ndarray] | None:
        """(origin_mm, voxel_mm, shape (3,) int64, memo (flat int32)) or None without a grid."""
        if self._grid is None:
            return None
        origin, voxel, shape = self._grid
        return origin, voxel, np.asarray(shape, dtype=np.int64), self._cache

    def query(self, points_mm: np.ndarray, dist_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Nearest surface vertex within ``dist_mm``: (distance (N,), index (N,)).

        Misses have distance inf and index ``len(points)`` (as scipy's cKDTree).
        """
        y = np.ascontiguousarray(points_mm, dtype=np.float64)
        n = len(self.points)
        if self._grid is None or dist_mm > self.max_dist_mm:
            return self.tree.query(y, distance_upper_bound=dist_mm)
        origin, voxel, shape = self._grid
        shape_a = np.asarray(shape, dtype=np.int64)
        d, idx = _grid_nearest(y, origin, voxel, shape_a, self._cache, self.points, dist_mm)
        unknown = idx == -2
        if unknown.any():
            # First visit of these voxels: one tree search per voxel centre, memoised.
            ijk = np.rint((y[unknown] - origin) / voxel).astype(np.int64)
            u = np.unique(np.ravel_multi_index(ijk.T, shape))
            centres = np.stack(np.unravel_index(u, shape), axis=1) * voxel + origin
            reach = self.max_dist_mm + voxel
            _, nn = self.tree.query(centres, distance_upper_bound=reach)
            self._cache[u] = np.where(nn >= n, -1, nn).astype(np.int32)
            d, idx = _grid_nearest(y, origin, voxel, shape_a, self._cache, self.points, dist_mm)
        idx[idx < 0] = n
        return d, idx


@numba.njit(cache=True, nogil=True)
def _grid_nearest(y, origin, voxel, shape, cache, points, dist_mm):
    """Memoised nearest vertex per voxel: (distance (N,), index (N,)); index -1 = no vertex
    within reach or outside the grid, -2 = voxel not looked up yet (distance inf)."""
    n = y.shape[0]
    d = np.full(n, np.inf)
    idx = np.full(n, -1, dtype=np.int64)
    nx, ny, nz = shape[0], shape[1], shape[2]
    for a in range(n):
        i = int(np.rint((y[a, 0] - origin[0]) / voxel))
        j = int(np.rint((y[a, 1] - origin[1]) / voxel))
        k = int(np.rint((y[a, 2] - origin[2]) / voxel))
        if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
            continue
        c = cache[(i * ny + j) * nz + k]
        if c == -2:
            idx[a] = -2
            continue
        if c < 0:
            continue
        dx = y[a, 0] - points[c, 0]
        dy = y[a, 1] - points[c, 1]
        dz = y[a, 2] - points[c, 2]
        dd = np.sqrt(dx * dx + dy * dy + dz * dz)
        if dd <= dist_mm:
            d[a] = dd
            idx[a] = c
    return d, idx


@numba.njit(cache=True, nogil=True)
def _normal_equations(y_rel, c_new, idx, points, normals, k, with_scale):
    """Tukey-weighted point-to-plane normal equations of one ICP iteration.

    Unknowns (rotation vector (3), centre shift (3)[, log scale]); returns (A, b, sum of
    weights, number of correspondences). ``idx >= len(points)`` marks a miss.
    """
    m = 7 if with_scale else 6
    A = np.zeros((m, m))
    b = np.zeros(m)
    J = np.zeros(m)
    npts = points.shape[0]
    wsum = 0.0
    count = 0
    for a in range(y_rel.shape[0]):
        c = idx[a]
        if c >= npts:
            continue
        count += 1
        xr, yr_, zr = y_rel[a, 0], y_rel[a, 1], y_rel[a, 2]
        n0, n1, n2 = normals[c, 0], normals[c, 1], normals[c, 2]
        r = ((xr + c_new[0] - points[c, 0]) * n0 + (yr_ + c_new[1] - points[c, 1]) * n1
             + (zr + c_new[2] - points[c, 2]) * n2)  # fmt: skip
        if abs(r) >= k:
            continue
        t = 1.0 - (r / k) ** 2
        w = t * t
        J[0] = yr_ * n2 - zr * n1
        J[1] = zr * n0 - xr * n2
        J[2] = xr * n1 - yr_ * n0
        J[3] = n0
        J[4] = n1
        J[5] = n2
        if with_scale:
            J[6] = xr * n0 + yr_ * n1 + zr * n2
        for p in range(m):
            wp = w * J[p]
            b[p] -= wp * r
            for q in range(p, m):
                A[p, q] += wp * J[q]
        wsum += w
    for p in range(m):
        for q in range(p):
            A[p, q] = A[q, p]
    return A, b, wsum, count


@numba.njit(cache=True, nogil=True)
def _rotvec_to_matrix(w):
    """(3, 3) rotation of a rotation vector (Rodrigues)."""
    a = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    out = np.eye(3)
    if a < 1e-15:
        return out
    k0, k1, k2 = w[0] / a, w[1] / a, w[2] / a
    K = np.array([[0.0, -k2, k1], [k2, 0.0, -k0], [-k1, k0, 0.0]])
    return out + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)


@numba.njit(cache=True, nogil=True)
def _matrix_to_rotvec(R):
    """Rotation vector of a (3, 3) rotation (small-angle safe; angles well below 180 deg)."""
    c = min(max((R[0, 0] + R[1, 1] + R[2, 2] - 1.0) / 2.0, -1.0), 1.0)
    a = np.arccos(c)
    f = 0.5 if a < 1e-8 else a / (2.0 * np.sin(a))
    return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) * f


@numba.njit(cache=True, nogil=True)
def _solve_small(A, b):
    """x with A x = b by Gaussian elimination with partial pivoting; (x, ok)."""
    m = A.shape[0]
    M = A.copy()
    x = b.copy()
    for col in range(m):
        piv = col
        for r in range(col + 1, m):
            if abs(M[r, col]) > abs(M[piv, col]):
                piv = r
        if not abs(M[piv, col]) > 0.0:  # also catches NaN
            return x, False
        if piv != col:
            for q in range(m):
                M[col, q], M[piv, q] = M[piv, q], M[col, q]
            x[col], x[piv] = x[piv], x[col]
        for r in range(col + 1, m):
            f = M[r, col] / M[col, col]
            for q in range(col, m):
                M[r, q] -= f * M[col, q]
            x[r] -= f * x[col]
    for col in range(m - 1, -1, -1):
        acc = x[col]
        for q in range(col + 1, m):
            acc -= M[col, q] * x[q]
        x[col] = acc / M[col, col]
    return x, True


# Outcomes of :func:`_icp_iterate`.
_RAN_OUT, _CONVERGED, _STOPPED, _NEED_LOOKUP = 0, 1, 2, 3


@numba.njit(cache=True, nogil=True)
def _icp_iterate(
    rel, sigma, R, c_new, idx_given, grid_origin, voxel, grid_shape, cache, use_grid,
    points, normals, dist, k, with_scale, prior, pose_prior, c_prior, R_prior, rho2, max_iter,
):  # fmt: skip
    """Up to ``max_iter`` ICP iterations at one correspondence distance, in one call.

    Correspondences come from the memo grid of :class:`SurfaceIndex` (``use_grid``), or,
    for one iteration only, from ``idx_given``. Returns (R, c_new, sigma, iterations
    started, outcome): ``_NEED_LOOKUP`` means a point fell in a voxel not looked up yet
    (nothing was done for that iteration: fill the memo and call again), ``_STOPPED``
    fewer than 10 correspondences or a singular system, ``_CONVERGED`` the update fell
    below rotation 2e-5 rad, shift 1e-3 mm, scale 2e-5.
    """
    n = rel.shape[0]
    npts = points.shape[0]
    y_rel = np.empty((n, 3))
    y = np.empty((n, 3))
    m = 7 if with_scale else 6
    for it in range(max_iter):
        for a in range(n):
            for r in range(3):
                v = sigma * (R[r, 0] * rel[a, 0] + R[r, 1] * rel[a, 1] + R[r, 2] * rel[a, 2])
                y_rel[a, r] = v
                y[a, r] = v + c_new[r]
        if use_grid:
            _, idx = _grid_nearest(y, grid_origin, voxel, grid_shape, cache, points, dist)
            for a in range(n):
                if idx[a] == -2:
                    return R, c_new, sigma, it, _NEED_LOOKUP
                if idx[a] < 0:
                    idx[a] = npts
        else:
            idx = idx_given
        A, b, wsum, count = _normal_equations(y_rel, c_new, idx, points, normals, k, with_scale)
        if count < 10:
            return R, c_new, sigma, it + 1, _STOPPED
        if prior:
            lam = pose_prior * wsum
            lam_r = lam * rho2
            dR = _matrix_to_rotvec(R_prior @ R.T)
            for r in range(3):
                A[3 + r, 3 + r] += lam
                b[3 + r] += lam * (c_prior[r] - c_new[r])
                A[r, r] += lam_r
                b[r] += lam_r * dR[r]
        tr = 0.0
        for r in range(m):
            tr += A[r, r]
        for r in range(m):
            A[r, r] += 1e-9 * tr + 1e-12
        x, ok = _solve_small(A, b)
        if not ok:
            return R, c_new, sigma, it + 1, _STOPPED
        R = _rotvec_to_matrix(x[:3]) @ R
        c_new = c_new + x[3:6]
        if with_scale:
            sigma *= np.exp(x[6])
        small = (
            max(abs(x[0]), abs(x[1]), abs(x[2])) < 2e-5
            and max(abs(x[3]), abs(x[4]), abs(x[5])) < 1e-3
            and (not with_scale or abs(x[6]) < 2e-5)
        )
        if small:
            return R, c_new, sigma, it + 1, _CONVERGED
    return R, c_new, sigma, max_iter, _RAN_OUT


@dataclass
class SimilarityResult:
    """Outcome of :func:`icp_similarity`."""

    T_model_from_est: np.ndarray
    """(4, 4) float64 rigid correction (world side), mm."""
    scale: float
    """Depth multiplier about the camera centre (1 = the scale passed in was right)."""
    fitness: float
    """Fraction of source points within ``fitness_dist_mm`` of the surface."""
    rmse_mm: float
    """Point-to-plane RMS of those inliers, mm."""
    iterations: int


def icp_similarity(
    source_mm: np.ndarray,
    center_mm: np.ndarray,
    surface: SurfaceIndex,
    init: np.ndarray,
    cfg: RegistrationConfig,
    estimate_scale: bool = True,
    prior: bool = False,
) -> SimilarityResult:
    """Robust point-to-plane ICP with an optional scale about the camera centre (7 DoF).

    A monocular estimate's scale and the camera's distance to the scene trade off for a
    single view; solving them jointly removes the bias a fixed scale would leave in the
    pose (and vice versa). Each pass uses nearest-neighbour correspondences within
    ``dist`` and Tukey weights of width max(tukey_k_mm, dist / 2) on the point-to-plane
    residual, so points on removed tissue (deeper than the model) carry no weight.

    source_mm : (N, 3) float64 estimate points in world mm placed with the tracked pose.
    center_mm : (3,) the tracked camera centre (the scale acts about it), mm.
    init : (4, 4) starting rigid correction ``T_model_from_est``.
    prior : keep the corrected camera centre and orientation near ``init``'s (weight
        ``cfg.pose_prior``; rotation measured in mm at the points' median distance); use
        it when ``init`` already predicts the pose well (a known hand-eye error).
    The corrected points are ``R * scale * (p - c) + c'`` with ``c' = init(c)`` refined.
    """
    p = np.asarray(source_mm, dtype=np.float64)
    if len(p) < 10:
        raise InvalidInputError("registration", f"too few estimate points: {len(p)}")
    c = np.asarray(center_mm, dtype=np.float64)
    init = np.asarray(init, dtype=np.float64)
    R = init[:3, :3].copy()
    c_new = init[:3, :3] @ c + init[:3, 3]
    c_prior = c_new.copy()
    R_prior = R.copy()
    sigma = 1.0
    rel = p - c
    rho2 = float(np.median(np.einsum("ij,ij->i", rel, rel)))
    it = 0
    # With a prior and a known scale the start is already close: skip the coarsest pass.
    # (A scale from the render at the tracked pose can be off by tens of % in a tube.)
    skip = prior and not estimate_scale and len(cfg.icp_max_dist_mm) > 1
    dists = cfg.icp_max_dist_mm[1:] if skip else cfg.icp_max_dist_mm
    grid = surface.grid
    # Placeholders for the numba call when the memo grid is not used (never read then).
    no_grid = (np.zeros(3), 1.0, np.ones(3, np.int64), np.zeros(1, dtype=np.int32))
    no_idx = np.zeros(0, dtype=np.int64)
    for dist in dists:
        k = max(cfg.tukey_k_mm, dist / 2.0)
        # The memo grid answers every lookup inside numba; a voxel met for the first time
        # (or a search beyond the memo's reach) comes back here for the k-d tree.
        use_grid = grid is not None and dist <= surface.max_dist_mm
        origin, voxel, shape_a, cache = grid if use_grid and grid is not None else no_grid
        left = cfg.icp_max_iter
        while left > 0:
            if use_grid:
                idx, budget = no_idx, left
            else:
                _, idx = surface.query(sigma * rel @ R.T + c_new, dist)
                budget = 1
            R, c_new, sigma, started, outcome = _icp_iterate(
                rel, sigma, R, c_new, idx, origin, voxel, shape_a, cache, use_grid,
                surface.points, surface.normals, dist, k, estimate_scale, prior,
                cfg.pose_prior, c_prior, R_prior, rho2, budget,
            )  # fmt: skip
            it += started
            left -= started
            if outcome == _NEED_LOOKUP:
                surface.query(sigma * rel @ R.T + c_new, dist)  # fills the memo
            elif outcome != _RAN_OUT:
                break
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c_new - R @ c
    y = sigma * rel @ R.T + c_new
    d, idx = surface.query(y, cfg.fitness_dist_mm)
    ok = np.isfinite(d)
    fitness = float(ok.mean())
    if ok.any():
        r = np.einsum("ij,ij->i", y[ok] - surface.points[idx[ok]], surface.normals[idx[ok]])
        rmse = float(np.sqrt(np.mean(r**2)))
    else:
        rmse = float("nan")
    return SimilarityResult(T, sigma, fitness, rmse, it)


def icp_hand_eye(
    clouds_cam: list[np.ndarray],
    poses: list[np.ndarray],
    surface: SurfaceIndex,
    init: np.ndarray,
    cfg: RegistrationConfig,
    estimate_scale: bool = True,
) -> tuple[np.ndarray, np.ndarray, float]:
    """One camera-side correction F for all frames at once, by robust point-to-plane ICP.

    The tracker's hand-eye error is the same in every frame: a frame's points ``x``
    (camera mm, already scaled) land at ``T_i F (s_i x)`` in the world. F (6 DoF, in the
    camera frame) is solved from every frame's points together, each frame with its own
    depth scale ``s_i`` about its camera centre when ``estimate_scale``; Tukey weights as in
    :func:`icp_similarity`. A frame that sees a plane cannot fix F's rotation alone, and
    the median of per-frame corrections carries its arbitrary rotation; the joint normal
    equations weight each direction by the frames that constrain it.

    Returns (F (4, 4), per-frame scales (n,), fitness of all points after alignment).
    """
    n_frames = len(clouds_cam)
    fid = np.concatenate([np.full(len(c), i) for i, c in enumerate(clouds_cam)])
    X = np.concatenate(clouds_cam).astype(np.float64)
    Rw = np.stack([np.asarray(T, np.float64)[:3, :3] for T in poses])[fid]
    tw = np.stack([np.asarray(T, np.float64)[:3, 3] for T in poses])[fid]
    F = np.asarray(init, dtype=np.float64).copy()
    logs = np.zeros(n_frames)

    def place() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        zs = np.exp(logs)[fid, None] * X
        z = zs @ F[:3, :3].T + F[:3, 3]
        return zs, z, np.einsum("nij,nj->ni", Rw, z) + tw

    for dist in cfg.icp_max_dist_mm:
        k = max(cfg.tukey_k_mm, dist / 2.0)
        for _ in range(cfg.icp_max_iter):
            zs, z, y = place()
            d, idx = surface.query(y, dist)
            ok = np.isfinite(d)
            if ok.sum() < 10:
                break
            nw = surface.normals[idx[ok]]
            r = np.einsum("ij,ij->i", y[ok] - surface.points[idx[ok]], nw)
            w = np.where(np.abs(r) < k, (1.0 - (r / k) ** 2) ** 2, 0.0)
            nc = np.einsum("nji,nj->ni", Rw[ok], nw)  # the normal in the camera frame
            J = np.hstack([np.cross(z[ok], nc), nc])
            A = J.T @ (w[:, None] * J)
            b = -J.T @ (w * r)
            ds = np.zeros(n_frames)
            if estimate_scale:
                # Each frame's log scale is its own unknown: eliminated (Schur complement)
                # so that F and the scales take one Gauss-Newton step together.
                f = fid[ok]
                js = np.einsum("ij,ij->i", zs[ok] @ F[:3, :3].T, nc)
                D = np.bincount(f, w * js * js, n_frames) + 1e-12
                bs = np.bincount(f, -w * js * r, n_frames)
                B = np.stack([np.bincount(f, w * js * J[:, c], n_frames) for c in range(6)], 1)
                A = A - B.T @ (B / D[:, None])
                b = b - B.T @ (bs / D)
            A += (1e-9 * np.trace(A) + 1e-12) * np.eye(6)
            x = np.linalg.solve(A, b)
            if estimate_scale:
                ds = (bs - B @ x) / D
                logs += ds
            dR = _rotvec_to_matrix(x[:3])
            F[:3, :3] = dR @ F[:3, :3]
            F[:3, 3] = dR @ F[:3, 3] + x[3:]
            if (np.abs(x[:3]).max() < 2e-5 and np.abs(x[3:]).max() < 1e-3
                    and np.abs(ds).max() < 2e-5):  # fmt: skip
                break
    _, _, y = place()
    d, _ = surface.query(y, cfg.fitness_dist_mm)
    return F, np.exp(logs), float(np.isfinite(d).mean())
