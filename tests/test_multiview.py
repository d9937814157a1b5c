"""The multi-view check of change masks, the noise-adaptive threshold, relative depth files."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
from test_updater_scenes import (
    BITE_HI,
    BITE_LO,
    bitten_mesh,
    camera,
    frames,
    poses,
    preop_poses,
    tissue_mesh,
)

from chisel.batch import update_step
from chisel.build import BuildConfig, build_preop_model
from chisel.change import ChangeConfig, frame_threshold, multiview_support
from chisel.core.errors import InvalidInputError
from chisel.core.raycast import MeshRaycaster
from chisel.depth_source import CallableDepth, SequenceDepth
from chisel.detect import Detection, confirm_changes
from chisel.io.sequence import Frame, write_sequence
from chisel.mesh import extract_mesh
from chisel.update_config import UpdateConfig

SINGLE = ChangeConfig(min_views=0, noise_k=0.0)
"""The paper's per-frame detector: fixed threshold, every frame trusted alone."""


@pytest.fixture(scope="module")
def scene() -> dict:
    tissue = tissue_mesh()
    cam = camera()
    model = build_preop_model(tissue, cam, preop_poses(30, seed=1), BuildConfig(voxel_size_mm=0.5))
    return {"tissue": tissue, "bitten": bitten_mesh(tissue), "cam": cam, "model": model}


def _blob(shape: tuple[int, int], centre: tuple[int, int], radius_px: int) -> np.ndarray:
    v, u = np.mgrid[: shape[0], : shape[1]]
    return (u - centre[0]) ** 2 + (v - centre[1]) ** 2 <= radius_px**2


def _pixels_of(cam, T_world_from_cam: np.ndarray, world: np.ndarray, render: np.ndarray):
    """(H, W) bool: the pixels where a camera at ``T_world_from_cam`` sees ``world`` points
    (nearest pixel), on the surface its ``render`` shows."""
    Tcw = np.linalg.inv(T_world_from_cam)
    uv, z = cam.project((Tcw[:3, :3] @ world.T).T + Tcw[:3, 3])
    u, v = uv[:, 0], uv[:, 1]
    ok = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width - 1) & (v < cam.height - 1)
    m = np.zeros(cam.shape, bool)
    m[np.round(v[ok]).astype(int), np.round(u[ok]).astype(int)] = True
    return m & np.isfinite(render)


def test_support_counts_on_a_plane(scene: dict) -> None:
    # Unchanged tissue, exact renders: a pixel that one frame claims changed is observed
    # by the other frames that see its point, and none of them supports it.
    cam = scene["cam"]
    P = poses(5, seed=3, spread_mm=1.0)
    rc = MeshRaycaster.from_trimesh(scene["tissue"])
    renders = np.stack([rc.render_depth(cam, T) for T in P])
    estimates = renders.copy()
    masks = np.zeros(renders.shape, bool)
    masks[0] = _blob(cam.shape, (48, 40), 6) & np.isfinite(renders[0])
    used = np.ones(5, bool)
    support, observed = multiview_support(masks, renders, estimates, cam, P, used, 1.0, 1.0)
    on = masks[0]
    assert support[0][on].max() == 0
    assert observed[0][on].min() >= 3 and observed[0][on].max() == 4  # the others see it
    assert observed[1:].max() == 0 and support[~masks].max() == 0
    # If the other frames' estimates are deeper there too, every observer supports it.
    estimates[1:] += 3.0
    support, observed4 = multiview_support(masks, renders, estimates, cam, P, used, 1.0, 1.0)
    np.testing.assert_array_equal(support, observed4)
    # A frame whose registration failed neither votes nor counts.
    used[2] = False
    _, observed3 = multiview_support(masks, renders, estimates, cam, P, used, 1.0, 1.0)
    assert np.all(observed3[0][on] <= observed4[0][on]) and observed3[0][on].max() == 3
    # Per-frame thresholds: frame 1 needs more than 3 mm, so it observes but does not support.
    thr = np.array([1.0, 3.5, 1.0, 1.0, 1.0])
    support, observed = multiview_support(masks, renders, estimates, cam, P, used, thr, 1.0)
    np.testing.assert_array_equal(observed, observed3)
    assert np.all(support[0][on] <= observed[0][on]) and np.any(support[0][on] < observed[0][on])
    with pytest.raises(InvalidInputError, match="renders_mm"):
        multiview_support(masks, renders[:4], estimates, cam, P, used, 1.0, 1.0)
    with pytest.raises(InvalidInputError, match="T_world_from_cams"):
        multiview_support(masks, renders, estimates, cam, P[:4], used, 1.0, 1.0)


