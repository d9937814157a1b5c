"""The monocular depth network: losses, metrics, checkpoints, training, inference, CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from chisel import cli
from chisel.core.errors import EmptyResultError, FormatVersionError, InvalidInputError
from chisel.core.geometry import Camera, look_at
from chisel.core.raycast import MeshRaycaster
from chisel.depth import (
    DEFAULT_CHECKPOINT,
    EFFECTS_CHECKPOINT,
    AugmentConfig,
    CheckpointError,
    DepthNet,
    DepthNetConfig,
    DepthPredictor,
    SequenceRef,
    TrainConfig,
    check_training_seeds,
    evaluate_source,
    export_model,
    find_sequences,
    frame_metrics,
    gradient_matching_loss,
    load_checkpoint,
    load_depth_source,
    load_frames,
    predict_sequence,
    save_checkpoint,
    scale_invariant_log_loss,
    split_by_group,
    train,
)
from chisel.depth.change_aware import DEFAULT_CHANGE_CHECKPOINT
from chisel.depth.data import augment, downsample_targets
from chisel.depth.train import resolve_device
from chisel.io.sequence import Frame, Sequence, SequenceWriter

TINY = DepthNetConfig(widths=(8, 12, 16), blocks=(1, 1, 1))
W, H = 64, 48


# --------------------------------------------------------------------------- tiny scenes


def _tube_scene(seed: int) -> trimesh.Trimesh:
    """A capped tube (a nasal-passage stand-in) with a few bumps on its wall, mm."""
    rng = np.random.default_rng(seed)
    parts = [trimesh.creation.cylinder(radius=9.0 + rng.uniform(-1, 1), height=80.0, sections=48)]
    for _ in range(5):
        a = rng.uniform(0, 2 * np.pi)
        bump = trimesh.creation.icosphere(subdivisions=2, radius=rng.uniform(2.0, 4.0))
        bump.apply_translation([9.0 * np.cos(a), 9.0 * np.sin(a), rng.uniform(-5, 35)])
        parts.append(bump)
    return trimesh.util.concatenate(parts)


def _shade(camera: Camera, depth: np.ndarray, seed: int) -> np.ndarray:
    """Lambertian shading with the light at the camera, inverse-square fall-off, texture."""
    pts = camera.backproject(np.nan_to_num(depth, nan=1e3))
    du = np.gradient(pts, axis=1)
    dv = np.gradient(pts, axis=0)
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    view = pts / (np.linalg.norm(pts, axis=-1, keepdims=True) + 1e-12)
    cos = np.abs(np.sum(n * view, axis=-1))
    phase = seed * 0.37
    albedo = 0.75 + 0.2 * np.sin(0.9 * pts[..., 0] + phase) * np.sin(0.7 * pts[..., 2])
    intensity = np.clip(albedo * (0.15 + 0.85 * cos) * (120.0 / depth**2), 0, 1)
    intensity = np.where(np.isfinite(depth), intensity, 0.0)
    rgb = intensity[..., None] * np.array([1.0, 0.6, 0.55])
    return (255 * np.clip(rgb, 0, 1)).astype(np.uint8)


def make_sequence(path: Path, seed: int, frames: int = 6, with_mask: bool = True) -> Path:
    """Render a tiny tube sequence (64x48) with true depth, RGB and a circular mask."""
    rng = np.random.default_rng(seed)
    mesh = _tube_scene(seed)
    rc = MeshRaycaster.from_trimesh(mesh)
    cam = Camera.from_fov(W, H, 80.0)
    v, u = np.mgrid[0:H, 0:W]
    circle = (u - cam.cx) ** 2 + (v - cam.cy) ** 2 < (0.55 * W) ** 2
    with SequenceWriter(path, cam, meta={"phantom_seed": seed}) as w:
        for i in range(frames):
            eye = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), -30.0 + 3.0 * i])
            target = eye + np.array([rng.uniform(-6, 6), rng.uniform(-6, 6), 20.0])
            T = look_at(eye, target, up=[0.0, -1.0, 0.0])
            depth = rc.render_depth(cam, T)
            w.add(
                Frame(
                    index=i,
                    T_world_from_cam=T,
                    rgb=_shade(cam, depth, seed),
                    depth_mm=depth,
                    mask=circle if with_mask else None,
                    T_world_from_cam_true=T,
                )
            )
    return path


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dataset folder like ``python -m sim dataset`` writes: dataset.json + sequences."""
    root = tmp_path_factory.mktemp("depth_data")
    entries = []
    for seed in (1000, 1001, 1002):
        make_sequence(root / f"seq_{seed}", seed)
        entries.append({"path": f"seq_{seed}", "phantom_seed": seed})
    (root / "dataset.json").write_text(json.dumps({"sequences": entries}))
    return root


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory: pytest.TempPathFactory, dataset: Path) -> Path:
    frames = load_frames(find_sequences([dataset]))
    cfg = TrainConfig(num_threads=1, epochs=2, batch_size=4, seed=3, augment=None)
    result = train(frames, cfg, TINY)
    return save_checkpoint(tmp_path_factory.mktemp("ck") / "tiny.pt", result.net, {"note": "t"})


