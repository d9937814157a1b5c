"""How large the surgery looks to the endoscope: the generator's stand-in for the no-update error.

Issue 18 calibrates the default procedure to the specimen: the unchanged preoperative
surface, scored with the paper's correspondence metric inside the change box from the
evaluation poses, is off by >= 1 mm after the first step and by 3-8 mm after the last,
rising at every step (specimen: 1.9 -> 5.6 mm). How large that error is depends on what
the endoscope sees through the opening, not on the removed volume (correlation 0.08 over
29 phantoms), so the generator measures it directly. The evaluation poses belong to the
simulator (``sim.paths.eval_poses``), which this package may not import;
:func:`view_change_mm` scores the same quantity from the change box's own ray origins
(:func:`phantoms.roi.ray_origins`: the end of the airway path and points 6-16 mm in
front of the target, each moved 3 mm sideways), each a pinhole view with an 85 deg
circular field (:data:`FIELD_HALF_ANGLE_DEG`) aimed at the target: per step, the mean
distance between the points that the same ray hits on the preoperative and on the step's
surface, over the rays whose step point lies in the change box. Same inputs, same
figures (no random numbers).

Measured against ``benchmarks/bench_regime.py`` on phantom seeds 0-26 (the simulator's 12
seeded evaluation poses at 320 x 256 with the field stop): correlation 0.94 at the last
step and 0.91 at the first; the benchmark's figure is 0.96-1.70x this one at the last step
(median 1.29) and 0.75-2.0x at the first. :data:`REGIME_WINDOWS` holds the procedure's
window in this figure's own millimetres, narrower than the goal's by that spread.
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d as m3d
import numpy as np
import open3d as o3d

from chisel.core.geometry import look_at
from phantoms.anatomy import arrays_from_manifold
from phantoms.roi import ray_origins, raycasting_scene

FIELD_HALF_ANGLE_DEG = 42.5
"""Half of the default endoscope's 85 deg field of view (``sim`` ``camera.fov_deg``). That
is its image diagonal; the field stop shows about 69 deg, so these views see a wider cone
than the evaluation poses. A cone of 69 deg tracked the benchmark no better (correlation
0.95 against 0.94 at the last step, seeds 0-26), and the window was set with this one."""
RAYS_ACROSS = 41
"""Rays across each view's square grid (those inside the circular field are cast)."""
EYE_CLEARANCE_MM = 2.5
"""Views closer than this to the preoperative tissue are dropped, as the evaluation poses
drop theirs (``paths.clearance_mm`` + 0.5)."""


@dataclass(frozen=True)
class RegimeWindow:
    """What a procedure's :func:`view_change_mm` must show, in its own millimetres."""

    first_min_mm: float
    """The first step's figure at least this."""
    last_mm: tuple[float, float]
    """The last step's figure inside this range."""

    def miss(self, view_mm: list[float]) -> str:
        """Why ``view_mm`` (one figure per step) misses the window ("" when it does not)."""
        if not view_mm or not np.all(np.isfinite(view_mm)):
            return "no view of the change box"
        why = []
        if view_mm[0] < self.first_min_mm:
            why.append(f"step 1 {view_mm[0]:.2f} mm < {self.first_min_mm}")
        lo, hi = self.last_mm
        if not lo <= view_mm[-1] <= hi:
            why.append(f"last step {view_mm[-1]:.2f} mm outside {lo}-{hi}")
        if any(b <= a for a, b in zip(view_mm, view_mm[1:], strict=False)):
            why.append("not rising at every step")
        return "; ".join(why)

    def distance(self, view_mm: list[float]) -> float:
        """How far ``view_mm`` lies outside the window, mm (0 inside; inf without a view)."""
        if not view_mm or not np.all(np.isfinite(view_mm)):
            return float("inf")
        lo, hi = self.last_mm
        steps = np.diff(view_mm)
        return (
            max(0.0, self.first_min_mm - view_mm[0])
            + max(0.0, lo - view_mm[-1], view_mm[-1] - hi)
            + float(np.clip(-steps, 0.0, None).sum())
        )


