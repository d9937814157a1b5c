"""UpdateConfig.skip_occluded_frames: a frame with an instrument in view is left out of
the step, as the paper picked tool-free frames by hand."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import test_updater_scenes as sc

from chisel.batch import SKIPPED_OCCLUDED, update_step
from chisel.depth_source import CallableDepth
from chisel.io.sequence import Frame
from chisel.update_config import UpdateConfig

HELD = {3, 4, 5}  # a tool episode: consecutive frames


@pytest.fixture(scope="module")
def scene() -> dict:
    tissue, cam = sc.tissue_mesh(), sc.camera()
    model = sc.preop_model(tissue, cam)
    P = sc.poses(12, seed=2)
    frames = sc.frames(sc.bitten_mesh(tissue), cam, P, P)
    h, w = cam.shape
    tool = np.ones((h, w), dtype=bool)
    tool[h // 3 :, w // 3 : 2 * w // 3] = False  # an instrument from the bottom edge
    with_tool = [replace(f, mask=tool) if f.index in HELD else f for f in frames]
    return {"model": model, "cam": cam, "frames": frames, "with_tool": with_tool}


def _source(asked: list[int], metric: bool = False) -> CallableDepth:
    """Depth up to scale (a monocular network's), except in the tool episode: 5 mm too deep
    beyond the tool too (a network thrown off by the tool). ``metric``: exact depth."""

    def depth(f: Frame) -> np.ndarray:
        asked.append(f.index)
        d = np.asarray(f.depth_mm, dtype=np.float32)
        if metric:
            return d
        return np.float32(0.037) * (d + np.float32(5.0) if f.index in HELD else d)

    return CallableDepth(depth, metric=metric)


def test_frames_with_an_instrument_are_left_out_and_reported(scene: dict) -> None:
    cfg = UpdateConfig(skip_occluded_frames=True, register=False)
    asked: list[int] = []
    new, rep = update_step(scene["model"], scene["cam"], scene["with_tool"], _source(asked), cfg)
    assert sorted(asked) == sorted(set(range(12)) - HELD)  # their depth is never estimated
    d = rep.to_dict()
    assert d["frames_skipped"] == [{"index": i, "reason": SKIPPED_OCCLUDED} for i in sorted(HELD)]
    assert [f["index"] for f in d["frames"]] == list(range(12))
    # The same as updating with the tool-free frames alone; and the tool episode's wrong
    # depth, used, makes another model.
    tool_free = [f for f in scene["with_tool"] if f.index not in HELD]
    alone, _ = update_step(scene["model"], scene["cam"], tool_free, _source([]), cfg)
    assert np.array_equal(new.tsdf, alone.tsdf) and np.array_equal(new.weight, alone.weight)
    used, _ = update_step(
        scene["model"],
        scene["cam"],
        scene["with_tool"],
        _source([]),
        replace(cfg, skip_occluded_frames=False),
    )
    assert not np.array_equal(used.tsdf, alone.tsdf)


def test_frames_without_an_instrument_are_all_used(scene: dict) -> None:
    cfg = UpdateConfig(skip_occluded_frames=True, register=False)
    _, rep = update_step(scene["model"], scene["cam"], scene["frames"], _source([]), cfg)
    assert rep.to_dict()["frames_skipped"] == []


def test_a_step_whose_every_frame_has_an_instrument_uses_them_all(scene: dict) -> None:
    h, w = scene["cam"].shape
    mask = np.ones((h, w), dtype=bool)
    frames = []
    for f in scene["frames"]:
        m = mask.copy()  # the instrument moves: each frame hides another column band
        m[:, (f.index * 5) % (w - 10) : (f.index * 5) % (w - 10) + 10] = False
        frames.append(replace(f, mask=m))
    cfg = UpdateConfig(skip_occluded_frames=True, register=False)
    asked: list[int] = []
    _, rep = update_step(scene["model"], scene["cam"], frames, _source(asked), cfg)
    assert rep.to_dict()["frames_skipped"] == [] and sorted(asked) == list(range(12))


def test_metric_depth_keeps_every_frame(scene: dict) -> None:
    """A tool does not throw off metric depth elsewhere in the frame, and the frame's
    other views count: exact depth is never left out."""
    cfg = UpdateConfig(skip_occluded_frames=True, register=False)
    asked: list[int] = []
    _, rep = update_step(
        scene["model"], scene["cam"], scene["with_tool"], _source(asked, metric=True), cfg
    )
    assert rep.to_dict()["frames_skipped"] == [] and sorted(asked) == list(range(12))
