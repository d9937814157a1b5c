"""Change detection pieces: robust scale, re-projection, imputation, the change mask."""

import numpy as np
import pytest

from chisel.change import (
    ChangeConfig,
    change_mask,
    impute,
    reproject_depth,
    solve_scale,
    warp_depth,
)
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.geometry import Camera, invert_rigid, look_at, transform_points


def _bumpy_depth(cam: Camera) -> np.ndarray:
    u, v = cam.pixel_grid()
    return (20.0 + 3.0 * np.sin(u / 9.0) + 2.0 * np.cos(v / 7.0)).astype(np.float32)


def test_scale_ignores_a_bite_in_view() -> None:
    cam = Camera.from_fov(80, 64, 80.0)
    render = _bumpy_depth(cam)
    truth = render.copy()
    truth[5:50, 10:65] += 6.0  # removed tissue: 48 % of the pixels are 6 mm deeper
    rng = np.random.default_rng(0)
    est = (truth + rng.normal(0, 0.2, truth.shape)).astype(np.float32) * 0.0421
    est[::9, ::4] = np.nan
    s, n = solve_scale(render, est)
    assert abs(s * 0.0421 - 1.0) < 0.01
    bite_valid = np.isfinite(est[5:50, 10:65]).sum()
    assert n <= np.isfinite(est).sum() - 0.95 * bite_valid  # the bite was left out
    # A plain median of ratios is pulled by the bite by more than 1 %.
    naive = np.nanmedian(render / est) * 0.0421
    assert abs(naive - 1.0) > 0.01


def test_scale_needs_overlap() -> None:
    a = np.full((10, 10), np.nan, np.float32)
    with pytest.raises(EmptyResultError, match="cannot solve the scale"):
        solve_scale(a, np.ones((10, 10), np.float32))


def test_warp_equals_backproject_transform_reproject() -> None:
    cam = Camera.from_fov(64, 48, 80.0, dist=np.array([-0.05, 0.01, 0.0, 0.0, 0.0]))
    depth = _bumpy_depth(cam)
    depth[5:9, 5:30] = np.nan
    T_a = look_at([0, 0, 0], [0.5, 0.2, 10], [0, -1, 0])
    T_b = look_at([0.8, -0.3, 0.4], [0.2, 0.4, 10], [0, -1, 0.1])
    pts = transform_points(T_a, cam.backproject(depth).reshape(-1, 3))
    pts = pts[np.isfinite(pts).all(axis=1)]
    ref = reproject_depth(pts, cam, T_b)
    out = warp_depth(depth, cam, invert_rigid(T_b) @ T_a)
    both = np.isfinite(ref) & np.isfinite(out)
    assert np.array_equal(np.isfinite(ref), np.isfinite(out))
    np.testing.assert_allclose(out[both], ref[both], atol=1e-4)
    # Identity motion gives the depth back exactly where valid.
    same = warp_depth(depth, cam, np.eye(4))
    ok = np.isfinite(depth)
    np.testing.assert_allclose(same[ok], depth[ok], rtol=1e-6)
    assert np.isnan(same[~ok]).all()


def test_zbuffer_keeps_the_nearest_point() -> None:
    cam = Camera.from_fov(16, 12, 60.0)
    ray = cam.rays_cam()[6, 8]
    pts = np.stack([ray * 20.0, ray * 10.0, ray * 30.0])
    d = reproject_depth(pts, cam, np.eye(4))
    assert d[6, 8] == pytest.approx(10.0) and np.isfinite(d).sum() == 1


def test_impute_fills_lost_pixels_with_render() -> None:
    mp = np.array([[1.0, np.nan], [3.0, np.nan]], np.float32)
    mt = np.array([[9.0, 8.0], [7.0, np.nan]], np.float32)
    out = impute(mp, mt)
    np.testing.assert_array_equal(out[0], [1.0, 8.0])
    assert out[1, 0] == 3.0 and np.isnan(out[1, 1])


def test_change_mask_threshold_and_cleaning() -> None:
    mt = np.full((60, 80), 20.0, np.float32)
    mp = mt.copy()
    mp[10:30, 10:40] += 4.0  # a real change
    mp[50, 70] += 4.0  # a speckle
    mp[45:48, 5:8] += 4.0  # a small blob (9 px)
    mp[40:44, 60:70] -= 3.0  # closer: tissue never grows, not a change
    mp[0:5, 0:5] += 0.9  # below the 1 mm threshold
    mp[20, 20] = 20.0  # a pin hole inside the change
    mt[25, 30] = np.nan  # no model: never changed
    m = change_mask(mp, mt, ChangeConfig(threshold_mm=1.0, min_area_px=30))
    assert m[10:30, 10:40].sum() == 20 * 30 - 1  # pin hole closed, the NaN pixel excluded
    assert m[20, 20] and not m[25, 30]
    assert m.sum() == 20 * 30 - 1
    raw = change_mask(mp, mt, ChangeConfig(threshold_mm=1.0, open_px=0, close_px=0, min_area_px=0))
    assert raw[50, 70] and raw[45:48, 5:8].all() and not raw[20, 20]
    higher = change_mask(mp, mt, ChangeConfig(threshold_mm=5.0))
    assert not higher.any()