def test_confirmation_is_a_pure_function_of_the_detections(scene: dict) -> None:
    # Frame 0 alone claims a 3 mm change on unchanged tissue: the others see the point
    # unchanged, so the change goes; its detection is returned anew, the input untouched.
    cam = scene["cam"]
    P = poses(6, seed=3, spread_mm=1.0)
    rc = MeshRaycaster.from_trimesh(scene["tissue"])
    renders = [rc.render_depth(cam, T) for T in P]
    blob = _blob(cam.shape, (48, 40), 8) & np.isfinite(renders[0])

    def det(i: int, deeper: np.ndarray) -> Detection:
        raw = np.where(deeper, renders[i] + 3.0, renders[i]).astype(np.float32)
        return Detection(
            index=i, used=True, threshold_mm=1.0, T_world_from_cam=P[i], mask=deeper.copy(),
            m_prime=raw, m_t=renders[i], m_raw=raw,
        )  # fmt: skip

    none = np.zeros(cam.shape, bool)
    dets = [det(0, blob)] + [det(i, none) for i in range(1, 6)]
    out = confirm_changes(dets, cam, ChangeConfig(min_views=3, min_agreement=0.8))
    assert not out[0].mask.any() and out[0].unconfirmed_px == blob.sum() > 100
    assert np.array_equal(dets[0].mask, blob) and dets[0].unconfirmed_px == 0
    with pytest.raises(AttributeError):
        out[0].mask = blob  # type: ignore[misc]
    # The same change seen by every frame (each frame's render pushed 3 mm deeper where
    # it sees the blob's points) is kept by all: removal is removal in every view.
    pts = cam.backproject(renders[0])[blob]
    world = (P[0][:3, :3] @ pts.T).T + P[0][:3, 3]
    seen = [_pixels_of(cam, P[i], world, renders[i]) for i in range(6)]
    kept = confirm_changes([det(i, seen[i]) for i in range(6)], cam, ChangeConfig(min_views=3))
    assert kept[0].mask[blob].mean() > 0.8


def test_frame_threshold_follows_the_noise() -> None:
    rng = np.random.default_rng(0)
    m_t = np.full((120, 160), 25.0, np.float32)
    cfg = ChangeConfig(noise_k=3.0, threshold_mm=1.0)
    # Exact depth: the fixed threshold.
    assert frame_threshold(m_t.copy(), m_t, cfg) == 1.0
    # Gaussian noise of 0.8 mm: about 3 x 0.8 mm.
    noisy = (m_t + rng.normal(0.0, 0.8, m_t.shape)).astype(np.float32)
    assert frame_threshold(noisy, m_t, cfg) == pytest.approx(2.4, rel=0.1)
    # Half of the view really 3 mm deeper, with 0.2 mm noise: capped by the shallow side's
    # spread, the threshold stays far below the 3 mm change.
    half = (m_t + rng.normal(0.0, 0.2, m_t.shape)).astype(np.float32)
    half[:, :80] += 3.0
    assert frame_threshold(half, m_t, cfg) < 2.0
    # Off: the fixed threshold whatever the noise.
    assert frame_threshold(noisy, m_t, ChangeConfig(noise_k=0.0)) == 1.0
    with pytest.raises(InvalidInputError, match="noise_k"):
        ChangeConfig(noise_k=-1.0)
    with pytest.raises(InvalidInputError, match="min_agreement"):
        ChangeConfig(min_agreement=1.5)
    with pytest.raises(InvalidInputError, match="min_views"):
        ChangeConfig(min_views=-1)


