"""Less tracker jitter: the motion between consecutive frames, seen in their texture,
fused with the tracked poses.

An optical tracker's per-frame error (jitter) is independent from frame to frame, while
the motion between two consecutive frames is in their images: the mucosa's texture moves
with it. Open3D's RGB-D odometry (photometric, Steinbruecker et al. 2011) measures that
motion for each consecutive pair, with the model's depth render at the earlier frame's
tracked pose as its depth; a linear least-squares pose graph then places every frame
between its tracked pose (its jitter's covariance) and its neighbours' measured motion
(the odometry's). The constant hand-eye error is common to all frames and invisible to
odometry: it is left to the step's correction that follows (:mod:`chisel.shading`,
registration). Measured on the benchmark's tracker (0.2 mm / 0.1 deg jitter per axis):
docs/results.md, fifty-first session.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from chisel.core.config import check_fields, check_ranges
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, invert_rigid, make_transform

# Depth limits of the odometry's points, mm: an endoscope's working range (5-30 mm) with
# room on both sides; nearer or farther the render is no longer the tissue's depth.
_DEPTH_MIN_MM = 1.0
_DEPTH_MAX_MM = 80.0
# A point pair whose depths differ by more than this is no correspondence, mm (Open3D's
# default, 0.03, is in metres).
_DEPTH_DIFF_MAX_MM = 3.0


def _o3d() -> ModuleType:
    # Imported on first use: Open3D takes ~1 s to import.
    import open3d  # noqa: PLC0415

    return open3d


@dataclass(frozen=True)
class OdometryConfig:
    """Smoothing a step's tracked poses by frame-to-frame odometry (``UpdateConfig.odometry``)."""

    smooth_by_odometry: bool = False
    """Batch mode, frames with RGB: before any other correction, move each tracked pose by
    the least-squares fit of the tracker's jitter to the motion the consecutive frames'
    texture shows (:func:`smooth_poses`); the shading's step correction is then measured
    from the smoothed poses. Off by default: on seeds 0-4 it brought the frames 22 %
    closer to their true view (6.38 -> 4.95 px, 24 of 25 steps), but the table did not
    follow (the change-aware row 0.981x, the paper's row 1.062x, seed 1 worse in both;
    docs/results.md, fifty-first session). Not in streaming mode."""
    tracker_jitter_mm: float = 0.2
    """The tracker's per-frame translation noise assumed, std per axis, mm (the benchmark's
    tracker: 0.2)."""
    tracker_jitter_deg: float = 0.1
    """The tracker's per-frame rotation noise assumed, std per axis, degrees (0.1)."""
    odometry_sigma_mm: float = 0.1
    """The odometry's translation error between consecutive frames, std per axis, mm."""
    odometry_sigma_deg: float = 0.4
    """The odometry's rotation error between consecutive frames, std per axis, degrees: a
    small turn and a sideways shift move the image alike, so its rotation is the weak part."""
    odometry_gate: float = 4.0
    """A pair whose measured motion differs from the tracked one by more than this many
    standard deviations of their difference (two frames' jitter and the odometry's error,
    per axis) is not used: the odometry failed (a dark, blurred or occluded view)."""

    def __post_init__(self) -> None:
        check_fields(self, "odometry")
        checks = (
            ("tracker_jitter_mm", self.tracker_jitter_mm > 0, "> 0 mm"),
            ("tracker_jitter_deg", self.tracker_jitter_deg > 0, "> 0 deg"),
            ("odometry_sigma_mm", self.odometry_sigma_mm > 0, "> 0 mm"),
            ("odometry_sigma_deg", self.odometry_sigma_deg > 0, "> 0 deg"),
            ("odometry_gate", self.odometry_gate > 0, "> 0 standard deviations"),
        )
        check_ranges(self, "odometry", checks)


def _pinhole_maps(camera: Camera) -> tuple[np.ndarray, np.ndarray] | None:
    """Remap tables from the raw image to the pinhole image of the same K (None: no
    distortion). Open3D's odometry knows pinhole cameras only."""
    if not camera.has_distortion:
        return None
    size = (camera.width, camera.height)
    return cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, size, cv2.CV_32FC1)


def _rgbd(
    rgb: np.ndarray,
    mask: np.ndarray | None,
    depth_mm: np.ndarray,
    maps: tuple[np.ndarray, np.ndarray] | None,
) -> object:
    """Open3D's RGBDImage of a frame: its colour and the render's z-depth, pixels outside
    the frame's mask without depth (so they give no point)."""
    o3d = _o3d()
    d: np.ndarray = np.where(np.isfinite(depth_mm), depth_mm, 0.0).astype(np.float32)
    if mask is not None:
        d[~np.asarray(mask, dtype=bool)] = 0.0
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if maps is not None:
        rgb = cv2.remap(rgb, maps[0], maps[1], cv2.INTER_LINEAR)
        # Nearest: a depth edge interpolated would be a surface that is not there.
        d = cv2.remap(d, maps[0], maps[1], cv2.INTER_NEAREST)
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.ascontiguousarray(rgb)),
        o3d.geometry.Image(np.ascontiguousarray(d)),
        depth_scale=1.0,
        depth_trunc=_DEPTH_MAX_MM,
        convert_rgb_to_intensity=True,
    )


