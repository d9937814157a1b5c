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

import numpy as np

from chisel.core.config import check_fields, check_ranges
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import rotation_angle_deg, transform_points
from chisel.io.limits import MAX_VOXEL_SIZE_MM, MIN_VOXEL_SIZE_MM

if TYPE_CHECKING:
    import open3d as o3d


def _o3d() -> ModuleType:
    """Open3D, imported on first use: the updater's own ICP does not need it, only the
    global search fallback and the Open3D ICP do, and its import costs ~1 s per process."""
    import open3d  # noqa: PLC0415

    return open3d


MAX_DISTANCE_MM = 1e3
"""Largest distance a registration setting may name, mm: a metre is past any endoscopic
scene (a sinus is ~50 mm across), so a larger value is a unit slip (um for mm), not a
setting."""
MAX_ICP_ITER = 10_000
"""Most ICP iterations per pass: each one queries every point's nearest neighbour, and ICP
has converged (or diverged) long before (the default is 10, Open3D's own 30)."""
MAX_RANSAC_ITER = 10_000_000
"""Most RANSAC iterations: 200x the default, minutes of sampling without an early stop;
Open3D takes a C ``int`` and died allocating for -1."""
MAX_SEED = 2**31 - 1
"""Largest seed: Open3D's random generator takes a signed 32-bit C ``int``."""


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
        check_fields(self, "registration")  # kinds, NaN and infinity
        d, dists = MAX_DISTANCE_MM, self.icp_max_dist_mm
        checks = (
            ("voxel_mm", MIN_VOXEL_SIZE_MM <= self.voxel_mm <= MAX_VOXEL_SIZE_MM,
             f"in [{MIN_VOXEL_SIZE_MM:g}, {MAX_VOXEL_SIZE_MM:g}] mm"),
            ("icp_max_dist_mm", bool(dists) and all(0 < x <= d for x in dists),
             f"one or more distances in (0, {d:g}] mm"),
            ("tukey_k_mm", 0 < self.tukey_k_mm <= d, f"in (0, {d:g}] mm"),
            ("icp_max_iter", 1 <= self.icp_max_iter <= MAX_ICP_ITER, f"in [1, {MAX_ICP_ITER}]"),
            ("fitness_dist_mm", 0 < self.fitness_dist_mm <= d, f"in (0, {d:g}] mm"),
            ("min_fitness", 0 <= self.min_fitness <= 1, "in [0, 1]"),
            ("max_correction_mm", 0 < self.max_correction_mm <= d, f"in (0, {d:g}] mm"),
            ("max_correction_deg", 0 < self.max_correction_deg <= 180, "in (0, 180] deg"),
            ("ransac_max_iter", 1 <= self.ransac_max_iter <= MAX_RANSAC_ITER,
             f"in [1, {MAX_RANSAC_ITER}]"),
            ("ransac_confidence", 0 < self.ransac_confidence <= 1, "in (0, 1]"),
            ("pose_prior", 0 <= self.pose_prior <= 1, "in [0, 1]"),
            ("tracking_accuracy_mm", 0 < self.tracking_accuracy_mm <= d, f"in (0, {d:g}] mm"),
            ("tracking_accuracy_deg", 0 < self.tracking_accuracy_deg <= 180, "in (0, 180] deg"),
            ("max_scale_change", 0 < self.max_scale_change < 1, "in (0, 1)"),
            ("seed", 0 <= self.seed <= MAX_SEED, f"in [0, {MAX_SEED}]"),
        )  # fmt: skip
        check_ranges(self, "registration", checks)


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


def correction_z(F: np.ndarray, transforms: list[np.ndarray]) -> tuple[float, float]:
    """How far the robust mean ``F`` of ``transforms`` stands from no correction, in standard
    errors: (rotation, translation).

    Each transform's deviation from F (rotation vector, translation) is one sample of the
    scatter; with per-axis scatter sigma the median deviation length is 1.538 sigma (chi,
    3 degrees of freedom) and the standard error of a median is 1.2533 sigma / sqrt(n).
    Fewer than 3 transforms give no scatter to judge by: (0, 0); no scatter at all gives
    inf (0 for an identity F). Under no true correction the ratio follows that chi
    distribution: 3 is its 97th percentile.
    """
    from scipy.spatial.transform import Rotation

    n = len(transforms)
    if n < 3:
        return 0.0, 0.0
    Ts = np.stack(transforms)
    dev = np.einsum("ij,njk->nik", np.linalg.inv(F), Ts)
    rot_dev = np.linalg.norm(Rotation.from_matrix(dev[:, :3, :3]).as_rotvec(), axis=1)
    shift_dev = np.linalg.norm(Ts[:, :3, 3] - F[:3, 3], axis=1)

    def z(size: float, devs: np.ndarray) -> float:
        se = 1.2533 * float(np.median(devs)) / 1.538 / np.sqrt(n)
        if se <= 0.0:
            return float("inf") if size > 0.0 else 0.0
        return size / se

    angle_rad = float(np.radians(rotation_angle_deg(F[:3, :3])))
    return z(angle_rad, rot_dev), z(float(np.linalg.norm(F[:3, 3])), shift_dev)


# Which gate refused a correction: a report's `rejected_by` (its `rejected` is prose).
REJECTED_BY_TRACKING_ACCURACY = "tracking_accuracy"
REJECTED_BY_DEPTH_RESIDUAL = "depth_residual"


def tracking_excess(F: np.ndarray, cfg: RegistrationConfig) -> str:
    """Why the camera-side correction F is one the tracker cannot need ("" if it can)."""
    shift_mm, angle_deg = float(np.linalg.norm(F[:3, 3])), rotation_angle_deg(F[:3, :3])
    if shift_mm <= cfg.tracking_accuracy_mm and angle_deg <= cfg.tracking_accuracy_deg:
        return ""
    return (
        f"correction {shift_mm:.2f} mm / {angle_deg:.2f} deg exceeds the tracking accuracy "
        f"({cfg.tracking_accuracy_mm} mm / {cfg.tracking_accuracy_deg} deg)"
    )
