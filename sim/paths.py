"""Camera paths through the airway: smooth, seeded, collision-checked.

Three kinds, all returning (N, 4, 4) float64 ``T_world_from_cam`` (OpenCV axes, mm):

- :func:`preop_sweep`: along the phantom's airway polyline, looking ahead, turning to
  the target over the last part;
- :func:`intraop_path`: a smooth spline through seeded keyframe viewpoints near the
  target, each with a clear line of sight to an aim point in the ROI;
- :func:`eval_poses`: a fixed set of seeded viewpoints of the ROI (same for every step).

The optical centre stays ``clearance_mm`` from tissue everywhere along a path (checked
on samples at most ``clearance_mm / 4`` apart with a signed-distance query). Same inputs
and seed, same poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from chisel.core.geometry import look_at, make_transform
from sim.collision import TissueDistance
from sim.config import PathConfig
from sim.errors import PathError, PathInTissueError, PhantomError

_KIND_SEED = {"intraop": 1, "eval": 2}

TARGET_DEPTH_TOL_MM = 1.0
"""How deep inside tissue the target centre may lie (it is on the surface; the mesh is a
triangulation of it). Deeper, no viewpoint has a line of sight to it."""


@dataclass(frozen=True)
class PathTarget:
    """What intraoperative and evaluation paths look at (from the phantom manifest)."""

    center_mm: np.ndarray
    """(3,) float64 target centre on the tissue surface, mm."""
    normal: np.ndarray
    """(3,) float64 unit normal from the target into the airway."""
    roi_box_mm: np.ndarray
    """(2, 3) float64 change-region box [[min], [max]], mm."""
    approach_mm: np.ndarray
    """(3,) float64 a point in the air in front of the target (end of the airway path), mm."""
    source: str = "phantom.json"
    """The manifest these come from, named in error messages."""


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _arclength(points: np.ndarray) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def _resample(points: np.ndarray, s_new: np.ndarray) -> np.ndarray:
    s = _arclength(points)
    return np.stack([np.interp(s_new, s, points[:, k]) for k in range(3)], axis=1)


def _densify(points: np.ndarray, step_mm: float) -> np.ndarray:
    s = _arclength(points)
    n = max(int(math.ceil(s[-1] / step_mm)) + 1, 2)
    return _resample(points, np.linspace(0.0, s[-1], n))


def _catmull_rom(keys: np.ndarray, samples_per_segment: int) -> tuple[np.ndarray, np.ndarray]:
    """Centripetal Catmull-Rom spline through ``keys`` (K, D); returns (points, key param)."""
    p = np.concatenate([2 * keys[:1] - keys[1:2], keys, 2 * keys[-1:] - keys[-2:-1]])
    out = []
    for i in range(1, len(p) - 2):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        t0 = 0.0
        t1 = t0 + max(float(np.linalg.norm(p1[:3] - p0[:3])) ** 0.5, 1e-6)
        t2 = t1 + max(float(np.linalg.norm(p2[:3] - p1[:3])) ** 0.5, 1e-6)
        t3 = t2 + max(float(np.linalg.norm(p3[:3] - p2[:3])) ** 0.5, 1e-6)
        last = i == len(p) - 3
        t = np.linspace(t1, t2, samples_per_segment + (1 if last else 0), endpoint=last)[:, None]
        a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
        a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
        a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
        b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
        b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
        out.append((t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2)
    return np.concatenate(out), np.arange(len(keys)) * samples_per_segment


def _orient(
    eyes: np.ndarray, aims: np.ndarray, up_hint: np.ndarray, roll_deg: np.ndarray
) -> np.ndarray:
    """Poses looking from ``eyes`` at ``aims`` with the image-up transported frame to frame.

    Transporting the up vector (instead of a fixed world up) keeps the roll smooth when the
    view direction sweeps through the hint; ``roll_deg`` then adds a deliberate roll.
    """
    up = np.asarray(up_hint, dtype=np.float64) / np.linalg.norm(up_hint)
    poses = np.empty((len(eyes), 4, 4))
    for i, (e, a) in enumerate(zip(eyes, aims, strict=True)):
        z = _normalize(a - e)
        u = up - np.dot(up, z) * z
        if np.linalg.norm(u) < 1e-6:  # looking along the previous up: pick any perpendicular
            axis = np.eye(3)[int(np.argmin(np.abs(z)))]
            u = axis - np.dot(axis, z) * z
        up = u / np.linalg.norm(u)
        T = look_at(e, e + z, up)
        r = math.radians(float(roll_deg[i]))
        c, s = math.cos(r), math.sin(r)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        poses[i] = make_transform(T[:3, :3] @ Rz, e)
    return poses


def check_mesh_frame(points_mm: np.ndarray, what: str, tissue: TissueDistance, source: str) -> None:
    """Raise :class:`PhantomError` if a point lies far outside the tissue mesh's bounding box.

    ``phantom.json`` and its meshes share one world frame in mm. A mesh in metres (1000x
    too small) or in another frame would otherwise give collision-free paths that look at
    nothing and renders without valid depth, with exit status 0. The tolerance (2 mm +
    a quarter of the box diagonal) leaves room for a nostril just outside the box.
    """
    pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
    box = tissue.bounds
    outside = np.linalg.norm(np.maximum(box[0] - pts, 0) + np.maximum(pts - box[1], 0), axis=1)
    i = int(np.argmax(outside))
    if outside[i] > 2.0 + 0.25 * float(np.linalg.norm(box[1] - box[0])):
        raise PhantomError(
            source,
            f"{what} {np.round(pts[i], 2).tolist()} mm lies {outside[i]:.1f} mm outside the "
            f"bounding box {np.round(box, 3).tolist()} mm of the tissue mesh {tissue.source}: "
            f"the mesh is probably in other units (mm expected) or another frame than the "
            f"phantom manifest",
        )


def _check_target(target: PathTarget, tissue: TissueDistance) -> None:
    """Refuse a target (or approach point) no viewpoint can work with, naming the manifest."""
    check_mesh_frame(target.center_mm, "target.center_mm", tissue, target.source)
    check_mesh_frame(target.approach_mm, "airway_path_mm[-1]", tissue, target.source)
    d = float(tissue.signed_distance(target.center_mm[None])[0])
    if d < -TARGET_DEPTH_TOL_MM:
        raise PathError(
            target.source,
            f"target.center_mm {np.round(target.center_mm, 2).tolist()} mm lies {-d:.2f} mm "
            f"inside the tissue of {tissue.source}: it must be on the tissue surface, where "
            f"a camera in the airway can see it",
        )


def _why_unseen(target: PathTarget, tissue: TissueDistance) -> str:
    """A hint for "no viewpoint found": is the target hidden from the airway's end?"""
    dist = float(np.linalg.norm(target.center_mm - target.approach_mm))
    hit = float(tissue.first_hit_mm(target.approach_mm[None], target.center_mm[None])[0])
    if dist > 0 and hit < dist - 1.5:  # the same margin as the line-of-sight test
        return (
            f"; tissue hides target.center_mm of {target.source} from the end of the airway "
            f"path ({dist - hit:.1f} mm before it): the target must be on the tissue surface "
            f"facing the airway"
        )
    return ""


