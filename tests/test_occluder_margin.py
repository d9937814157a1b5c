"""The margin an update leaves around an occluder in a frame's mask (an instrument)."""

import numpy as np
import pytest
from scipy import ndimage

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera
from chisel.detect import occluder_margin, validate_estimate
from chisel.io.sequence import Frame
from chisel.update_config import UpdateConfig

H, W = 120, 160


def _field_stop() -> np.ndarray:
    v, u = np.mgrid[:H, :W]
    return (u - 80.0) ** 2 + (v - 60.0) ** 2 <= 55.0**2


def _tool() -> np.ndarray:
    # A shaft entering from the right edge of the view to the middle.
    t = np.zeros((H, W), bool)
    t[52:66, 90:] = True
    return t


def test_margin_is_the_euclidean_distance_to_the_instrument() -> None:
    stop, tool = _field_stop(), _tool()
    mask = stop & ~tool
    out = occluder_margin(mask, 8.0)
    # Independent: scipy's exact Euclidean distance to the tool's pixels in the view.
    dist = ndimage.distance_transform_edt(~(tool & stop))
    expected = mask & (dist > 8.0)
    # The field stop's edge is no occluder: pixels near it, away from the tool, stay.
    rim = stop & ~ndimage.binary_erosion(stop, iterations=3)
    assert (out & rim).sum() >= (expected & rim).sum() - 20
    inner = ndimage.binary_erosion(stop, iterations=3)
    assert np.array_equal(out & inner, expected & inner)
    assert out.sum() < mask.sum() - 8 * 2 * 14  # a band on both sides of the shaft went


def test_no_occluder_or_no_margin_leaves_the_mask_alone() -> None:
    stop = _field_stop()
    assert np.array_equal(occluder_margin(stop, 8.0), stop)  # the field stop alone
    mask = stop & ~_tool()
    assert np.array_equal(occluder_margin(mask, 0.0), mask)
    full = np.ones((H, W), bool)
    assert np.array_equal(occluder_margin(full, 8.0), full)


def test_the_estimate_is_invalid_beside_the_instrument() -> None:
    cam = Camera(width=W, height=H, K=np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]]))
    tool = _tool()
    frame = Frame(index=0, T_world_from_cam=np.eye(4), mask=_field_stop() & ~tool)
    depth = np.full((H, W), 10.0, np.float32)
    plain = validate_estimate(depth, frame, cam, metric=True)
    wide = validate_estimate(depth, frame, cam, metric=True, margin_px=6.0)
    assert np.isnan(plain[tool]).all() and np.isnan(wide[tool]).all()
    assert np.isfinite(plain[58, 85]) and np.isnan(wide[58, 85])  # 5 px left of the shaft
    assert np.isfinite(wide[58, 80])  # 10 px away
    assert np.isfinite(wide[60, 30])  # across the view


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_a_bad_margin_is_named(bad: float) -> None:
    with pytest.raises(InvalidInputError, match="occluder_margin_px"):
        UpdateConfig(occluder_margin_px=bad)
