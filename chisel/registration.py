"""Rigid registration of a (scaled) depth estimate to the model surface, with Open3D.

Global: FPFH features + RANSAC (``registration_ransac_based_on_feature_matching``), as
in the paper, because changed (removed) tissue must not pull the alignment; then ICP.
Refinement: point-to-plane ICP with a Tukey robust kernel, coarse to fine correspondence
distances, so points on removed tissue (several mm deeper than the model) are rejected:
Open3D's ICP after RANSAC (:func:`register_global`), and per frame
:func:`icp_similarity`, which also solves the monocular depth scale.

All transforms returned are ``T_model_from_est``: they map the estimate's world points
(placed with the tracked camera pose) onto the model (world = CT frame). For a camera
this is a correction applied on the world side: ``T_world_from_cam_corrected =
T_model_from_est @ T_world_from_cam_tracked``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING

import numba
import numpy as np
from scipy.spatial import cKDTree

from chisel.core.config import check_fields
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import rotation_angle_deg, transform_points

if TYPE_CHECKING:
    import open3d as o3d


def _o3d() -> ModuleType:
    """Open3D, imported on first use: the updater's own ICP does not need it, only the
    global search fallback and the Open3D ICP do, and its import costs ~1 s per process."""
    import open3d  # noqa: PLC0415

    return open3d


@dataclass(frozen=True)
class RegistrationConfig:
    """Parameters of RANSAC + ICP registration (mm)."""

    voxel_mm: float = 1.0
    """Down-sampling voxel of the global (FPFH + RANSAC) stage, mm."""
    icp_max_dist_mm: tuple[float, ...] = (3.0, 1.5, 0.75)
    """Correspondence distances of the coarse-to-fine ICP passes, mm."""
    tukey_k_mm: float = 0.5
    """Tukey kernel width of the point-to-plane ICP, mm: residuals beyond it count 0."""
    icp_max_iter: int = 10
    """ICP iterations per pass (at most)."""
    fitness_dist_mm: float = 1.5
    """Inlier distance used to report fitness (fraction of estimate points near the model)."""
    min_fitness: float = 0.3
    """A registration with fitness below this fails; its frames are skipped, never fused."""
    max_correction_mm: float = 10.0
    """A correction moving the estimate's centroid further than this fails (implausible)."""
    max_correction_deg: float = 15.0
    """A correction rotating more than this fails (implausible for a tracked endoscope)."""
    ransac_max_iter: int = 50_000
    """RANSAC iteration cap."""
    ransac_confidence: float = 0.999
    """RANSAC early-stop confidence."""
    pose_prior: float = 0.05
    """Per-frame ICP: weight of a prior keeping the camera centre at its starting point,
    as a fraction of the total correspondence weight per mm^2. It breaks the scale /
    distance ambiguity of a nearly planar view and costs a bias of about this fraction of
    the true offset in well-constrained directions."""
    tracking_accuracy_mm: float = 3.0
    """The tracker's accuracy (hand-eye calibration included), mm. A correction that moves
    the camera further than this (a step's hand-eye correction F, or one frame's) is not
    applied: it explains the depth estimate's shape error, not the pose."""
    tracking_accuracy_deg: float = 3.0
    """The same for F's rotation, degrees."""
    max_scale_change: float = 0.2
    """The depth scale solved by ICP stays within a factor (1 +- this) of the scale anchored to
    the render (robust median of ratios); a registration that leaves the range has collapsed
    (flat walls let scale trade against distance: 0.33 or 1e-6 was seen) and fails."""
    seed: int = 0
    """Seed of Open3D's random generator (RANSAC sampling): same seed, same result."""

    def __post_init__(self) -> None:
        check_fields(self, "registration")
        if self.voxel_mm <= 0:
            raise InvalidInputError("voxel_mm", f"must be > 0, got {self.voxel_mm}")
        if not self.icp_max_dist_mm or min(self.icp_max_dist_mm) <= 0:
            raise InvalidInputError(
                "icp_max_dist_mm", f"need positive distances, got {self.icp_max_dist_mm}"
            )
        if self.tracking_accuracy_mm <= 0 or self.tracking_accuracy_deg <= 0:
            raise InvalidInputError(
                "tracking_accuracy",
                f"must be > 0, got {self.tracking_accuracy_mm} mm / {self.tracking_accuracy_deg} deg",
            )
        if not 0.0 < self.max_scale_change < 1.0:
            raise InvalidInputError(
                "max_scale_change", f"must be in (0, 1), got {self.max_scale_change}"
            )
        if self.tukey_k_mm <= 0 or self.fitness_dist_mm <= 0:
            raise InvalidInputError("tukey_k_mm", "kernel width and fitness distance must be > 0")
        if not 0.0 <= self.min_fitness <= 1.0:
            raise InvalidInputError("min_fitness", f"must be in [0, 1], got {self.min_fitness}")