# --------------------------------------------------------------------------- losses


def _t(a: list) -> torch.Tensor:
    return torch.tensor(a, dtype=torch.float64)


def test_scale_invariant_loss_hand_values() -> None:
    log_pred = _t([[[0.0, 1.0], [2.0, 3.0]]])
    zeros = torch.zeros_like(log_pred)
    valid = torch.ones_like(log_pred, dtype=torch.bool)
    # r = 0, 1, 2, 3: mean(r^2) = 3.5, mean(r) = 1.5.
    assert float(scale_invariant_log_loss(log_pred, zeros, valid, lam=0.5)) == pytest.approx(
        3.5 - 0.5 * 2.25
    )
    assert float(scale_invariant_log_loss(log_pred, zeros, valid, lam=0.0)) == pytest.approx(3.5)
    # Pixel with r = 3 invalid: r = 0, 1, 2 -> 5/3 - 1 = 2/3 for lam = 1.
    valid[0, 1, 1] = False
    assert float(scale_invariant_log_loss(log_pred, zeros, valid, lam=1.0)) == pytest.approx(2 / 3)
    # Batch mean over images; an image without valid pixels does not count.
    lp = torch.cat([log_pred, log_pred])
    v2 = torch.cat([valid, torch.zeros_like(valid)])
    assert float(scale_invariant_log_loss(lp, torch.zeros_like(lp), v2, 1.0)) == pytest.approx(
        2 / 3
    )


def test_scale_invariant_loss_ignores_global_scale_for_lambda_one() -> None:
    g = torch.Generator().manual_seed(0)
    lp = torch.randn(2, 5, 6, generator=g, dtype=torch.float64)
    lg = torch.randn(2, 5, 6, generator=g, dtype=torch.float64)
    valid = torch.rand(2, 5, 6, generator=g) > 0.3
    a = scale_invariant_log_loss(lp, lg, valid, 1.0)
    b = scale_invariant_log_loss(lp + math.log(7.0), lg, valid, 1.0)
    assert float(a) == pytest.approx(float(b))
    assert float(scale_invariant_log_loss(lg, lg, valid, 0.85)) == 0.0


def test_gradient_matching_hand_values() -> None:
    log_pred = _t([[[0.0, 1.0, 3.0], [0.0, 0.0, 0.0]]])
    zeros = torch.zeros_like(log_pred)
    valid = torch.ones_like(log_pred, dtype=torch.bool)
    # Scale 1: horizontal |diffs| 1, 2, 0, 0; vertical 0, 1, 3 -> 7 over 7 pairs.
    assert float(gradient_matching_loss(log_pred, zeros, valid, 1)) == pytest.approx(1.0)
    # Scale 2 keeps row 0, columns 0 and 2: one pair, |3 - 0| = 3.
    assert float(gradient_matching_loss(log_pred, zeros, valid, 2)) == pytest.approx(4.0)
    # Invalid (0, 2): horizontal pairs 1 + 0 + 0 = 1 (3 pairs), vertical 0 + 1 (2 pairs).
    valid[0, 0, 2] = False
    assert float(gradient_matching_loss(log_pred, zeros, valid, 1)) == pytest.approx(2 / 5)
    # A global scale (constant in log) changes nothing.
    assert float(gradient_matching_loss(log_pred + 2.0, zeros, valid, 1)) == pytest.approx(2 / 5)


