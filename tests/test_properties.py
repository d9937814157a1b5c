"""Property-based tests (hypothesis) of the geometry core and the import path.

Distortion is drawn from a realistic, non-folding range: the radial map
r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6) must stay increasing out past the image corners,
otherwise a distorted pixel has two undistorted preimages and no round trip exists.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from chisel.core.geometry import Camera, check_rigid, invert_rigid, make_transform, transform_points
from chisel.io.import_poses import match_poses_by_time
from chisel.io.undistort import Circle, circle_mask, fit_field_stop, make_undistortion

# derandomize: CI runs the same examples every time (the project wants reproducible runs).
SETTINGS = settings(
    max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)

seeds = st.integers(0, 2**32 - 1)
translations = st.lists(st.floats(-500, 500), min_size=3, max_size=3).map(np.array)


@st.composite
def rigid(draw) -> np.ndarray:
    R = Rotation.random(random_state=draw(seeds)).as_matrix()
    return make_transform(R, draw(translations))


@st.composite
def distorted_cameras(draw) -> Camera:
    w = draw(st.integers(40, 120))
    h = draw(st.integers(32, 100))
    f = draw(st.floats(0.6, 1.6)) * w
    cx = (w - 1) / 2 + draw(st.floats(-0.05, 0.05)) * w
    cy = (h - 1) / 2 + draw(st.floats(-0.05, 0.05)) * h
    k1 = draw(st.floats(-0.35, 0.15))
    k2 = draw(st.floats(-0.05, 0.12))
    p1 = draw(st.floats(-0.003, 0.003))
    p2 = draw(st.floats(-0.003, 0.003))
    k3 = draw(st.floats(-0.01, 0.01))
    cam = Camera(
        w, h, np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), np.array([k1, k2, p1, p2, k3])
    )
    # Non-folding: d(r_d)/dr > 0.3 up to 1.3 x the (undistorted) corner radius.
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    r_max = 1.3 * np.max(np.hypot((corners[:, 0] - cx) / f, (corners[:, 1] - cy) / f)) * 1.5
    r = np.linspace(0, r_max, 200)
    assume(np.all(1 + 3 * k1 * r**2 + 5 * k2 * r**4 + 7 * k3 * r**6 > 0.3))
    return cam


@SETTINGS
@given(rigid(), rigid(), st.lists(st.floats(-100, 100), min_size=3, max_size=3))
def test_compose_and_invert(A, B, p) -> None:
    p = np.array(p)
    inv_A = invert_rigid(A)
    np.testing.assert_allclose(inv_A @ A, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert_rigid(A @ B), invert_rigid(B) @ inv_A, atol=1e-9)
    np.testing.assert_allclose(invert_rigid(inv_A), A, atol=1e-9)
    np.testing.assert_allclose(
        transform_points(A @ B, p), transform_points(A, transform_points(B, p)), atol=1e-9
    )
    np.testing.assert_allclose(transform_points(inv_A, transform_points(A, p)), p, atol=1e-9)
    check_rigid(A @ B)  # composition stays rigid


@SETTINGS
@given(distorted_cameras(), st.floats(3.0, 80.0))
def test_backproject_then_project_is_identity(cam, depth_mm) -> None:
    depth = np.full(cam.shape, depth_mm, np.float32)
    pts = cam.backproject(depth)
    uv, z = cam.project(pts)
    u, v = cam.pixel_grid()
    np.testing.assert_allclose(z, depth_mm, rtol=1e-6)
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-4)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-4)


@SETTINGS
@given(distorted_cameras(), st.floats(0.0, 1.0), seeds)
def test_undistortion_maps_agree_with_the_camera_model(cam, alpha, seed) -> None:
    """OpenCV's remap tables (initUndistortRectifyMap) against our numpy lens model, and
    the point round trip raw -> undistorted -> raw."""
    und = make_undistortion(cam, alpha)
    assert not und.camera.has_distortion and und.camera.shape == cam.shape
    rng = np.random.default_rng(seed)
    ij = np.stack([rng.integers(0, cam.height, 50), rng.integers(0, cam.width, 50)], axis=1)
    uv_new = ij[:, ::-1].astype(float)
    uv_raw = und.points_to_raw(uv_new)
    maps = np.stack([und.map_x[ij[:, 0], ij[:, 1]], und.map_y[ij[:, 0], ij[:, 1]]], axis=1)
    np.testing.assert_allclose(maps, uv_raw, atol=2e-3)  # float32 tables
    inside = und.valid[ij[:, 0], ij[:, 1]]
    assume(inside.any())
    back = und.points_to_undistorted(uv_raw[inside])
    np.testing.assert_allclose(back, uv_new[inside], atol=1e-5)


@SETTINGS
@given(distorted_cameras(), seeds)
def test_undistorted_pixels_see_the_same_3d_points(cam, seed) -> None:
    """A 3-D point projects to raw pixel p (distorted camera) and to q (new pinhole camera);
    the undistortion map sends q to p."""
    und = make_undistortion(cam)
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-0.5, 0.5, (30, 2)), np.ones(30)] * rng.uniform(5, 50, (30, 1))
    q = und.camera.project(X)[0]
    p = cam.project(X)[0]
    keep = (
        (q[:, 0] >= 0) & (q[:, 0] <= cam.width - 1) & (q[:, 1] >= 0) & (q[:, 1] <= cam.height - 1)
    )
    assume(keep.sum() > 3)
    np.testing.assert_allclose(und.points_to_raw(q[keep]), p[keep], atol=1e-6)


@SETTINGS
@given(st.floats(30, 70), st.floats(25, 55), st.floats(22, 60), st.integers(0, 40), seeds)
def test_field_stop_fit_recovers_circles(cx, cy, r, dark, seed) -> None:
    shape = (80, 100)
    circle = Circle(cx, cy, r)
    inside = circle_mask(shape, circle)
    assume(inside.sum() < 0.9 * inside.size)
    rng = np.random.default_rng(seed)
    img = rng.integers(60 + dark, 230, (*shape, 3)).astype(np.uint8)
    img[~inside] = rng.integers(0, 12, (int((~inside).sum()), 3))
    # Fraction of the rim inside the image: a short arc pins the circle less tightly.
    a = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    x, y = cx + r * np.cos(a), cy + r * np.sin(a)
    frac = np.mean((x > 1) & (x < shape[1] - 2) & (y > 1) & (y < shape[0] - 2))
    assume(frac > 0.2)
    tol = 0.5 if frac > 0.5 else 1.0
    fit = fit_field_stop([img])
    assert fit is not None
    assert abs(fit.cx - cx) < tol and abs(fit.cy - cy) < tol and abs(fit.r - r) < tol + 0.1


@SETTINGS
@given(
    st.lists(st.floats(0.001, 0.5), min_size=2, max_size=30),
    st.lists(st.floats(-1.0, 20.0), min_size=1, max_size=20),
    st.floats(0.001, 0.3),
    seeds,
)
def test_nearest_matching_never_exceeds_the_tolerance(gaps, frame_times, tol, seed) -> None:
    t = np.cumsum(gaps)
    rng = np.random.default_rng(seed)
    P = np.stack(
        [
            make_transform(
                Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(size=3)
            )
            for _ in t
        ]
    )
    P[:, 0, 3] = np.arange(len(t))  # tag each sample by its index
    f = np.array(frame_times)
    out = match_poses_by_time(t, P, f, tol, "nearest")
    for fi, T in zip(f, out, strict=True):
        d = np.abs(t - fi)
        if d.min() > tol:
            assert np.isnan(T).all()
        else:
            k = int(T[0, 3])
            assert d[k] == pytest.approx(d.min()) and d[k] <= tol
    slerped = match_poses_by_time(t, P, f, tol, "slerp")
    ok = np.isfinite(slerped.reshape(len(f), -1)).all(axis=1)
    if ok.any():
        check_rigid(slerped[ok])  # interpolated poses stay rigid


_HAS_FUSION = importlib.util.find_spec("chisel.fusion") is not None


@pytest.mark.skipif(not _HAS_FUSION, reason="chisel.fusion not present")
@SETTINGS
@given(seeds, st.floats(0.5, 2.0), st.floats(0.0, 0.4))
def test_fusion_of_random_depth_stays_finite_and_bounded(seed, trunc_factor, invalid_frac) -> None:
    from chisel.core.geometry import look_at
    from chisel.fusion import integrate
    from chisel.model import TsdfModel

    rng = np.random.default_rng(seed)
    cam = Camera.from_fov(24, 20, 80, dist=np.array([-0.2, 0.03, 0.0, 0.0, 0.0]))
    model = TsdfModel.empty([-10, -10, 0], [10, 10, 30], 1.0, max(1.0, 3.0 * trunc_factor))
    for _ in range(3):
        depth = rng.uniform(0.5, 60, cam.shape).astype(np.float32)
        depth[rng.random(cam.shape) < invalid_frac] = np.nan
        eye = rng.uniform(-5, 5, 3) + np.array([0, 0, -10.0])
        T = look_at(
            eye, eye + np.array([rng.normal(0, 0.2), rng.normal(0, 0.2), 1.0]), up=[0, -1, 0]
        )
        w = (rng.random(cam.shape) > 0.3).astype(np.float32)
        integrate(model, cam, T, depth, pixel_weight=w)
        assert np.isfinite(model.tsdf).all() and np.isfinite(model.weight).all()
        assert model.tsdf.min() >= -1.0 and model.tsdf.max() <= 1.0
        assert model.weight.min() >= 0.0