def check_clearance(
    positions_mm: np.ndarray, tissue: TissueDistance, clearance_mm: float, source: str
) -> np.ndarray:
    """Raise :class:`PathError` unless every position is ``clearance_mm`` from tissue.

    positions_mm : (N, 3) world mm. A position inside tissue raises
    :class:`PathInTissueError`. Returns the (N,) signed distances in mm.
    """
    d = tissue.signed_distance(positions_mm)
    inside = np.flatnonzero(d < 0)
    if inside.size:
        i = int(inside[0])
        where = "starts" if i == 0 else f"runs (position {i} of {len(d)})"
        raise PathInTissueError(
            source,
            f"the camera path {where} inside tissue at {np.round(positions_mm[i], 2).tolist()} "
            f"mm (signed distance {d[i]:.2f} mm); it must stay in the air",
        )
    close = np.flatnonzero(d < clearance_mm - 1e-6)
    if close.size:
        i = int(close[np.argmin(d[close])])
        raise PathError(
            source,
            f"the optical centre comes within {d[i]:.2f} mm of tissue at position {i} "
            f"{np.round(positions_mm[i], 2).tolist()} mm; expected >= {clearance_mm} mm "
            f"({close.size} position(s) too close)",
        )
    return d


def _dense_positions(poses: np.ndarray, step_mm: float) -> np.ndarray:
    return _densify(poses[:, :3, 3], step_mm) if len(poses) > 1 else poses[:, :3, 3]