@dataclass
class RegistrationResult:
    """Outcome of one registration."""

    T_model_from_est: np.ndarray
    """(4, 4) float64 correction, mm (identity when registration failed or was off)."""
    fitness: float
    """Fraction of estimate points within ``fitness_dist_mm`` of the model after alignment."""
    rmse_mm: float
    """RMS distance of those inliers, mm."""
    method: str
    """"ransac+icp", "icp" or "none"."""
    ok: bool = True
    """False when the result failed a check (fitness, plausibility)."""
    reason: str = ""
    """Why it failed, empty when ok."""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "T_model_from_est": np.asarray(self.T_model_from_est).tolist(),
            "fitness": float(self.fitness),
            "rmse_mm": float(self.rmse_mm),
            "method": self.method,
            "ok": bool(self.ok),
            "reason": self.reason,
            **self.extra,
        }


def make_cloud(points_mm: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """Open3D point cloud. points_mm : (N, 3) float, mm; normals : (N, 3) unit or None."""
    o3d = _o3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_mm, np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    return pcd


def correction_size(T_model_from_est: np.ndarray, center_mm: np.ndarray) -> tuple[float, float]:
    """(displacement of ``center_mm`` in mm, rotation angle in degrees) of a correction."""
    c = np.asarray(center_mm, dtype=np.float64)
    moved = transform_points(T_model_from_est, c[None])[0]
    return float(np.linalg.norm(moved - c)), rotation_angle_deg(T_model_from_est[:3, :3])


def _fpfh(pcd: o3d.geometry.PointCloud, voxel: float) -> o3d.pipelines.registration.Feature:
    o3d = _o3d()
    reg = o3d.pipelines.registration
    return reg.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    )


def icp_refine(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    cfg: RegistrationConfig,
) -> np.ndarray:
    """Coarse-to-fine point-to-plane ICP with a Tukey kernel; returns ``T_target_from_source``.

    ``target`` must carry normals.
    """
    reg = _o3d().pipelines.registration
    T = np.asarray(init, dtype=np.float64)
    for dist in cfg.icp_max_dist_mm:
        kernel = reg.TukeyLoss(k=max(cfg.tukey_k_mm, dist / 2.0))
        res = reg.registration_icp(
            source,
            target,
            dist,
            T,
            reg.TransformationEstimationPointToPlane(kernel),
            reg.ICPConvergenceCriteria(max_iteration=cfg.icp_max_iter),
        )
        T = np.asarray(res.transformation, dtype=np.float64)
    return T


def evaluate(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    T: np.ndarray,
    cfg: RegistrationConfig,
) -> tuple[float, float]:
    """(fitness, inlier RMSE mm) of ``T`` at ``cfg.fitness_dist_mm``."""
    reg = _o3d().pipelines.registration
    ev = reg.evaluate_registration(source, target, cfg.fitness_dist_mm, T)
    return float(ev.fitness), float(ev.inlier_rmse)


def check_result(
    T: np.ndarray,
    fitness: float,
    rmse: float,
    method: str,
    center: np.ndarray,
    cfg: RegistrationConfig,
    scale: float = 1.0,
) -> RegistrationResult:
    """Package a registration, failing it on low fitness, an implausible correction, or a
    scale refinement outside ``1 +- cfg.max_scale_change`` (collapse)."""
    shift_mm, angle_deg = correction_size(T, center)
    extra = {"correction_mm": shift_mm, "correction_deg": angle_deg}
    lo, hi = 1.0 / (1.0 + cfg.max_scale_change), 1.0 + cfg.max_scale_change
    if not (lo <= scale <= hi):
        return RegistrationResult(
            T, fitness, rmse, method, False,
            f"scale refinement {scale:.3g} outside [{lo:.3g}, {hi:.3g}] of the render's scale", extra,
        )  # fmt: skip
    if fitness < cfg.min_fitness:
        return RegistrationResult(
            T, fitness, rmse, method, False,
            f"fitness {fitness:.3f} < min_fitness {cfg.min_fitness}", extra,
        )  # fmt: skip
    if shift_mm > cfg.max_correction_mm or angle_deg > cfg.max_correction_deg:
        return RegistrationResult(
            T, fitness, rmse, method, False,
            f"implausible correction {shift_mm:.2f} mm / {angle_deg:.2f} deg (limits "
            f"{cfg.max_correction_mm} mm / {cfg.max_correction_deg} deg)", extra,
        )  # fmt: skip
    return RegistrationResult(T, fitness, rmse, method, True, "", extra)


