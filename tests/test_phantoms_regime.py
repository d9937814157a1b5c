"""The default procedure is specimen-sized: anatomies whose surgery looks too small (or too
large) to the endoscope are drawn again.

:func:`phantoms.regime.view_change_mm` is checked against analytic truth (a wall moved
back by a known distance) and, on a generated phantom, against z-depth renders of the
phantom's own meshes by chisel's ray caster (Mitsuba where it works).
"""

from __future__ import annotations

import importlib
import logging

import manifold3d as m3d
import numpy as np
import pytest
import trimesh

from chisel.core.geometry import Camera
from chisel.core.raycast import MeshRaycaster, SurfaceQueries
from phantoms.generate import build_phantom
from phantoms.params import PARAM_RANGES, PhantomConfig, sample_params
from phantoms.regime import (
    EYE_CLEARANCE_MM,
    FIELD_HALF_ANGLE_DEG,
    RAYS_ACROSS,
    REGIME_WINDOWS,
    RegimeWindow,
    view_change_mm,
    view_rays,
)
from phantoms.roi import ray_origins

generate = importlib.import_module("phantoms.generate")

CENTER = np.array([0.0, 0.0, 0.0])
NORMAL = np.array([-1.0, 0.0, 0.0])  # the wall faces -x, the endoscope stands at x < 0
APPROACH = np.array([-12.0, 1.0, 0.5])


def _wall(front_x: float, thickness_mm: float = 10.0) -> m3d.Manifold:
    """A 200 mm square wall whose front face lies at ``front_x``."""
    return m3d.Manifold.cube([thickness_mm, 200.0, 200.0]).translate([front_x, -100.0, -100.0])


def test_view_rays_fill_the_endoscopes_field_and_aim_at_the_target() -> None:
    eyes = ray_origins(APPROACH, CENTER, NORMAL)
    o, d = view_rays(eyes, CENTER)
    assert len(o) == len(d) and len(o) % len(eyes) == 0
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    for eye in eyes:
        mine = np.all(o == eye, axis=1)
        aim = (CENTER - eye) / np.linalg.norm(CENTER - eye)
        angle = np.degrees(np.arccos(np.clip(d[mine] @ aim, -1.0, 1.0)))
        assert angle.max() <= FIELD_HALF_ANGLE_DEG + 1e-9
        assert angle.min() < 1e-5  # the central ray looks at the target
        assert angle.max() > FIELD_HALF_ANGLE_DEG - 3.0


def test_a_wall_moved_back_changes_the_view_by_its_distance_along_each_ray() -> None:
    shift_mm = 2.0
    box = (np.array([-1.0, -100.0, -100.0]), np.array([20.0, 100.0, 100.0]))
    view = view_change_mm(_wall(0.0), [_wall(shift_mm)], box, APPROACH, CENTER, NORMAL)
    # analytic: a ray at angle theta to the wall's normal travels shift / cos(theta) further
    eyes = ray_origins(APPROACH, CENTER, NORMAL)
    o, d = view_rays(eyes[eyes[:, 0] <= -EYE_CLEARANCE_MM], CENTER)
    cos = d @ -NORMAL
    hit_y_z = o[:, 1:] + d[:, 1:] * (shift_mm - o[:, 0])[:, None] / cos[:, None]
    assert np.abs(hit_y_z).max() < 100.0  # every ray hits the moved wall inside the box
    assert view[0] == pytest.approx(float(np.mean(shift_mm / cos)), rel=1e-5)


def test_only_rays_whose_step_point_is_in_the_box_count() -> None:
    outside = (np.array([50.0, 50.0, 50.0]), np.array([60.0, 60.0, 60.0]))
    assert view_change_mm(_wall(0.0), [_wall(2.0)], outside, APPROACH, CENTER, NORMAL) == [0.0]
    inside = (np.array([-1.0, -100.0, -100.0]), np.array([20.0, 100.0, 100.0]))
    assert view_change_mm(_wall(0.0), [_wall(0.0)], inside, APPROACH, CENTER, NORMAL) == [0.0]
    # every view inside the tissue: nothing to see
    walls = [_wall(-30.0, 40.0), _wall(-28.0, 40.0)]
    buried = view_change_mm(walls[0], walls[1:], inside, APPROACH, CENTER, NORMAL)
    assert np.isnan(buried).all()


def test_the_window_says_why_a_view_misses_it() -> None:
    w = RegimeWindow(first_min_mm=1.0, last_mm=(3.0, 8.0))
    assert w.miss([1.2, 2.0, 4.0]) == "" and w.distance([1.2, 2.0, 4.0]) == 0.0
    assert "step 1 0.50 mm < 1.0" in w.miss([0.5, 2.0, 4.0])
    assert "last step 2.50 mm outside 3.0-8.0" in w.miss([1.2, 2.0, 2.5])
    assert "not rising" in w.miss([1.2, 4.5, 4.0])
    assert w.distance([0.5, 2.0, 9.0]) == pytest.approx(0.5 + 1.0)
    assert w.distance([1.2, 4.5, 4.0]) == pytest.approx(0.5)
    assert w.miss([float("nan")] * 3) and w.distance([float("nan")] * 3) == float("inf")