def preop_sweep(
    airway_path_mm: np.ndarray,
    target_center_mm: np.ndarray,
    tissue: TissueDistance,
    n_frames: int,
    cfg: PathConfig,
    source: str = "phantom.json",
) -> np.ndarray:
    """The preoperative scoping sweep: nostril to the target along the airway.

    airway_path_mm : (M, 3) polyline, mm. target_center_mm : (3,) mm. source : the
    manifest they come from (named in errors).
    Returns (n_frames, 4, 4) ``T_world_from_cam``. The polyline is smoothed (Gaussian,
    sigma 1.5 mm) and pushed away from tissue where it comes closer than the clearance.
    Raises :class:`PathInTissueError` if the polyline starts or runs inside tissue,
    :class:`PathError` if the clearance cannot be kept, :class:`PhantomError` if the
    points lie far outside the mesh (units or frame mismatch).
    """
    airway = np.asarray(airway_path_mm, dtype=np.float64)
    check_mesh_frame(target_center_mm, "target.center_mm", tissue, source)
    check_mesh_frame(airway, "airway_path_mm", tissue, source)
    check_inside = tissue.signed_distance(airway)
    if check_inside[0] < 0:
        raise PathInTissueError(
            source,
            f"airway_path_mm: the airway path starts inside tissue at "
            f"{np.round(airway[0], 2).tolist()} mm (signed distance {check_inside[0]:.2f} mm "
            f"from {tissue.source})",
        )
    step = cfg.clearance_mm / 4.0
    dense = _densify(airway, step)
    check_clearance(dense[:1], tissue, 0.0, f"{source}: airway_path_mm")
    room = tissue.signed_distance(_densify(airway, 0.5))
    # The phantom's airway path keeps the most room it can (phantoms/path.py), so a
    # clearance beyond its widest point cannot be kept by any sweep; pushing the path
    # anyway drives it through walls or out of the nostril (once: NaN poses).
    if cfg.clearance_mm > room.max():
        raise PathError(
            "paths.clearance_mm",
            f"no camera position along the airway keeps {cfg.clearance_mm:g} mm from tissue: "
            f"the airway path of {source} is at most {room.max():.2f} mm from tissue "
            f"(narrowest {room.min():.2f} mm); lower the clearance",
        )
    for _ in range(3):
        smooth = gaussian_filter1d(dense, sigma=1.5 / step, axis=0, mode="nearest")
        smooth[0], smooth[-1] = dense[0], dense[-1]
        if tissue.signed_distance(smooth).min() >= 0:
            dense = smooth
        dense = tissue.push_to_clearance(dense, cfg.clearance_mm)
        dense = _densify(dense, step)
    try:
        check_clearance(dense, tissue, cfg.clearance_mm, f"preop sweep ({source}: airway_path_mm)")
    except PathError as exc:
        if cfg.clearance_mm <= room.min():
            raise
        # The path had to be pushed away from tissue and that failed: say why.
        raise type(exc)(
            exc.source,
            f"{exc.problem}; the airway path is only {room.min():.2f} mm from tissue in "
            f"places, pushing it to paths.clearance_mm = {cfg.clearance_mm:g} mm failed",
        ) from None
    s = _arclength(dense)
    length = s[-1]
    if length <= 0:
        raise PathError(source, "airway_path_mm: the airway path has zero length")
    s_frames = np.linspace(0.0, length, int(n_frames))
    eyes = _resample(dense, s_frames)
    ahead = _resample(dense, np.minimum(s_frames + cfg.lookahead_mm, length))
    end_dir = _normalize(dense[-1] - dense[max(len(dense) - 1 - int(cfg.lookahead_mm / step), 0)])
    dir_ahead = ahead - eyes
    n = np.linalg.norm(dir_ahead, axis=1)
    dir_ahead = np.where(n[:, None] > 1e-6, dir_ahead / np.maximum(n, 1e-9)[:, None], end_dir)
    dir_target = _normalize(np.asarray(target_center_mm, dtype=np.float64) - eyes)
    f = s_frames / length
    start = 1.0 - cfg.turn_fraction
    w = np.clip((f - start) / max(cfg.turn_fraction, 1e-9), 0.0, 1.0)
    w = w * w * (3 - 2 * w)  # smoothstep: no kink where the turn starts
    dirs = (1 - w)[:, None] * dir_ahead + w[:, None] * dir_target
    bad = np.linalg.norm(dirs, axis=1) < 1e-3
    dirs[bad] = dir_target[bad]
    return _orient(eyes, eyes + _normalize(dirs), np.asarray(cfg.up_hint), np.zeros(len(eyes)))