def frame_motions(
    rgbs: list[np.ndarray],
    masks: list[np.ndarray | None],
    depths_mm: list[np.ndarray],
    poses: list[np.ndarray],
    camera: Camera,
) -> dict[int, np.ndarray]:
    """Measured motion between consecutive frames: {i: (4, 4) T_cam_i_from_cam_i+1} for
    every pair whose odometry converged (Open3D's colour term, started from the tracked
    motion). depths_mm : per frame the z-depth its points are taken at (the model's render
    at the frame's tracked pose), NaN = none."""
    n = len(poses)
    if not (len(rgbs) == len(masks) == len(depths_mm) == n):
        raise InvalidInputError(
            "frame_motions", f"{len(rgbs)} frames, {len(depths_mm)} depths, {n} poses"
        )
    o3d = _o3d()
    maps = _pinhole_maps(camera)
    K = camera.K
    intrinsic = o3d.camera.PinholeCameraIntrinsic(
        camera.width, camera.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    )
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_min, option.depth_max = _DEPTH_MIN_MM, _DEPTH_MAX_MM
    option.depth_diff_max = _DEPTH_DIFF_MAX_MM
    term = o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm()
    images = [_rgbd(c, m, d, maps) for c, m, d in zip(rgbs, masks, depths_mm, strict=True)]
    out: dict[int, np.ndarray] = {}
    for i in range(n - 1):
        init = invert_rigid(poses[i]) @ poses[i + 1]
        # Open3D's result maps the source's (frame i + 1's) points into the target's (i's).
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            images[i + 1], images[i], intrinsic, init, term, option
        )
        if ok and np.all(np.isfinite(T)):
            out[i] = np.asarray(T, dtype=np.float64)
    return out


def _log(T: np.ndarray) -> np.ndarray:
    """(6,) translation and rotation vector of a small rigid transform."""
    return np.r_[T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()]


def _exp(x: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform of a (6,) translation and rotation vector (inverse of _log)."""
    return make_transform(Rotation.from_rotvec(x[3:]).as_matrix(), x[:3])


def _adjoint(T: np.ndarray) -> np.ndarray:
    """(6, 6) adjoint of T on (translation, rotation) twists: Exp(Ad x) = T Exp(x) T^-1."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[:3, 3:] = tx @ R
    return A


def fuse_poses(
    poses: list[np.ndarray], motions: dict[int, np.ndarray], cfg: OdometryConfig
) -> tuple[list[np.ndarray], int]:
    """Each tracked pose moved camera-side by x_i (``T_i Exp(x_i)``), the x minimising

        sum_i |x_i|^2_tracker + sum_(i, i+1) |log(Z_i^-1 (T_i Exp(x_i))^-1 T_i+1 Exp(x_i+1))|^2_odometry

    (Gauss-Newton, three passes; the jitter and the odometry's error per axis as in
    ``cfg``). A pair whose motion Z_i is further from the tracked motion than
    ``cfg.odometry_gate`` standard deviations of their difference is left out. Returns
    (the poses, the number of pairs used); the poses unchanged when none is."""
    n = len(poses)
    sd_tr = np.r_[[cfg.tracker_jitter_mm] * 3, [np.radians(cfg.tracker_jitter_deg)] * 3]
    sd_od = np.r_[[cfg.odometry_sigma_mm] * 3, [np.radians(cfg.odometry_sigma_deg)] * 3]
    # The tracked motion holds two frames' jitter, the measured one the odometry's error.
    sd_pair = np.sqrt(2.0 * sd_tr**2 + sd_od**2)
    used = {}
    for i, Z in motions.items():
        if not 0 <= i < n - 1:
            raise InvalidInputError("fuse_poses", f"motion {i} for {n} poses")
        d = _log(invert_rigid(invert_rigid(poses[i]) @ poses[i + 1]) @ Z)
        if np.all(np.abs(d) <= cfg.odometry_gate * sd_pair):
            used[i] = Z
    if not used:
        return [np.asarray(T, dtype=np.float64).copy() for T in poses], 0
    w_tr, w_od = 1.0 / sd_tr**2, 1.0 / sd_od**2
    x = np.zeros((n, 6))
    for _ in range(3):
        H = np.zeros((6 * n, 6 * n))
        g = np.zeros(6 * n)
        for i in range(n):
            H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += np.diag(w_tr)
            g[6 * i : 6 * i + 6] += w_tr * x[i]
        corrected = [poses[i] @ _exp(x[i]) for i in range(n)]
        for i, Z in used.items():
            D = invert_rigid(corrected[i]) @ corrected[i + 1]
            r = _log(invert_rigid(Z) @ D)
            # D(dx) = Exp(-dx_i) D Exp(dx_i+1) = D Exp(-Ad(D^-1) dx_i + dx_i+1)
            blocks = ((i, -_adjoint(invert_rigid(D))), (i + 1, np.eye(6)))
            for a, Ja in blocks:
                g[6 * a : 6 * a + 6] += Ja.T @ (w_od * r)
                for b, Jb in blocks:
                    H[6 * a : 6 * a + 6, 6 * b : 6 * b + 6] += Ja.T @ (w_od[:, None] * Jb)
        x -= np.linalg.solve(H, g).reshape(n, 6)
    return [np.asarray(poses[i], dtype=np.float64) @ _exp(x[i]) for i in range(n)], len(used)


def smooth_poses(
    rgbs: list[np.ndarray],
    masks: list[np.ndarray | None],
    depths_mm: list[np.ndarray],
    poses: list[np.ndarray],
    camera: Camera,
    cfg: OdometryConfig,
) -> tuple[list[np.ndarray], int]:
    """:func:`frame_motions` then :func:`fuse_poses`: the step's poses with less jitter, and
    how many consecutive pairs moved them."""
    motions = frame_motions(rgbs, masks, depths_mm, poses, camera)
    return fuse_poses(poses, motions, cfg)