def test_loss_input_errors() -> None:
    a = torch.zeros(1, 4, 4)
    valid = torch.ones(1, 4, 4, dtype=torch.bool)
    with pytest.raises(InvalidInputError, match="matching"):
        scale_invariant_log_loss(a, torch.zeros(1, 4, 5), valid)
    with pytest.raises(InvalidInputError, match="bool"):
        gradient_matching_loss(a, a, valid.float())
    with pytest.raises(InvalidInputError, match="lam"):
        scale_invariant_log_loss(a, a, valid, lam=1.5)
    with pytest.raises(InvalidInputError, match="num_scales"):
        gradient_matching_loss(a, a, valid, num_scales=0)


# --------------------------------------------------------------------------- metrics


def test_metrics_hand_values_and_median_scaling() -> None:
    gt = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)
    pred = np.array([[1.0, 2.0], [3.0, 8.0]], np.float32)  # medians 2.5 and 2.5 -> s = 1
    abs_rel, rmse, delta = frame_metrics(pred, gt)
    assert abs_rel == pytest.approx(0.25)
    assert rmse == pytest.approx(2.0)
    assert delta == pytest.approx(0.75)
    # Any global scale of the prediction is removed by median scaling.
    assert frame_metrics(0.01 * pred, gt) == pytest.approx((0.25, 2.0, 0.75))
    # NaN and the mask exclude pixels; nothing valid -> None.
    pred_nan = pred.copy()
    pred_nan[1, 1] = np.nan
    assert frame_metrics(pred_nan, gt)[0] == pytest.approx(0.0)
    assert frame_metrics(pred, gt, np.zeros((2, 2), bool)) is None
    with pytest.raises(InvalidInputError, match="shape"):
        frame_metrics(pred, gt[:1])


# --------------------------------------------------------------------------- network


def test_config_validation_and_round_trip() -> None:
    assert DepthNetConfig.from_dict(TINY.to_dict()) == TINY
    with pytest.raises(InvalidInputError, match="blocks"):
        DepthNetConfig(widths=(8, 16), blocks=(1,))
    with pytest.raises(InvalidInputError, match="stages"):
        DepthNetConfig(widths=(8,), blocks=(1,))
    with pytest.raises(InvalidInputError, match="unknown"):
        DepthNetConfig.from_dict({"widths": [8, 16], "depth": 3})
    with pytest.raises(InvalidInputError, match="epochs"):
        TrainConfig(num_threads=1, epochs=0)
    with pytest.raises(InvalidInputError, match="hflip"):
        AugmentConfig(hflip=2.0)


@pytest.mark.parametrize(
    ("hw", "scale"), [((48, 64), 0.5), ((37, 53), 0.5), ((37, 53), 1.0), ((256, 320), 0.5)]
)
def test_predictor_shape_positive_finite(hw: tuple[int, int], scale: float) -> None:
    torch.manual_seed(0)
    pred = DepthPredictor(DepthNet(DepthNetConfig(input_scale=scale))).eval()
    rgb = torch.randint(0, 256, (2, *hw, 3), dtype=torch.uint8)
    with torch.inference_mode():
        out = pred(rgb)
    assert out.shape == (2, *hw)
    assert out.dtype == torch.float32
    assert torch.isfinite(out).all() and (out > 0).all()


# --------------------------------------------------------------------------- checkpoints


def test_checkpoint_round_trip_weights_only(tmp_path: Path) -> None:
    torch.manual_seed(1)
    net = DepthNet(TINY).eval()
    ck = save_checkpoint(tmp_path / "a.pt", net, {"seeds": [1000, 1001]})
    raw = torch.load(ck, weights_only=True)  # plain tensors + JSON-able dicts, no pickle
    assert raw["config"] == TINY.to_dict()
    loaded, info = load_checkpoint(ck)
    assert info == {"seeds": [1000, 1001]}
    assert loaded.config == TINY
    for k, v in net.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k
    side = json.loads((tmp_path / "a.json").read_text())
    assert side["config"] == TINY.to_dict() and side["info"]["seeds"] == [1000, 1001]
    rgb = torch.randint(0, 256, (1, H, W, 3), dtype=torch.uint8)
    with torch.inference_mode():
        assert torch.equal(DepthPredictor(net)(rgb), DepthPredictor(loaded)(rgb))