def test_one_frames_depth_error_is_not_carved(scene: dict) -> None:
    # Exact depth everywhere except a 6 mm-too-deep blob on unchanged tissue in one frame
    # (a network's error): the single-frame detector carves it for good, the multi-view
    # check does not, and the true bite is carved either way.
    cam, model = scene["cam"], scene["model"]
    P = poses(12, seed=2)
    fr = frames(scene["bitten"], cam, P)
    blob = _blob(cam.shape, (15, 15), 7)

    def depth(f: Frame) -> np.ndarray:
        d = f.depth_mm.copy()
        if f.index == 4:
            d[blob] += 6.0
        return d

    src = CallableDepth(depth, metric=True)
    # The paper's detector and carving (every changed pixel fuses its depth).
    single, rep_single = update_step(
        model, cam, fr, src, UpdateConfig(change=SINGLE, carve="paper")
    )
    multi, rep_multi = update_step(model, cam, fr, src, UpdateConfig())
    assert rep_single.frames[4].changed_fraction > rep_multi.frames[4].changed_fraction
    assert rep_multi.frames[4].unconfirmed_px >= blob.sum() * 0.8
    rc0 = MeshRaycaster.from_trimesh(extract_mesh(model))
    d0 = rc0.render_depth(cam, P[4])
    d_single = MeshRaycaster.from_trimesh(extract_mesh(single)).render_depth(cam, P[4])
    d_multi = MeshRaycaster.from_trimesh(extract_mesh(multi)).render_depth(cam, P[4])
    on_blob = blob & np.isfinite(d0)
    assert np.nanmedian(d_single[on_blob] - d0[on_blob]) > 2.0  # carved by one frame's error
    assert np.nanmax(np.abs(d_multi[on_blob] - d0[on_blob])) < 0.25  # left alone
    # The bite itself is carved by both: its floor (z = 29) appears.
    for new in (single, multi):
        v = extract_mesh(new).vertices
        inside = np.all((v >= BITE_LO + [0.5, 0.5, 0]) & (v <= BITE_HI - [0.5, 0.5, 0]), axis=1)
        assert np.sum(inside & (np.abs(v[:, 2] - 29.0) < 0.5)) > 50


def test_relative_depth_folders_are_not_metric(scene: dict, tmp_path) -> None:
    cam = scene["cam"]
    fr = frames(scene["bitten"], cam, poses(2, seed=2))
    write_sequence(tmp_path / "metric", cam, fr)
    write_sequence(
        tmp_path / "relative", cam, fr, meta={"depth_prediction": {"relative_depth": True}}
    )
    assert SequenceDepth(tmp_path / "metric").is_metric
    assert not SequenceDepth(tmp_path / "relative").is_metric