def test_change_config_checks() -> None:
    with pytest.raises(InvalidInputError, match="threshold_mm"):
        ChangeConfig(threshold_mm=0.0)
    with pytest.raises(InvalidInputError, match="min_area_px"):
        ChangeConfig(min_area_px=-1)
    with pytest.raises(InvalidInputError, match="shape"):
        change_mask(np.zeros((3, 3), np.float32), np.zeros((3, 4), np.float32), ChangeConfig())


def test_surface_index_lookup_matches_tree() -> None:
    from chisel.icp import SurfaceIndex

    rng = np.random.default_rng(1)
    pts = rng.normal(size=(4000, 3))
    pts = 10.0 * pts / np.linalg.norm(pts, axis=1, keepdims=True)  # a sphere of 10 mm
    grid = (np.array([-12.0, -12.0, -12.0]), 0.5, (49, 49, 49))
    fast = SurfaceIndex(pts, pts / 10.0, grid=grid)
    exact = SurfaceIndex(pts, pts / 10.0)
    q = pts[:500] * rng.uniform(0.85, 1.15, (500, 1))
    for _ in range(2):  # the second call is served from the memo
        d_fast, i_fast = fast.query(q, 1.5)
        d_tree, _ = exact.query(q, 1.5)
        hit = np.isfinite(d_fast)
        assert hit.mean() > 0.95 and np.all(np.isfinite(d_tree[hit]))
        # Nearest to the voxel centre, not to the point: within a voxel diagonal.
        assert np.all(d_fast[hit] - d_tree[hit] < 0.5 * np.sqrt(3))
        assert np.all(i_fast[~hit] == len(pts))
    far = fast.query(np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]]), 1.5)
    assert np.all(np.isinf(far[0]))


def test_shift_to_render_recovers_a_relative_estimates_scale_and_shift() -> None:
    # A sloped view, 12-28 mm, estimated up to scale 0.05 and shift 3 mm (render = 0.05 E + 3),
    # with a 5 mm deeper removal over a fifth of the view that only the estimate sees.
    from chisel.change import shift_to_render

    rng = np.random.default_rng(0)
    H, W = 64, 80
    render = np.tile(np.linspace(12.0, 28.0, W), (H, 1)).astype(np.float32)
    truth = render.copy()
    truth[:, : W // 5] += 5.0
    est = ((truth + rng.normal(0.0, 0.1, truth.shape) - 3.0) / 0.05).astype(np.float32)
    shifted, shift, scale = shift_to_render(render, est, outlier_mm=1.0)
    assert scale == pytest.approx(0.05, rel=0.01)
    assert shift == pytest.approx(3.0 / 0.05, rel=0.02)
    metric = scale * shifted
    assert np.median(np.abs(metric - render)[:, W // 5 :]) < 0.15
    assert np.median((metric - render)[:, : W // 5]) == pytest.approx(5.0, abs=0.2)
    # A scale alone cannot fit it: the removal's edge is off by ~1 mm and the ramp bends.
    s = solve_scale(render, est)[0]
    assert np.median(np.abs(s * est - render)[:, W // 5 :]) > 0.5


def test_shift_to_render_keeps_the_scale_of_a_view_of_one_depth() -> None:
    # A wall seen head-on: scale and shift are collinear; the fit must not trade one for the
    # other (a collapse of the scale), and the estimate still maps onto the render.
    from chisel.change import MAX_SHIFT_SCALE_RATIO, shift_to_render

    rng = np.random.default_rng(1)
    render = np.full((64, 80), 15.0, np.float32)
    est = ((render + rng.normal(0.0, 0.5, render.shape)) / 0.04).astype(np.float32)
    s = solve_scale(render, est)[0]
    shifted, _, scale = shift_to_render(render, est)
    assert s / MAX_SHIFT_SCALE_RATIO <= scale <= s * MAX_SHIFT_SCALE_RATIO
    assert abs(float(np.median(scale * shifted)) - 15.0) < 0.1
