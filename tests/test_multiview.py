"""The multi-view check of change masks, the noise-adaptive threshold, relative depth files."""

import numpy as np
import pytest
from test_updater_scenes import (
    BITE_HI,
    BITE_LO,
    bitten_mesh,
    camera,
    frames,
    poses,
    preop_model,
    tissue_mesh,
)

from chisel.batch import update_step
from chisel.change import (
    ChangeConfig,
    change_mask,
    frame_threshold,
    multiview_support,
    threshold_map,
)
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
    model = preop_model(tissue, cam)
    return {"tissue": tissue, "bitten": bitten_mesh(tissue), "cam": cam, "model": model}


def _blob(shape: tuple[int, int], centre: tuple[int, int], radius_px: int) -> np.ndarray:
    v, u = np.mgrid[: shape[0], : shape[1]]
    return (u - centre[0]) ** 2 + (v - centre[1]) ** 2 <= radius_px**2


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
    # The same through a threshold that grows with depth: 1 mm per mm puts frame 1's at its
    # render's depth, far above 3 mm; the other frames keep 1 mm.
    per = np.array([0.0, 1.0, 0.0, 0.0, 0.0])
    grown = multiview_support(masks, renders, estimates, cam, P, used, 1.0, 1.0, 1.0, per)
    np.testing.assert_array_equal(grown[0], support)
    np.testing.assert_array_equal(grown[1], observed)
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
    seen = []
    for i in range(6):
        Tcw = np.linalg.inv(P[i])
        pc = (Tcw[:3, :3] @ world.T).T + Tcw[:3, 3]
        uv, z = cam.project(pc)
        u, v = uv[:, 0], uv[:, 1]
        m = np.zeros(cam.shape, bool)
        ok = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width - 1) & (v < cam.height - 1)
        m[np.round(v[ok]).astype(int), np.round(u[ok]).astype(int)] = True
        seen.append(m & np.isfinite(renders[i]))
    kept = confirm_changes([det(i, seen[i]) for i in range(6)], cam, ChangeConfig(min_views=3))
    assert kept[0].mask[blob].mean() > 0.8


def test_frame_threshold_follows_the_noise() -> None:
    rng = np.random.default_rng(0)
    m_t = np.full((120, 160), 25.0, np.float32)
    cfg = ChangeConfig(noise_k=3.0, threshold_mm=1.0)
    # Exact depth: the fixed threshold.
    assert frame_threshold(m_t.copy(), m_t, cfg) == (1.0, 0.0)
    # Gaussian noise of 0.8 mm: about 3 x 0.8 mm.
    noisy = (m_t + rng.normal(0.0, 0.8, m_t.shape)).astype(np.float32)
    assert frame_threshold(noisy, m_t, cfg)[0] == pytest.approx(2.4, rel=0.1)
    # Half of the view really 3 mm deeper, with 0.2 mm noise: capped by the shallow side's
    # spread, the threshold stays far below the 3 mm change.
    half = (m_t + rng.normal(0.0, 0.2, m_t.shape)).astype(np.float32)
    half[:, :80] += 3.0
    assert frame_threshold(half, m_t, cfg)[0] < 2.0
    # Off: the fixed threshold whatever the noise.
    assert frame_threshold(noisy, m_t, ChangeConfig(noise_k=0.0)) == (1.0, 0.0)
    with pytest.raises(InvalidInputError, match="noise_k"):
        ChangeConfig(noise_k=-1.0)
    with pytest.raises(InvalidInputError, match="min_agreement"):
        ChangeConfig(min_agreement=1.5)
    with pytest.raises(InvalidInputError, match="min_views"):
        ChangeConfig(min_views=-1)


def test_threshold_grows_with_depth_for_a_relative_error() -> None:
    # A wall slanting from 10 to 40 mm deep, seen by an estimate whose error is 3 % of the
    # depth (a network's: abs-rel), with 2 mm of tissue removed where it is 11-16 mm deep.
    # One threshold per frame is 3 robust deviations of all of M' - M_t, set by the far
    # side (~2.2 mm), and misses the removal; 3 deviations of the relative error
    # (~0.09 x depth, 1.0-1.5 mm there) find it, and flag no unchanged pixel either way.
    H, W = 120, 160
    m_t = np.tile(np.linspace(10.0, 40.0, W, dtype=np.float32), (H, 1))
    removed = np.zeros((H, W), bool)
    removed[40:80, 8:32] = True
    truth = np.where(removed, m_t + 2.0, m_t)
    fixed, grows = ChangeConfig(), ChangeConfig(noise_with_depth=True)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        est = (truth * (1.0 + rng.normal(0.0, 0.03, (H, W)))).astype(np.float32)
        one, per = frame_threshold(est, m_t, fixed)
        assert per == 0.0 and one == pytest.approx(3 * 0.03 * 25.0, rel=0.15)
        floor, per = frame_threshold(est, m_t, grows)
        assert floor == 1.0 and per == pytest.approx(3 * 0.03, rel=0.15)
        assert not change_mask(est, m_t, fixed, one).any()
        found = change_mask(est, m_t, grows, threshold_map(floor, per, m_t))
        assert found[removed].mean() > 0.85 and not found[~removed].any()
    # Exact depth: the floor, whichever rule.
    assert frame_threshold(m_t.copy(), m_t, grows) == (1.0, 0.0)
    with pytest.raises(InvalidInputError, match="threshold_mm"):
        change_mask(m_t, m_t, grows, np.ones((H, W + 1), np.float32))


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