def _tool_scene(scene: dict) -> tuple:
    """Eight frames of unchanged tissue; frame 0's blob, where each frame sees it, and an
    instrument over it (its pixels and their neighbours: > 2 % of the view)."""
    cam = scene["cam"]
    P = poses(8, seed=2, spread_mm=1.0)  # every frame sees all of the blob
    fr = frames(scene["tissue"], cam, P)
    blob = _blob(cam.shape, (48, 40), 8) & np.isfinite(fr[0].depth_mm)
    world = (P[0][:3, :3] @ cam.backproject(fr[0].depth_mm)[blob].T).T + P[0][:3, 3]
    seen = [_pixels_of(cam, P[i], world, f.depth_mm) for i, f in enumerate(fr)]
    assert all(m.sum() > 170 for m in seen)
    tool = [cv2.dilate(m.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0 for m in seen]
    return cam, P, fr, blob, seen, tool


def test_a_hidden_view_votes_as_its_neighbour_in_time(scene: dict) -> None:
    # Frames 1-4 see frame 0's 3 mm change, frame 5 sees the point unchanged, and an
    # instrument hides it from frames 6-7, which without it would see what frame 5 sees.
    # Ignoring the hidden views, 4 of 5 agree (kept); the tool-free step has 4 of 7
    # (refused); frames 6-7 voting as frame 5, their nearest frame in time that sees the
    # point, give the tool-free count.
    cam, P, fr, blob, seen, tool = _tool_scene(scene)
    R = np.stack([f.depth_mm for f in fr]).astype(np.float32)
    changed = np.stack([seen[i] if i < 5 else np.zeros(cam.shape, bool) for i in range(8)])
    E = np.where(changed, R + 3.0, R).astype(np.float32)
    hidden = np.zeros(R.shape, bool)
    hidden[6:] = np.stack(tool[6:])
    E_hid = np.where(hidden, np.nan, E).astype(np.float32)
    used = np.ones(8, bool)

    def counts(est: np.ndarray, hid: np.ndarray | None, window: int) -> tuple:
        sup, obs = multiview_support(changed, R, est, cam, P, used, 1.0, 1.0, 0.5, hid, window)
        return sup[0][blob], obs[0][blob]

    def kept(sup: np.ndarray, obs: np.ndarray) -> float:
        return float(np.mean((sup >= 3) & (sup >= 0.8 * obs)))

    free_sup, free_obs = counts(E, None, 0)
    assert kept(free_sup, free_obs) < 0.2
    sup, obs = counts(E_hid, hidden, 0)  # hidden views do not count
    np.testing.assert_array_equal(sup, free_sup)
    assert np.mean(obs == free_obs - 2) > 0.9 and kept(sup, obs) > 0.8
    sup, obs = counts(E_hid, hidden, 8)
    np.testing.assert_array_equal(sup, free_sup)
    assert np.mean(obs == free_obs) > 0.9 and kept(sup, obs) < 0.2
    # With a window of one frame, frame 7's neighbours are frame 6 (hidden) and none.
    _, obs1 = counts(E_hid, hidden, 1)
    assert np.mean(obs1 == free_obs - 1) > 0.9
    with pytest.raises(InvalidInputError, match="hidden"):
        multiview_support(changed, R, E_hid, cam, P, used, 1.0, 1.0, 0.5, hidden[:, :10], 8)
    with pytest.raises(InvalidInputError, match="hidden_vote_frames"):
        ChangeConfig(hidden_vote_frames=-1)


def test_an_update_with_an_instrument_keeps_the_tool_free_verdict(scene: dict) -> None:
    # The same through update_step, with the frames' masks: the 3 mm "change" on unchanged
    # tissue that frames 0-4 see and frames 5-7 do not is refused with the instrument over
    # it in frames 6-7, as without it; the step without frames 6-7 at all carves it (4 of
    # 5 agree), so the hidden views' votes are what keep it.
    cam, P, fr, blob, seen, tool = _tool_scene(scene)
    model = scene["model"]
    src = CallableDepth(
        lambda f: np.where(seen[f.index] & (f.index < 5), f.depth_mm + 3.0, f.depth_mm),
        metric=True,
    )
    masked = [f if f.index < 6 else replace(f, mask=~tool[f.index]) for f in fr]
    cfg = UpdateConfig(change=ChangeConfig(min_views=3))
    d0 = MeshRaycaster.from_trimesh(extract_mesh(model)).render_depth(cam, P[0])

    def carved(frames_: list[Frame]) -> float:
        new, _ = update_step(model, cam, frames_, src, cfg)
        d = MeshRaycaster.from_trimesh(extract_mesh(new)).render_depth(cam, P[0])
        return float(np.nanmedian(d[blob] - d0[blob]))

    assert abs(carved(fr)) < 0.25
    assert abs(carved(masked)) < 0.25
    assert carved(fr[:6]) > 2.0