def test_checkpoint_errors(tmp_path: Path) -> None:
    ck = save_checkpoint(tmp_path / "a.pt", DepthNet(TINY))
    other = DepthNetConfig(widths=(8, 12, 24), blocks=(1, 1, 1))
    with pytest.raises(CheckpointError, match=r"do not match.*expected shape"):
        load_checkpoint(ck, config=other)
    deeper = DepthNetConfig(widths=(8, 12, 16), blocks=(1, 1, 2))
    with pytest.raises(CheckpointError, match="missing tensor"):
        load_checkpoint(ck, config=deeper)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nope.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="weights_only"):
        load_checkpoint(junk)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(CheckpointError, match="format"):
        load_checkpoint(foreign)
    payload = torch.load(ck, weights_only=True)
    payload["version"] = 99
    torch.save(payload, tmp_path / "v99.pt")
    with pytest.raises(FormatVersionError, match="version 99"):
        load_checkpoint(tmp_path / "v99.pt")
    with pytest.raises(InvalidInputError, match=r"\.pt"):
        save_checkpoint(tmp_path / "a.pth", DepthNet(TINY))
    with pytest.raises(InvalidInputError, match="JSON"):
        save_checkpoint(tmp_path / "b.pt", DepthNet(TINY), {"x": object()})
    assert not (tmp_path / "b.pt").exists()


# --------------------------------------------------------------------------- data


def test_dataset_index_split_and_seed_guard(dataset: Path, tmp_path: Path) -> None:
    refs = find_sequences([dataset])
    assert [r.seed for r in refs] == [1000, 1001, 1002]
    # A sequence folder given directly takes its seed from its meta.
    assert find_sequences([dataset / "seq_1001"])[0].seed == 1001
    train_refs, val_refs = split_by_group(refs, 0.34, seed=5)
    assert len(val_refs) == 1 and len(train_refs) == 2
    assert {r.seed for r in train_refs}.isdisjoint({r.seed for r in val_refs})
    assert split_by_group(refs, 0.34, seed=5) == (train_refs, val_refs)
    check_training_seeds(refs)
    with pytest.raises(InvalidInputError, match="evaluation seeds"):
        check_training_seeds([SequenceRef(dataset / "seq_1000", 42)])
    with pytest.raises(InvalidInputError, match="neither a sequence"):
        find_sequences([tmp_path])
    (tmp_path / "bad.json").write_text(json.dumps({"sequences": [{"seed": 3}]}))
    with pytest.raises(InvalidInputError, match="needs a path"):
        find_sequences([tmp_path / "bad.json"])


def test_load_frames_masks_and_augment(dataset: Path) -> None:
    refs = find_sequences([dataset / "seq_1000"])
    fs = load_frames(refs)
    seq = Sequence(dataset / "seq_1000")
    assert fs.rgb.shape == (6, H, W, 3) and fs.rgb.dtype == torch.uint8
    expected_valid = np.isfinite(seq.depth_mm(0)) & seq.mask(0)
    assert np.array_equal(fs.valid[0].numpy(), expected_valid)
    half = load_frames(refs, size=(32, 24), frame_step=2)
    assert half.rgb.shape == (3, 24, 32, 3)
    with pytest.raises(EmptyResultError, match="no usable frame"):
        load_frames(refs, min_valid_fraction=1.1)
    # Flips move RGB, depth and validity together; the same seed gives the same batch.
    flip = AugmentConfig(
        hflip=1.0, vflip=0.0, brightness=0.0, contrast=0.0, channel_gain=0.0, noise_std=0.0
    )
    rgb, depth, valid = augment(
        fs.rgb[:2], fs.depth_mm[:2], fs.valid[:2], flip, torch.Generator().manual_seed(0)
    )
    assert torch.equal(rgb, fs.rgb[:2].flip(2).float())
    assert torch.equal(depth, fs.depth_mm[:2].flip(2))
    assert torch.equal(valid, fs.valid[:2].flip(2))
    a = augment(fs.rgb, fs.depth_mm, fs.valid, AugmentConfig(), torch.Generator().manual_seed(4))
    b = augment(fs.rgb, fs.depth_mm, fs.valid, AugmentConfig(), torch.Generator().manual_seed(4))
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not torch.equal(a[0], fs.rgb.float())


def test_downsample_targets_hand_values() -> None:
    depth = torch.tensor([[[1.0, 3.0, 5.0, 5.0], [1.0, 3.0, 7.0, 9.0]]])
    valid = torch.tensor([[[True, True, True, True], [True, True, False, True]]])
    d, v = downsample_targets(depth, valid, (1, 2))
    assert v.tolist() == [[[True, False]]]  # a block with an invalid pixel is invalid
    assert d[0, 0, 0].item() == pytest.approx(2.0)
    same = downsample_targets(depth, valid, (2, 4))
    assert same[0] is depth and same[1] is valid