def register_global(
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    target_normals: np.ndarray,
    cfg: RegistrationConfig,
    init: np.ndarray | None = None,
) -> RegistrationResult:
    """RANSAC (FPFH) + robust ICP of estimate points onto model surface points.

    source_mm : (N, 3) float64 estimate points in world mm (placed with tracked poses).
    target_mm : (M, 3) float64 model surface points, world mm; target_normals : (M, 3).
    init : (4, 4) prior correction (identity = trust the tracker). ICP is run both from
    the RANSAC solution and from ``init``; the one with the higher fitness wins, so a
    RANSAC failure on a symmetric scene cannot make things worse than the tracker.
    """
    o3d = _o3d()
    reg = o3d.pipelines.registration
    src = np.asarray(source_mm, np.float64)
    tgt = np.asarray(target_mm, np.float64)
    if len(src) < 10 or len(tgt) < 10:
        raise InvalidInputError(
            "registration", f"too few points: {len(src)} source, {len(tgt)} target"
        )
    init = np.eye(4) if init is None else np.asarray(init, np.float64)
    o3d.utility.random.seed(int(cfg.seed))
    v = cfg.voxel_mm
    src_pcd = make_cloud(src).voxel_down_sample(v)
    tgt_pcd = make_cloud(tgt, target_normals).voxel_down_sample(v)
    tgt_pcd.normalize_normals()
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * v, max_nn=30)
    src_pcd.estimate_normals(search)
    src_f = _fpfh(src_pcd, v)
    tgt_f = _fpfh(tgt_pcd, v)
    ransac = reg.registration_ransac_based_on_feature_matching(
        src_pcd,
        tgt_pcd,
        src_f,
        tgt_f,
        True,
        1.5 * v,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [
            reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            reg.CorrespondenceCheckerBasedOnDistance(1.5 * v),
        ],
        reg.RANSACConvergenceCriteria(cfg.ransac_max_iter, cfg.ransac_confidence),
    )
    center = src.mean(axis=0)
    candidates = []
    for name, start in (("ransac+icp", np.asarray(ransac.transformation)), ("icp", init)):
        # The sequence-level result only seeds per-frame ICP: the 1-voxel target is enough.
        T = icp_refine(src_pcd, tgt_pcd, start, cfg)
        fit, rmse = evaluate(src_pcd, tgt_pcd, T, cfg)
        shift, ang = correction_size(T, center)
        plausible = shift <= cfg.max_correction_mm and ang <= cfg.max_correction_deg
        candidates.append((plausible, fit, -rmse, name, T))
    candidates.sort(key=lambda c: (c[0], c[1], c[2]), reverse=True)
    _, fit, neg_rmse, name, T = candidates[0]
    res = check_result(T, fit, -neg_rmse, name, center, cfg)
    res.extra["ransac_fitness"] = float(ransac.fitness)
    return res


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


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


@numba.njit(cache=True)
def _rotvec_to_matrix(w):
    """(3, 3) rotation of a rotation vector (Rodrigues)."""
    a = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    out = np.eye(3)
    if a < 1e-15:
        return out
    k0, k1, k2 = w[0] / a, w[1] / a, w[2] / a
    K = np.array([[0.0, -k2, k1], [k2, 0.0, -k0], [-k1, k0, 0.0]])
    return out + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)


@numba.njit(cache=True)
def _matrix_to_rotvec(R):
    """Rotation vector of a (3, 3) rotation (small-angle safe; angles well below 180 deg)."""
    c = min(max((R[0, 0] + R[1, 1] + R[2, 2] - 1.0) / 2.0, -1.0), 1.0)
    a = np.arccos(c)
    f = 0.5 if a < 1e-8 else a / (2.0 * np.sin(a))
    return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) * f


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


def robust_mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """Robust average of rigid transforms: median rotation vector and median translation.

    transforms : list of (4, 4) float64 rigid transforms that differ by small rotations.
    """
    from scipy.spatial.transform import Rotation

    if not transforms:
        raise InvalidInputError("transforms", "need at least one transform to average")
    Ts = np.stack(transforms)
    rv = Rotation.from_matrix(Ts[:, :3, :3]).as_rotvec()
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(np.median(rv, axis=0)).as_matrix()
    out[:3, 3] = np.median(Ts[:, :3, 3], axis=0)
    return out