def _rendered_view(ph) -> list[float]:
    """The same figure from z-depth renders of the phantom's own meshes: chisel's ray caster
    (Mitsuba where a JIT variant works) at pinhole cameras whose pixels are the views' rays."""
    preop = trimesh.Trimesh(ph.steps[0].vertices_mm, ph.steps[0].faces, process=False)
    eyes = ray_origins(ph.airway_path_mm[-1], ph.target.center_mm, ph.target.normal)
    eyes = eyes[SurfaceQueries.from_trimesh(preop).signed_distance(eyes) >= EYE_CLEARANCE_MM]
    n = RAYS_ACROSS
    c = (n - 1) / 2.0
    f = c / np.tan(np.radians(FIELD_HALF_ANGLE_DEG))
    camera = Camera(n, n, np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]]), np.zeros(5))
    v, u = np.mgrid[0:n, 0:n].astype(float)
    field = (u - c) ** 2 + (v - c) ** 2 <= c * c + 1e-9
    ray_len = np.sqrt(((u - c) / f) ** 2 + ((v - c) / f) ** 2 + 1.0)  # per unit z-depth
    poses = []
    for eye in eyes:
        z = (ph.target.center_mm - eye) / np.linalg.norm(ph.target.center_mm - eye)
        helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(z, helper) / np.linalg.norm(np.cross(z, helper))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.stack([x, np.cross(z, x), z], axis=1), eye
        poses.append(T)
    poses_arr = np.stack(poses)

    def ray_lengths(step) -> tuple[np.ndarray, np.ndarray]:
        rc = MeshRaycaster(step.vertices_mm, step.faces)
        z = rc.render_depths(camera, poses_arr)
        pts = [
            camera.backproject(zi) @ T[:3, :3].T + T[:3, 3]
            for zi, T in zip(z, poses_arr, strict=True)
        ]
        return z * ray_len, np.stack(pts)

    t0, _ = ray_lengths(ph.steps[0])
    out = []
    for s in ph.steps[1:]:
        t, p = ray_lengths(s)
        ok = field[None] & np.isfinite(t) & np.isfinite(t0)
        ok &= np.all((p >= ph.roi_min_mm) & (p <= ph.roi_max_mm), axis=-1)
        out.append(float(np.abs(t[ok] - t0[ok]).mean()))
    return out


def test_a_seed_whose_surgery_looks_too_small_takes_a_specimen_sized_draw() -> None:
    """Seed 6's first draw: the first fragment changes the view by 0.39 mm (the benchmark:
    0.78 mm at step 1, 2.95 at step 5, below the goal)."""
    ph = build_phantom(PhantomConfig(seed=6, ct=False))
    window = REGIME_WINDOWS["uncinectomy"]
    assert ph.anatomy_draw >= 1 and ph.regime_met is True
    assert window.miss(list(ph.view_change_mm)) == ""
    assert {k: ph.params[k] for k in PARAM_RANGES} == sample_params(6, draw=ph.anatomy_draw)
    np.testing.assert_allclose(ph.view_change_mm, _rendered_view(ph), rtol=0.02)
    manifest = generate.manifest(ph)
    assert manifest["regime_met"] is True
    np.testing.assert_allclose(manifest["view_change_mm"], ph.view_change_mm, atol=1e-5)


def test_no_draw_in_the_window_keeps_the_nearest_and_says_so(monkeypatch, caplog) -> None:
    views = iter([[0.2, 0.4, 0.6, 0.8, 1.0], [0.5, 1.0, 1.5, 2.0, 2.5]])
    monkeypatch.setattr(generate, "view_change_mm", lambda *a, **k: next(views))
    monkeypatch.setattr(generate, "MAX_ANATOMY_DRAWS", 2)
    with caplog.at_level(logging.WARNING, logger="phantoms.generate"):
        ph = build_phantom(PhantomConfig(seed=0, ct=False))
    assert ph.anatomy_draw == 1 and ph.regime_met is False
    assert ph.view_change_mm == (0.5, 1.0, 1.5, 2.0, 2.5)
    assert "none of 2 anatomy draws gives a specimen-sized uncinectomy" in caplog.text


def test_procedures_without_a_window_and_explicit_plans_are_not_redrawn(monkeypatch) -> None:
    monkeypatch.setattr(generate, "view_change_mm", lambda *a, **k: [0.0])
    ph = build_phantom(PhantomConfig(seed=6, ct=False, procedure="bites", n_bites=1))
    assert ph.anatomy_draw == 0 and ph.regime_met is None
    planned = build_phantom(PhantomConfig(seed=6, ct=False), list(ph.bites))
    assert planned.anatomy_draw == 0 and planned.regime_met is None