# --------------------------------------------------------------------------- training


def test_training_reduces_loss_and_validates(dataset: Path) -> None:
    refs = find_sequences([dataset])
    train_refs, val_refs = split_by_group(refs, 0.34, seed=0)
    frames = load_frames(train_refs)
    val = load_frames(val_refs)
    cfg = TrainConfig(num_threads=1, epochs=12, batch_size=4, lr=3e-3, seed=0, augment=None)
    result = train(frames, cfg, TINY, val_frames=val)
    losses = [row["loss"] for row in result.history]
    assert losses[-1] < 0.6 * losses[0], losses
    assert result.val_metrics is not None and result.val_metrics.num_frames == len(val)
    best = min(row["val_abs_rel"] for row in result.history)
    assert result.val_metrics.abs_rel == pytest.approx(best, rel=1e-5)
    assert not result.net.training


def test_training_is_deterministic(dataset: Path) -> None:
    frames = load_frames(find_sequences([dataset / "seq_1000"]))
    cfg = TrainConfig(num_threads=1, epochs=2, batch_size=2, seed=7)  # with augmentation
    a = train(frames, cfg, TINY).net.state_dict()
    b = train(frames, cfg, TINY).net.state_dict()
    c = train(
        frames, TrainConfig(num_threads=1, epochs=2, batch_size=2, seed=8), TINY
    ).net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_finetune_freezes_batchnorm_and_keeps_parent(dataset: Path, tiny_checkpoint: Path) -> None:
    parent, _ = load_checkpoint(tiny_checkpoint)
    before = {k: v.clone() for k, v in parent.state_dict().items()}
    frames = load_frames(find_sequences([dataset / "seq_1002"]))
    result = train(
        frames, TrainConfig.finetune_defaults(epochs=1, batch_size=3, num_threads=1), init=parent
    )
    after = result.net.state_dict()
    assert all(torch.equal(before[k], parent.state_dict()[k]) for k in before)  # copy trained
    stats = [k for k in after if k.endswith("running_mean")]
    assert stats and all(torch.equal(after[k], before[k]) for k in stats)
    assert not torch.equal(after["head.weight"], before["head.weight"])


def test_resolve_device() -> None:
    assert resolve_device("cpu").type == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(InvalidInputError, match="CUDA is not available"):
            resolve_device("cuda")
    with pytest.raises(InvalidInputError, match="device"):
        resolve_device("tpu-ish")


# --------------------------------------------------------------------------- inference


def test_depth_source_and_export_round_trip(
    dataset: Path, tiny_checkpoint: Path, tmp_path: Path
) -> None:
    seq = Sequence(dataset / "seq_1001")
    frame = seq.frame(0)
    src = load_depth_source(tiny_checkpoint)
    assert src.is_metric is False
    depth = src(frame)
    assert depth.shape == seq.camera.shape and depth.dtype == np.float32
    inside = frame.mask
    assert np.isfinite(depth[inside]).all() and (depth[inside] > 0).all()
    assert np.isnan(depth[~inside]).all()

    net, _ = load_checkpoint(tiny_checkpoint)
    ts = export_model(DepthPredictor(net), tmp_path / "model.pt")
    scripted = torch.jit.load(str(ts))
    rgb = torch.from_numpy(np.stack([seq.rgb(0), seq.rgb(1)]))
    with torch.inference_mode():
        eager_out = DepthPredictor(net).eval()(rgb)
        ts_out = scripted(rgb)
    torch.testing.assert_close(ts_out, eager_out, rtol=1e-5, atol=1e-6)
    ts_src = load_depth_source(ts)
    np.testing.assert_allclose(ts_src(frame), depth, rtol=1e-5, equal_nan=True)
    # Odd sizes work through the exported model too.
    odd = torch.randint(0, 256, (1, 30, 41, 3), dtype=torch.uint8)
    assert scripted(odd).shape == (1, 30, 41)

    with pytest.raises(InvalidInputError, match="suffix"):
        export_model(DepthPredictor(net), tmp_path / "model.bin")
    with pytest.raises(CheckpointError, match="does not exist"):
        load_depth_source(tmp_path / "missing.pt")
    with pytest.raises(InvalidInputError, match="RGB"):
        src(Frame(index=0, T_world_from_cam=np.eye(4)))
    eager_src = load_depth_source(tiny_checkpoint, script=False)
    np.testing.assert_allclose(eager_src(frame), depth, rtol=1e-5, equal_nan=True)
    metrics = evaluate_source(src, [seq])
    assert metrics.num_frames == len(seq) and 0 <= metrics.abs_rel < 10


