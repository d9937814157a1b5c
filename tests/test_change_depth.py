"""The change-aware depth network (chisel.depth.change_aware): tiny images, seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from wall_scenes import H, W, wall_pairs, wall_scene

from chisel.batch import update_step
from chisel.build import BuildConfig, build_preop_model
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera
from chisel.core.raycast import MeshRaycaster
from chisel.depth import DepthNet, DepthNetConfig, DepthPredictor, export_model, save_checkpoint
from chisel.depth.change_aware import (
    ChangeAwarePredictor,
    ChangeNet,
    ChangeNetConfig,
    load_change_checkpoint,
    save_change_checkpoint,
)
from chisel.depth.change_source import (
    ChangeAwareDepthSource,
    export_change_aware,
    load_change_aware_source,
)
from chisel.depth.change_train import (
    ChangeTrainConfig,
    PriorSet,
    change_loss,
    train_change_aware,
)
from chisel.depth.checkpoint import CheckpointError, load_checkpoint
from chisel.depth.prior_data import StepSequenceRef, build_prior_set
from chisel.depth_source import estimate_depth, wants_prior
from chisel.io.sequence import Frame, SequenceWriter
from chisel.render import ModelRenderer
from chisel.update_config import UpdateConfig
from chisel.updater import ChiselUpdater

TINY = ChangeNetConfig(widths=(8, 12), input_scale=1.0)


@pytest.fixture(scope="module")
def tiny_trained() -> ChangeNet:
    cfg = ChangeTrainConfig(steps=150, batch_size=8, lr=1e-2, seed=0, num_threads=1, eval_every=150)
    return train_change_aware(wall_pairs(64, seed=1), cfg, TINY).net


def test_untrained_network_returns_the_render_exactly() -> None:
    pairs = wall_pairs(2, seed=3)
    prior = pairs.prior_mm.clone()
    prior[0, :3] = float("nan")
    depth, p = ChangeAwarePredictor(ChangeNet(TINY)).eval()(pairs.rgb, prior)
    assert torch.equal(torch.isnan(depth), torch.isnan(prior))
    ok = torch.isfinite(prior)
    assert torch.equal(depth[ok], prior[ok])
    assert torch.allclose(p, torch.full_like(p, 0.5))


class _FixedHead(ChangeAwarePredictor):
    """A predictor whose network outputs are given: (log-ratio correction, change logit)."""

    def __init__(self, r: torch.Tensor, c: torch.Tensor, decision_p: float = 0.5) -> None:
        super().__init__(ChangeNet(TINY), decision_p)
        self._r, self._c = r, c

    def raw(self, rgb: torch.Tensor, prior_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self._r, self._c


def test_output_is_the_render_where_the_change_head_says_unchanged() -> None:
    pairs = wall_pairs(1, seed=5)
    r = torch.full((1, 1, H, W), 0.5)
    c = torch.full((1, 1, H, W), -1.0)  # p = 0.27: a large correction, but "unchanged"
    c[..., W // 2 :] = 2.0  # p = 0.88: "changed"
    depth, p = _FixedHead(r, c).eval()(pairs.rgb, pairs.prior_mm)
    prior = pairs.prior_mm[0]
    assert torch.equal(depth[0, :, : W // 2], prior[:, : W // 2])
    expect = prior[:, W // 2 :] * torch.exp(torch.tensor(0.5) * torch.sigmoid(torch.tensor(2.0)))
    assert torch.allclose(depth[0, :, W // 2 :], expect)
    assert torch.allclose(p[0, :, W // 2 :], torch.sigmoid(torch.tensor(2.0)))


def test_the_decision_probability_is_kept_in_the_export(tmp_path: Path) -> None:
    """A change at p = 0.6 is applied at the default decision (0.5, the change head's own
    boundary) and not at 0.7; a TorchScript export keeps the decision it was made with."""
    from chisel.depth.change_aware import CHANGE_DECISION_P

    pairs = wall_pairs(1, seed=6)
    r = torch.full((1, 1, H, W), 0.5)
    c = torch.full((1, 1, H, W), float(np.log(0.6 / 0.4)))  # p = 0.6
    prior = pairs.prior_mm[0]
    moved = prior * torch.exp(torch.tensor(0.5 * 0.6))
    for decision_p, expect in ((CHANGE_DECISION_P, moved), (0.7, prior)):
        head = _FixedHead(r, c, decision_p).eval()
        depth, _ = head(pairs.rgb, pairs.prior_mm)
        assert torch.allclose(depth[0], expect)
    net = ChangeNet(TINY)
    ts = export_change_aware(ChangeAwarePredictor(net, decision_p=0.55), tmp_path / "ts.pt")
    assert torch.jit.load(str(ts)).decision_p == 0.55
    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(InvalidInputError, match="decision_p"):
            ChangeAwarePredictor(net, decision_p=bad)


def test_no_change_output_equals_the_render(tiny_trained: ChangeNet) -> None:
    rng = np.random.default_rng(11)
    predictor = ChangeAwarePredictor(tiny_trained).eval()
    for _ in range(4):
        rgb, prior, _, _ = wall_scene(rng, window=False)
        depth, _ = predictor(torch.from_numpy(rgb)[None], torch.from_numpy(prior)[None])
        rel = np.abs(depth[0].detach().numpy() - prior) / prior
        assert np.median(rel) < 0.01 and np.percentile(rel, 90) < 0.03


def test_known_window_comes_out_deeper(tiny_trained: ChangeNet) -> None:
    rng = np.random.default_rng(12)
    predictor = ChangeAwarePredictor(tiny_trained).eval()
    for _ in range(4):
        rgb, prior, target, win = wall_scene(rng, window=True)
        depth, p = predictor(torch.from_numpy(rgb)[None], torch.from_numpy(prior)[None])
        d, p = depth[0].detach().numpy(), p[0].detach().numpy()
        gap = float(np.median(target[win] - prior[win]))
        # Inside the window (away from its edge) most of the gap is found ...
        inner = (
            win
            & np.roll(win, 2, 0)
            & np.roll(win, -2, 0)
            & np.roll(win, 2, 1)
            & np.roll(win, -2, 1)
        )
        assert np.median(d[inner] - prior[inner]) > 0.5 * gap
        # ... and far from it the wall stays where the render says.
        outside = (
            ~win
            & ~np.roll(win, 3, 0)
            & ~np.roll(win, -3, 0)
            & ~np.roll(win, 3, 1)
            & ~np.roll(win, -3, 1)
        )
        assert np.median(np.abs(d[outside] - prior[outside])) < 0.5
        assert p[inner].mean() > p[outside].mean() + 0.3


def test_a_few_training_steps_lower_the_loss() -> None:
    pairs = wall_pairs(16, seed=5)
    cfg = ChangeTrainConfig(steps=30, batch_size=8, lr=1e-2, seed=0, num_threads=1, flips=False,
                            photometric=0.0)  # fmt: skip

    def loss_of(net: ChangeNet) -> float:
        pred = ChangeAwarePredictor(net).eval()
        with torch.no_grad():
            r, c = pred.raw(pairs.rgb, pairs.prior_mm)
        return float(change_loss(r, c, pairs.prior_mm, pairs.target_mm, pairs.changed, cfg)[0])

    torch.manual_seed(0)
    before = loss_of(ChangeNet(TINY))
    after = loss_of(train_change_aware(pairs, cfg, TINY).net)
    assert after < 0.7 * before


def test_training_is_seeded() -> None:
    pairs = wall_pairs(8, seed=6)
    cfg = ChangeTrainConfig(steps=4, batch_size=4, seed=3, num_threads=1)
    a = train_change_aware(pairs, cfg, TINY).net.state_dict()
    b = train_change_aware(pairs, cfg, TINY).net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_checkpoint_round_trip_and_torchscript(tmp_path: Path) -> None:
    net = ChangeNet(TINY)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.01 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    ck = save_change_checkpoint(tmp_path / "ca.pt", net, {"command": "test"})
    sidecar = json.loads((tmp_path / "ca.json").read_text())
    assert sidecar["kind"] == "change-aware" and sidecar["info"]["command"] == "test"
    loaded, info = load_change_checkpoint(ck)
    assert info["command"] == "test"
    pairs = wall_pairs(1, seed=2)
    ref, _ = ChangeAwarePredictor(net).eval()(pairs.rgb, pairs.prior_mm)
    ts = export_change_aware(ChangeAwarePredictor(loaded), tmp_path / "ca_ts.pt")
    for source in (load_change_aware_source(ck), load_change_aware_source(ts)):
        frame = Frame(0, np.eye(4), rgb=pairs.rgb[0].numpy())
        out = source(frame, prior_mm=pairs.prior_mm[0].numpy())
        assert np.allclose(out, ref[0].detach().numpy(), atol=1e-4)
        assert source.is_metric and wants_prior(source)


def test_kind_mismatch_is_refused_naming_both(tmp_path: Path) -> None:
    mono = save_checkpoint(
        tmp_path / "mono.pt", DepthNet(DepthNetConfig(widths=(4, 8), blocks=(0, 0)))
    )
    change = save_change_checkpoint(tmp_path / "change.pt", ChangeNet(TINY))
    for load, path in (
        (load_change_checkpoint, mono),
        (load_change_aware_source, mono),
        (load_checkpoint, change),
    ):
        with pytest.raises(CheckpointError, match="monocular") as err:
            load(path)
        assert "change-aware" in str(err.value) and str(path) in str(err.value)
    ts = export_model(
        DepthPredictor(DepthNet(DepthNetConfig(widths=(4, 8), blocks=(0, 0)))), tmp_path / "m.pt"
    )
    with pytest.raises(CheckpointError, match="'monocular' TorchScript .*'change-aware'"):
        load_change_aware_source(ts)


def test_prior_of_another_size_and_missing_prior_are_refused() -> None:
    source = ChangeAwareDepthSource(ChangeAwarePredictor(ChangeNet(TINY)))
    frame = Frame(3, np.eye(4), rgb=np.zeros((H, W, 3), np.uint8))
    with pytest.raises(InvalidInputError, match=r"prior render is 20x16 but the frame is 40x32"):
        source(frame, prior_mm=np.full((16, 20), 10.0, np.float32))
    with pytest.raises(InvalidInputError, match="needs the model's render"):
        source(frame)
    with pytest.raises(InvalidInputError, match="needs the model's render"):
        estimate_depth(source, frame, None)


def _plane(z_mm: float) -> trimesh.Trimesh:
    v = np.array([[-50, -50, z_mm], [50, -50, z_mm], [50, 50, z_mm], [-50, 50, z_mm]], float)
    return trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)


def test_prior_pairs_label_removed_tissue_not_tracking_error(tmp_path: Path) -> None:
    """Step 1 removes the wall at z = 20 (the next surface is at z = 26); tracking is off by
    0.3 mm along z. The prior is the step-0 wall at the tracked pose; the target is step 1's
    surface at the tracked pose (default) or the true depth; either way the label marks
    removed tissue only, so the preop sweep has none despite the tracking error."""
    phantom = tmp_path / "phantoms" / "seed_1000"
    (phantom / "meshes").mkdir(parents=True)
    _plane(20.0).export(phantom / "meshes" / "step_00.ply")
    _plane(26.0).export(phantom / "meshes" / "step_01.ply")
    steps = [{"step": k, "mesh": f"meshes/step_0{k}.ply"} for k in (0, 1)]
    (phantom / "phantom.json").write_text(json.dumps({"steps": steps}))
    cam = Camera(W, H, np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]]))
    true = np.eye(4)
    tracked = np.eye(4)
    tracked[2, 3] = 0.3
    for step, z in ((0, 20.0), (1, 26.0)):
        # Both cameras within 0.3 mm of the world origin, which the reader would take for
        # metres: the scene says its poses are mm on purpose.
        meta = {"pose_units_checked": False}
        with SequenceWriter(tmp_path / f"step_{step}", cam, meta=meta) as w:
            for i in range(2):
                w.add(Frame(i, tracked, rgb=np.full((H, W, 3), 90, np.uint8),
                            depth_mm=np.full((H, W), z, np.float32), T_world_from_cam_true=true))  # fmt: skip
    refs = [StepSequenceRef(tmp_path / f"step_{k}", 1000, k, phantom) for k in (0, 1)]
    for target_pose, step1_target in (("tracked", 26.0 - 0.3), ("true", 26.0)):
        pairs = build_prior_set(refs, target_pose=target_pose)
        assert len(pairs) == 4
        # The prior is always the step-0 wall at the tracked pose.
        assert np.allclose(pairs.prior_mm.numpy(), 20.0 - 0.3, atol=1e-3)
        assert not pairs.changed[:2].any() and pairs.changed[2:].all()
        assert np.allclose(pairs.target_mm[2:].numpy(), step1_target, atol=1e-3)
        assert np.allclose(pairs.true_mm[2:].numpy(), 26.0)
    # Tracked target: the preop frames' target is the prior itself (no change).
    pairs = build_prior_set(refs[:1])
    assert np.allclose(pairs.target_mm.numpy(), pairs.prior_mm.numpy())


class _RecordingPrior:
    """A metric depth source that wants the prior: returns the true depth, keeps the priors."""

    is_metric = True
    wants_prior = True

    def __init__(self, truth: trimesh.Trimesh, camera: Camera) -> None:
        self.rc = MeshRaycaster.from_trimesh(truth)
        self.camera = camera
        self.priors: dict[int, np.ndarray] = {}

    def __call__(self, frame: Frame, prior_mm: np.ndarray) -> np.ndarray:
        self.priors[frame.index] = prior_mm
        return self.rc.render_depth(self.camera, frame.T_world_from_cam)


def test_updater_hands_the_model_render_to_a_source_that_wants_it() -> None:
    from test_updater_scenes import bitten_mesh, camera, frames, poses, preop_poses, tissue_mesh

    tissue = tissue_mesh()
    cam = camera(48, 40)
    model = build_preop_model(tissue, cam, preop_poses(12, seed=1), BuildConfig(voxel_size_mm=1.0))
    P = poses(3, seed=2)
    fr = frames(bitten_mesh(tissue), cam, P)
    renderer = ModelRenderer(model)
    expected = [renderer.render(cam, T) for T in P]
    for register in (True, False):  # batch, with and without registration
        src = _RecordingPrior(bitten_mesh(tissue), cam)
        update_step(model, cam, fr, src, UpdateConfig(register=register))
        assert sorted(src.priors) == [0, 1, 2]
        for i, R in enumerate(expected):
            assert np.allclose(src.priors[i], R, equal_nan=True)
    src = _RecordingPrior(bitten_mesh(tissue), cam)  # streaming, one frame at a time
    upd = ChiselUpdater(model, cam, src, UpdateConfig(register=False))
    upd.begin_step()
    upd.process(fr[1])
    assert np.allclose(src.priors[1], expected[1], equal_nan=True)


def test_shipped_checkpoint_on_a_wall_with_a_window() -> None:
    """The shipped checkpoint (trained on phantom renders only) on a synthetic textured wall
    at 320x256: without change it returns the render (median within 2 %); with a window
    onto a wall 6 mm behind (darker, as an endoscope's light falls off) it comes out
    deeper inside the window and more sure of a change there. (It overshoots the depth
    there: 6 mm is not the phantoms' regime; docs/depth.md.)"""
    from chisel.depth.change_aware import DEFAULT_CHANGE_CHECKPOINT

    source = load_change_aware_source(DEFAULT_CHANGE_CHECKPOINT)
    h, w = 256, 320
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    prior = (12.0 + 0.01 * (xx - w / 2)).astype(np.float32)
    texture = 0.5 + 0.15 * np.sin(0.15 * xx) * np.cos(0.11 * yy)
    win = np.zeros((h, w), bool)
    win[90:170, 110:210] = True
    for window in (False, True):
        target = np.where(win & window, prior + 6.0, prior)
        gray = np.clip(texture * (12.0 / target) ** 2, 0.0, 1.0)
        rgb = (np.stack([gray, 0.55 * gray, 0.45 * gray], axis=-1) * 255).astype(np.uint8)
        depth = source(Frame(0, np.eye(4), rgb=rgb), prior_mm=prior)
        p = source.last_change_probability
        assert np.median(np.abs(depth - prior)[~win] / prior[~win]) < 0.02
        if window:
            assert np.median(depth[win] - prior[win]) > 3.0
            assert p[win].mean() > p[~win].mean() + 0.3


def test_synthetic_removal_puts_a_lamella_in_front_in_the_prior_only() -> None:
    import torch

    from chisel.core.errors import InvalidInputError
    from chisel.depth.prior_data import SYNTHETIC_REMOVAL_MM, add_synthetic_removal

    n, H, W = 6, 40, 48
    prior = torch.full((n, H, W), 20.0)
    prior[:, :, :4] = float("nan")  # outside the field stop
    pairs = PriorSet(
        rgb=torch.zeros((n, H, W, 3), dtype=torch.uint8),
        prior_mm=prior,
        target_mm=prior.clone(),
        changed=torch.zeros((n, H, W), dtype=torch.bool),
        sources=[f"s#{i}" for i in range(n)],
    )
    before = pairs.prior_mm.clone()
    out = add_synthetic_removal(pairs, 1.0, seed=3)
    assert torch.equal(pairs.prior_mm.nan_to_num(), before.nan_to_num())  # input untouched
    assert torch.equal(out.target_mm.nan_to_num(), pairs.target_mm.nan_to_num())
    for i in range(n):
        ch = out.changed[i].numpy()
        p = out.prior_mm[i].numpy()
        assert ch.any() and not ch[:, :4].any()  # a removal, only where the prior is valid
        lo, hi = SYNTHETIC_REMOVAL_MM
        gap = 20.0 - p[ch]
        assert np.all(gap >= lo - 1e-5) and np.all(gap <= hi + 1e-5)
        assert np.ptp(gap) < 1e-5  # one lamella, parallel to the surface
        np.testing.assert_array_equal(p[~ch & np.isfinite(p)], 20.0)
    again = add_synthetic_removal(pairs, 1.0, seed=3)
    assert torch.equal(again.prior_mm.nan_to_num(), out.prior_mm.nan_to_num())
    off = add_synthetic_removal(pairs, 0.0, seed=3)
    assert torch.equal(off.prior_mm.nan_to_num(), before.nan_to_num()) and not off.changed.any()
    with pytest.raises(InvalidInputError, match="synthetic-removal"):
        add_synthetic_removal(pairs, 1.5, seed=0)