def _draw_viewpoint(
    rng: np.random.Generator, target: PathTarget, tissue: TissueDistance, cfg: PathConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """One (eye, aim) pair that satisfies distance, clearance and line of sight, or None."""
    dmin, dmax = cfg.view_distance_mm
    if rng.random() < 0.5:
        centre = target.approach_mm
    else:
        centre = target.center_mm + target.normal * rng.uniform(dmin, dmax)
    v = rng.normal(size=3)
    eye = centre + v / np.linalg.norm(v) * cfg.viewpoint_spread_mm * rng.random() ** (1 / 3)
    a = rng.normal(size=3)
    aim = target.center_mm + a / np.linalg.norm(a) * cfg.aim_jitter_mm * rng.random() ** (1 / 3)
    aim = np.clip(aim, target.roi_box_mm[0], target.roi_box_mm[1])
    dist = float(np.linalg.norm(aim - eye))
    if not dmin <= dist <= dmax:
        return None
    if float(np.dot(_normalize(eye - target.center_mm), target.normal)) < math.cos(
        math.radians(75)
    ):
        return None
    if tissue.signed_distance(eye[None])[0] < cfg.clearance_mm + 0.5:
        return None
    # Line of sight: nothing in between (the aim point lies on or near the surface).
    hit = tissue.first_hit_mm(eye[None], aim[None])[0]
    if hit < dist - 1.5:
        return None
    return eye, aim


def _segment_clear(a: np.ndarray, b: np.ndarray, tissue: TissueDistance, clearance: float) -> bool:
    pts = _densify(np.stack([a, b]), clearance / 4.0)
    return bool(tissue.signed_distance(pts).min() >= clearance)


def intraop_path(
    target: PathTarget,
    tissue: TissueDistance,
    n_frames: int,
    seed: int,
    cfg: PathConfig,
) -> np.ndarray:
    """An intraoperative sequence looking at the change region from varied viewpoints.

    Keyframe viewpoints are drawn (seeded) around the approach point and in front of the
    target; a centripetal Catmull-Rom spline runs through them and their aim points, and
    the scope rolls smoothly by up to ``cfg.roll_deg``. Paths that come closer than the
    clearance are redrawn, up to ``cfg.max_tries`` times, then :class:`PathError`.
    Returns (n_frames, 4, 4) ``T_world_from_cam``.
    """
    rng = np.random.default_rng([int(seed), _KIND_SEED["intraop"]])
    _check_target(target, tissue)
    check_clearance(
        target.approach_mm[None],
        tissue,
        0.0,
        f"{target.source}: airway_path_mm[-1] (approach point)",
    )
    for _attempt in range(int(cfg.max_tries)):
        keys: list[tuple[np.ndarray, np.ndarray]] = []
        draws = 0
        while len(keys) < cfg.keyframes and draws < 50 * cfg.keyframes:
            draws += 1
            vp = _draw_viewpoint(rng, target, tissue, cfg)
            if vp is None:
                continue
            if keys and not _segment_clear(keys[-1][0], vp[0], tissue, cfg.clearance_mm + 0.25):
                continue
            keys.append(vp)
        if len(keys) < cfg.keyframes:
            continue
        key_arr = np.array([np.concatenate([e, a]) for e, a in keys])
        curve, _ = _catmull_rom(key_arr, 64)
        eyes_dense, aims_dense = curve[:, :3], curve[:, 3:]
        dense = _densify(eyes_dense, cfg.clearance_mm / 4.0)
        if tissue.signed_distance(dense).min() < cfg.clearance_mm:
            continue
        s = _arclength(eyes_dense)
        s_frames = np.linspace(0.0, s[-1], int(n_frames))
        eyes = _resample(eyes_dense, s_frames)
        aims = np.stack([np.interp(s_frames, s, aims_dense[:, k]) for k in range(3)], axis=1)
        phase = rng.uniform(0, 2 * math.pi)
        roll = cfg.roll_deg * np.sin(2 * math.pi * s_frames / max(s[-1], 1e-9) + phase)
        up0 = np.asarray(cfg.up_hint, dtype=np.float64)
        return _orient(eyes, aims, up0, roll)
    raise PathError(
        "intraop path",
        f"no collision-free path with {cfg.keyframes} keyframes found in {cfg.max_tries} tries "
        f"(clearance {cfg.clearance_mm} mm, view distance {list(cfg.view_distance_mm)} mm): the "
        f"space in front of the target is too tight{_why_unseen(target, tissue)}",
    )


def eval_poses(
    target: PathTarget, tissue: TissueDistance, n_poses: int, seed: int, cfg: PathConfig
) -> np.ndarray:
    """A fixed set of seeded viewpoints of the ROI (the same for every step).

    Returns (n_poses, 4, 4) ``T_world_from_cam``; raises :class:`PathError` if too few
    valid viewpoints are found.
    """
    rng = np.random.default_rng([int(seed), _KIND_SEED["eval"]])
    _check_target(target, tissue)
    poses: list[np.ndarray] = []
    draws = 0
    limit = 200 * int(n_poses) + 1000
    while len(poses) < n_poses and draws < limit:
        draws += 1
        vp = _draw_viewpoint(rng, target, tissue, cfg)
        if vp is None:
            continue
        roll = rng.uniform(-cfg.roll_deg, cfg.roll_deg)
        poses.append(
            _orient(vp[0][None], vp[1][None], np.asarray(cfg.up_hint), np.array([roll]))[0]
        )
    if len(poses) < n_poses:
        raise PathError(
            "eval poses",
            f"found only {len(poses)} of {n_poses} valid evaluation viewpoints in {limit} draws "
            f"(clearance {cfg.clearance_mm} mm, view distance {list(cfg.view_distance_mm)} mm): "
            f"the space in front of the target is too tight{_why_unseen(target, tissue)}",
        )
    return np.stack(poses)