def test_onnx_export_needs_onnx(tiny_checkpoint: Path, tmp_path: Path) -> None:
    net, _ = load_checkpoint(tiny_checkpoint)
    try:
        import onnx  # noqa: F401
    except ImportError:
        with pytest.raises(InvalidInputError, match="onnx"):
            export_model(DepthPredictor(net), tmp_path / "m.onnx")
        assert not (tmp_path / "m.onnx").exists()
    else:
        out = export_model(DepthPredictor(net), tmp_path / "m.onnx", example_hw=(H, W))
        assert out.stat().st_size > 1000


def test_predict_sequence_refuses_in_place(dataset: Path, tiny_checkpoint: Path) -> None:
    seq = Sequence(dataset / "seq_1000")
    with pytest.raises(InvalidInputError, match="new folder"):
        predict_sequence(load_depth_source(tiny_checkpoint), seq, seq.path)


# --------------------------------------------------------------------------- CLI


def test_cli_predict_writes_valid_sequence(
    dataset: Path, tiny_checkpoint: Path, tmp_path: Path
) -> None:
    out = tmp_path / "pred"
    rc = cli.main(
        [
            "depth",
            "predict",
            "--checkpoint",
            str(tiny_checkpoint),
            "--sequence",
            str(dataset / "seq_1000"),
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    src, new = Sequence(dataset / "seq_1000"), Sequence(out)
    assert len(new) == len(src) and new.has_depth and new.has_rgb and new.has_mask
    np.testing.assert_array_equal(new.poses, src.poses)
    np.testing.assert_array_equal(new.true_poses, src.true_poses)
    assert new.camera.to_dict() == src.camera.to_dict()
    assert new.meta["phantom_seed"] == 1000
    assert new.meta["depth_prediction"]["model"] == str(tiny_checkpoint)
    assert len(new.meta["depth_prediction"]["model_sha256"]) == 64
    for i in range(len(src)):
        np.testing.assert_array_equal(new.rgb(i), src.rgb(i))
        np.testing.assert_array_equal(new.mask(i), src.mask(i))
        d = new.depth_mm(i)
        assert np.isfinite(d[new.mask(i)]).all() and np.isnan(d[~new.mask(i)]).all()
    # A failing run (missing checkpoint) leaves the earlier output intact.
    before = (out / "sequence.json").read_text()
    rc = cli.main(
        [
            "depth",
            "predict",
            "--checkpoint",
            str(tmp_path / "none.pt"),
            "--sequence",
            str(dataset / "seq_1000"),
            "--out",
            str(out),
        ]
    )
    assert rc == 1 and (out / "sequence.json").read_text() == before


def test_cli_train_from_a_monocular_checkpoint(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--init starts training from a checkpoint's weights and keeps its architecture."""
    parent = tmp_path / "parent.pt"
    torch.manual_seed(3)
    save_checkpoint(parent, DepthNet(DepthNetConfig(widths=(8, 12, 16), blocks=(1, 1, 1))), {})
    out = tmp_path / "child.pt"
    argv = ["depth", "train", "--data", str(dataset), "--out", str(out), "--epochs", "1"]
    opts = ["--batch-size", "4", "--threads", "1", "--val-fraction", "0", "--lr", "1e-12"]
    assert cli.main([*argv, *opts, "--init", str(parent)]) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["config"]["widths"] == [8, 12, 16]  # the parent's, not the default's
    assert (
        sidecar["info"]["init"] == str(parent) and f"--init {parent}" in sidecar["info"]["command"]
    )
    # At a vanishing learning rate the weights are the parent's; a fresh network's are not.
    child, _ = load_checkpoint(out)
    (p_net, _), fresh = load_checkpoint(parent), DepthNet(DepthNetConfig((8, 12, 16), (1, 1, 1)))
    w_child, w_parent = child.state_dict(), p_net.state_dict()
    convs = [k for k in w_parent if k.endswith("weight") and w_parent[k].dim() == 4]
    assert convs and all(torch.allclose(w_child[k], w_parent[k], atol=1e-6) for k in convs)
    assert not all(torch.allclose(fresh.state_dict()[k], w_parent[k]) for k in convs)
    # --init keeps its own network; a change-aware checkpoint is not a monocular parent.
    capsys.readouterr()
    assert cli.main([*argv, *opts, "--init", str(parent), "--widths", "8,16"]) == 1
    assert "--widths" in capsys.readouterr().err
    assert cli.main([*argv, *opts, "--init", str(DEFAULT_CHANGE_CHECKPOINT)]) == 1
    err = capsys.readouterr().err
    assert "change-aware" in err and "monocular" in err


def test_cli_train_finetune_export_evaluate(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ck = tmp_path / "ck.pt"
    rc = cli.main(
        [
            "depth",
            "train",
            "--data",
            str(dataset),
            "--out",
            str(ck),
            "--epochs",
            "1",
            "--batch-size",
            "4",
            "--widths",
            "8,12,16",
            "--blocks",
            "1,1,1",
            "--threads",
            "1",
            "--val-fraction",
            "0.34",
            "--frame-step",
            "2",
        ]
    )
    assert rc == 0
    info = json.loads(ck.with_suffix(".json").read_text())["info"]
    assert info["command"].startswith("chisel depth train --data ")
    assert "--widths 8,12,16" in info["command"]
    assert sorted(info["train_phantom_seeds"] + info["val_phantom_seeds"]) == [1000, 1001, 1002]
    assert len(info["val_phantom_seeds"]) == 1 and info["val_metrics"]["num_frames"] == 3

    ft = tmp_path / "ft.pt"
    rc = cli.main(
        [
            "depth",
            "finetune",
            "--checkpoint",
            str(ck),
            "--sequence",
            str(dataset / "seq_1000"),
            "--out",
            str(ft),
            "--epochs",
            "1",
            "--batch-size",
            "3",
            "--threads",
            "1",
        ]
    )
    assert rc == 0
    ft_info = json.loads(ft.with_suffix(".json").read_text())["info"]
    assert ft_info["kind"] == "finetune" and ft_info["parent_checkpoint"] == str(ck)

    ts = tmp_path / "model.pt"
    assert cli.main(["depth", "export", "--checkpoint", str(ft), "--out", str(ts)]) == 0
    capsys.readouterr()
    assert (
        cli.main(
            ["depth", "evaluate", "--checkpoint", str(ts), "--data", str(dataset / "seq_1002")]
        )
        == 0
    )
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["num_frames"] == 6 and doc["abs_rel"] > 0

    # Training on evaluation phantoms (seeds 0-99) is refused with a clear message.
    bad = tmp_path / "bad_dataset"
    bad.mkdir()
    (bad / "dataset.json").write_text(
        json.dumps({"sequences": [{"path": str(dataset / "seq_1000"), "phantom_seed": 7}]})
    )
    argv = ["depth", "train", "--data", str(bad), "--out", str(tmp_path / "x.pt")]
    # The index names a folder outside its own: refused unless allowed (a manifest).
    rc = cli.main(argv)
    assert rc == 1 and "--allow-outside-manifest" in capsys.readouterr().err
    rc = cli.main([*argv, "--allow-outside-manifest"])
    assert rc == 1 and "evaluation seeds" in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()


# --------------------------------------------------------------------------- shipped model


@pytest.mark.parametrize(
    "shipped", [DEFAULT_CHECKPOINT, EFFECTS_CHECKPOINT], ids=["default", "effects"]
)
def test_shipped_checkpoints_load_and_predict(dataset: Path, shipped: Path) -> None:
    net, info = load_checkpoint(shipped)
    assert info["kind"] == "train"
    assert min(info["train_phantom_seeds"]) >= 1000
    if shipped == EFFECTS_CHECKPOINT:  # its record names the data that reproduces it
        assert "config/sim_train_effects.yaml" in info["command"]
    if shipped == DEFAULT_CHECKPOINT:  # trained on from a parent that ships beside it
        parent = shipped.with_name(Path(info["init"]).name)
        assert parent != shipped and "--procedure uncinectomy" in info["command"]
        assert load_checkpoint(parent)[0].config == net.config
    src = load_depth_source(shipped)
    frame = Sequence(dataset / "seq_1000").frame(0)
    depth = src(frame)
    assert np.isfinite(depth[frame.mask]).all() and (depth[frame.mask] > 0).all()