REGIME_WINDOWS: dict[str, RegimeWindow] = {
    # The goal (>= 1.0 mm at step 1, 3-8 mm at the last) in this figure's millimetres,
    # with the benchmark's ratio to it at its least for the lower bounds (first step:
    # 0.75-0.91x on 3 of seeds 0-26, last step 0.96-1.09x on two draws); above, 5.5 mm
    # is 7.1 mm at the median ratio (1.29) and 7.9 at seed 17's 1.44 (its draw at 5.36
    # here gave 7.73 mm).
    "uncinectomy": RegimeWindow(first_min_mm=1.2, last_mm=(3.0, 5.5)),
}
"""Procedures whose anatomy is drawn again until the surgery is specimen-sized."""


def view_rays(eyes_mm: np.ndarray, aim_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(origins (R, 3), unit directions (R, 3)): each eye's rays inside a circular field of
    ``2 * FIELD_HALF_ANGLE_DEG`` centred on ``aim_mm``."""
    t = np.tan(np.radians(FIELD_HALF_ANGLE_DEG))
    u, v = np.meshgrid(np.linspace(-t, t, RAYS_ACROSS), np.linspace(-t, t, RAYS_ACROSS))
    inside = u**2 + v**2 <= t * t
    u, v = u[inside], v[inside]
    origins, dirs = [], []
    aim = np.asarray(aim_mm, float)
    for eye in np.asarray(eyes_mm, float):
        a = aim - eye
        up = (
            np.array([0.0, 0.0, 1.0])
            if abs(a[2]) < 0.9 * np.linalg.norm(a)
            else np.array([0.0, 1.0, 0.0])
        )
        e1, e2, a = look_at(eye, aim, up)[:3, :3].T  # the view's camera axes x, y, z
        d = a[None] + u[:, None] * e1[None] + v[:, None] * e2[None]
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        origins.append(np.repeat(eye[None], len(d), axis=0))
    if not dirs:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(origins), np.concatenate(dirs)


def view_change_mm(
    preop: m3d.Manifold,
    steps: list[m3d.Manifold],
    box_mm: tuple[np.ndarray, np.ndarray],
    approach_mm: np.ndarray,
    target_center_mm: np.ndarray,
    target_normal: np.ndarray,
) -> list[float]:
    """Per step, the mean distance (mm) between the preoperative and the step's surface
    point along the same ray, over rays whose step point lies in ``box_mm`` (see module
    doc); NaN for every step when no view keeps its clearance."""
    pre = raycasting_scene(*arrays_from_manifold(preop))
    eyes = ray_origins(approach_mm, target_center_mm, target_normal).astype(np.float32)
    sd = pre.compute_signed_distance(o3d.core.Tensor.from_numpy(eyes)).numpy()
    # signed distance is negative inside a closed mesh; the views stand in the airway
    o, d = view_rays(eyes[sd >= EYE_CLEARANCE_MM], target_center_mm)
    if len(o) == 0:
        return [float("nan")] * len(steps)
    rays = o3d.core.Tensor.from_numpy(np.concatenate([o, d], axis=1).astype(np.float32))
    t_pre = pre.cast_rays(rays)["t_hit"].numpy()
    lo, hi = np.asarray(box_mm[0], float), np.asarray(box_mm[1], float)
    out = []
    for solid in steps:
        t = raycasting_scene(*arrays_from_manifold(solid)).cast_rays(rays)["t_hit"].numpy()
        p = o + d * np.where(np.isfinite(t), t, 0.0)[:, None]
        counted = np.isfinite(t) & np.isfinite(t_pre) & np.all((p >= lo) & (p <= hi), axis=1)
        out.append(float(np.abs(t[counted] - t_pre[counted]).mean()) if counted.any() else 0.0)
    return out
