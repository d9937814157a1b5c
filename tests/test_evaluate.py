"""Evaluation: analytic cases for every metric, the file-level wrapper, tables and the CLI."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from chisel.cli import main as cli_main
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.geometry import Camera, look_at
from chisel.eval.masks import (
    mask_precision_recall,
    true_change_masks,
    true_change_masks_from_depths,
)
from chisel.eval.metrics import (
    RoiBox,
    correspondence_error,
    render_depths,
)
from chisel.eval.step import (
    ChangeMaskInput,
    evaluate_methods,
    evaluate_step,
    load_change_masks,
    load_mesh,
)
from chisel.eval.surface import (
    SurfaceMetricConfig,
    distance_metrics,
    sample_surface_in_box,
    surface_metrics,
)
from chisel.eval.tables import (
    METRIC_KEYS,
    METRICS_FORMAT,
    aggregate_seeds,
    assemble_table,
    metrics_to_csv,
    metrics_to_markdown,
    read_metrics,
    read_sweep_csv,
    tabulate_sweep,
    validate_metrics,
    write_seed_table,
    write_sweep_csv,
    write_table,
)
from chisel.io.sequence import Frame, write_sequence

CAM = Camera.from_fov(48, 36, 60)
CFG = SurfaceMetricConfig(n_samples=4000, seed=3)
IDENTITY = np.eye(4)[None]  # camera at the origin looking down +z (OpenCV axes)


def plane(
    z_mm: float, half_mm: float = 60.0, x_range: tuple[float, float] | None = None
) -> trimesh.Trimesh:
    """A square plane z = z_mm facing the camera, finely triangulated (x, y in +-half_mm)."""
    x0, x1 = x_range if x_range else (-half_mm, half_mm)
    xs = np.linspace(x0, x1, 21)
    ys = np.linspace(-half_mm, half_mm, 21)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z_mm)], axis=1)
    idx = np.arange(X.size).reshape(X.shape)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return trimesh.Trimesh(v, f, process=False)


def ray_norms() -> np.ndarray:
    """(H, W) length of each pixel's z = 1 ray: the same-pixel distance per mm of z-shift."""
    return np.linalg.norm(CAM.rays_cam(), axis=-1)


def gt_pixels_in_box(z_mm: float, box: RoiBox) -> np.ndarray:
    """(H, W) bool: pixels whose point on the plane z = z_mm (camera at the origin) is in the box."""
    pts = CAM.rays_cam() * z_mm
    return box.contains(pts)


BOX = RoiBox([-4.0, -3.0, 15.0], [4.0, 3.0, 25.0])


# ------------------------------------------------------------------------- ROI box


def test_roi_box_contains_and_parse() -> None:
    box = RoiBox.parse("0,0,0,1,2,3")
    pts = np.array([[0.5, 1, 1], [1, 2, 3], [1.01, 1, 1], [np.nan, 1, 1]])
    assert box.contains(pts).tolist() == [True, True, False, False]
    assert box.to_list() == [0, 0, 0, 1, 2, 3]


@pytest.mark.parametrize(
    "text", ["0,0,0,1,2", "a,b,c,d,e,f", "0,0,0,0,1,1", "0,0,0,1,nan,1", "1,1,1,0,0,0"]
)
def test_roi_box_rejects_bad_text(text: str) -> None:
    with pytest.raises(InvalidInputError, match="--roi"):
        RoiBox.parse(text)


def test_roi_box_rejects_bad_corner_shape() -> None:
    with pytest.raises(InvalidInputError, match="3 \\+ 3"):
        RoiBox([0, 0], [1, 1])


# ------------------------------------------------------------------------- the paper's metric


def test_identical_meshes_give_zero() -> None:
    gt = plane(20.0)
    r = evaluate_methods(gt, {"no_update": gt.copy()}, CAM, IDENTITY, BOX, 1, CFG)
    cell = r["methods"]["no_update"]
    assert cell["mean_mm"] == 0.0 and cell["std_mm"] == 0.0
    assert cell["n_points"] == int(gt_pixels_in_box(20.0, BOX).sum()) > 100
    assert cell["missing_fraction"] == 0.0
    assert cell["accuracy_mm"] < 1e-4 and cell["completeness_mm"] < 1e-4
    assert cell["hd95_mm"] < 1e-4 and cell["fscore_1mm"] == 1.0


def test_plane_shifted_along_normal() -> None:
    # Shifted 0.7 mm along its normal (= the optical axis): each pixel's two points lie on
    # one ray, 0.7 * |ray| apart; the nearest-surface distance is exactly 0.7 mm.
    gt, shifted = plane(20.0), plane(20.7)
    inside = gt_pixels_in_box(20.0, BOX)
    expected = 0.7 * ray_norms()[inside]
    depths = render_depths(gt, CAM, IDENTITY)
    err = correspondence_error(depths, render_depths(shifted, CAM, IDENTITY), CAM, IDENTITY, BOX)
    assert err.n_points == err.n_gt_in_box == inside.sum()
    assert err.mean_mm == pytest.approx(expected.mean(), abs=2e-5)
    assert err.std_mm == pytest.approx(expected.std(), abs=2e-5)
    s = surface_metrics(shifted, gt, BOX, CFG)
    for v in (
        s.accuracy_mm,
        s.completeness_mm,
        s.accuracy_hd95_mm,
        s.completeness_hd95_mm,
        s.hd95_mm,
        s.chamfer_mm,
    ):
        assert v == pytest.approx(0.7, abs=1e-4)
    assert s.precision == s.recall == s.fscore == 1.0
    far = surface_metrics(plane(21.5), gt, BOX, CFG)  # 1.5 mm > the 1 mm threshold
    assert far.fscore == 0.0 and far.chamfer_mm == pytest.approx(1.5, abs=1e-4)


def test_sphere_radius_plus_half_mm() -> None:
    # Camera at the centre: every ray is radial, so same-pixel points are 0.5 mm apart.
    gt = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    big = gt.copy()
    big.apply_scale(1.05)
    T = look_at([0, 0, 0], [0, 0, 1], up=[0, -1, 0])[None]
    box = RoiBox([-5, -5, 5], [5, 5, 11])
    r = evaluate_methods(gt, {"updated": big}, CAM, T, box, 2, CFG)["methods"]["updated"]
    assert r["mean_mm"] == pytest.approx(0.5, abs=2e-3)
    assert r["std_mm"] < 2e-3
    for k in ("accuracy_mm", "completeness_mm", "hd95_mm", "chamfer_mm"):
        assert r[k] == pytest.approx(0.5, abs=5e-3), k
    assert r["fscore_1mm"] == 1.0


def test_points_outside_the_box_are_excluded() -> None:
    # The method agrees with GT for x < 0 and sits 5 mm deeper for x > 0.
    gt = plane(20.0)
    left, right = plane(20.0, x_range=(-60, 0)), plane(25.0, x_range=(0, 60))
    method = trimesh.util.concatenate([left, right])
    left_box = RoiBox([-4.0, -3.0, 15.0], [-0.5, 3.0, 30.0])
    r = evaluate_methods(gt, {"m": method}, CAM, IDENTITY, left_box, 1, CFG)["methods"]["m"]
    assert r["mean_mm"] == 0.0 and r["n_points"] == gt_pixels_in_box(20.0, left_box).sum()
    assert r["accuracy_mm"] < 1e-4 and r["completeness_mm"] < 1e-4
    whole = evaluate_methods(gt, {"m": method}, CAM, IDENTITY, BOX, 1, CFG)["methods"]["m"]
    inside = gt_pixels_in_box(20.0, BOX)
    right_px = inside & (CAM.rays_cam()[..., 0] > 0)
    expected = np.where(right_px, 5.0 * ray_norms(), 0.0)[inside]
    assert whole["mean_mm"] == pytest.approx(expected.mean(), abs=1e-4)


def test_missing_surface_is_counted_not_scored() -> None:
    # The method has no surface for x > 0: those pixels are missing, not errors.
    gt = plane(20.0)
    method = plane(20.0, x_range=(-60, 0))
    inside = gt_pixels_in_box(20.0, BOX)
    right_px = inside & (CAM.rays_cam()[..., 0] > 0)
    err = correspondence_error(
        render_depths(gt, CAM, IDENTITY), render_depths(method, CAM, IDENTITY), CAM, IDENTITY, BOX
    )
    assert err.n_gt_in_box == inside.sum()
    assert err.n_points == inside.sum() - right_px.sum()
    assert err.missing_fraction == pytest.approx(right_px.sum() / inside.sum())
    assert err.mean_mm == 0.0


def test_pixel_mask_limits_counted_pixels() -> None:
    gt = plane(20.0)
    d = render_depths(gt, CAM, IDENTITY)
    mask = np.zeros(CAM.shape, bool)
    mask[:, : CAM.width // 2] = True
    err = correspondence_error(d, d, CAM, IDENTITY, BOX, pixel_mask=mask)
    assert err.n_gt_in_box == (gt_pixels_in_box(20.0, BOX) & mask).sum()


def test_correspondence_error_raises_on_empty_or_bad_input() -> None:
    d = render_depths(plane(20.0), CAM, IDENTITY)
    far_box = RoiBox([100, 100, 100], [101, 101, 101])
    with pytest.raises(EmptyResultError, match="do not view the box"):
        correspondence_error(d, d, CAM, IDENTITY, far_box)
    with pytest.raises(EmptyResultError, match="no surface"):
        correspondence_error(d, np.full_like(d, np.nan), CAM, IDENTITY, BOX)
    with pytest.raises(InvalidInputError, match="expected depth of shape"):
        correspondence_error(d, d[:, :10], CAM, IDENTITY, BOX)
    with pytest.raises(InvalidInputError, match="pose"):
        correspondence_error(d, d, CAM, np.zeros((1, 4, 4)), BOX)


# ------------------------------------------------------------------------- surface metrics


def test_distance_metrics_hand_checked() -> None:
    a = np.array([0.5, 0.9, 1.0, 2.0])  # pred -> GT: 2 of 4 below 1 mm (1.0 is not below)
    c = np.array([0.1, 0.2, 3.0])  # GT -> pred: 2 of 3 below 1 mm
    m = distance_metrics(a, c, 1.0)
    assert m.precision == 0.5 and m.recall == pytest.approx(2 / 3)
    assert m.fscore == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    assert m.accuracy_mm == pytest.approx(1.1) and m.completeness_mm == pytest.approx(3.3 / 3)
    assert m.chamfer_mm == pytest.approx((1.1 + 1.1) / 2)
    # Linear-interpolated 95th percentiles: 1.0 + 0.85 * 1.0, and 0.2 + 0.9 * 2.8.
    assert m.accuracy_hd95_mm == pytest.approx(1.85)
    assert m.completeness_hd95_mm == pytest.approx(2.72)
    assert m.hd95_mm == pytest.approx(2.72)
    zero = distance_metrics(np.array([2.0]), np.array([3.0]), 1.0)
    assert zero.fscore == 0.0


@pytest.mark.parametrize(
    "a, c, match",
    [
        (np.array([]), np.array([1.0]), "no distances"),
        (np.array([np.nan]), np.array([1.0]), "finite"),
        (np.array([1.0]), np.array([-1.0]), "non-negative"),
    ],
)
def test_distance_metrics_rejects_bad_input(a, c, match) -> None:  # noqa: ANN001
    with pytest.raises(InvalidInputError, match=match):
        distance_metrics(a, c, 1.0)


def test_distance_metrics_rejects_bad_threshold() -> None:
    with pytest.raises(InvalidInputError, match="threshold"):
        distance_metrics(np.ones(3), np.ones(3), 0.0)


def test_samples_are_uniform_inside_the_box_and_seeded() -> None:
    box = RoiBox([-4.0, -3.0, 15.0], [4.0, 3.0, 25.0])
    p = sample_surface_in_box(plane(20.0), box, 20000, seed=1)
    assert p.shape == (20000, 3) and box.contains(p).all()
    assert np.allclose(p[:, 2], 20.0)
    # Uniform by area: the left half of the box's 8 x 6 mm patch holds half of the samples.
    assert np.mean(p[:, 0] < 0) == pytest.approx(0.5, abs=0.015)
    assert np.array_equal(p, sample_surface_in_box(plane(20.0), box, 20000, seed=1))
    with pytest.raises(EmptyResultError, match="no surface inside"):
        sample_surface_in_box(plane(40.0), box, 100, seed=1)


def test_surface_config_rejects_few_samples() -> None:
    with pytest.raises(InvalidInputError, match="n_samples"):
        SurfaceMetricConfig(n_samples=10)


# ------------------------------------------------------------------------- change masks


def test_mask_precision_recall_hand_checked() -> None:
    pred = np.array([[[1, 1, 0, 0], [1, 0, 0, 0]]], dtype=bool)
    true = np.array([[[1, 0, 1, 0], [1, 0, 1, 1]]], dtype=bool)
    s = mask_precision_recall(pred, true)
    assert (s.n_true_positive, s.n_false_positive, s.n_false_negative) == (2, 1, 3)
    assert s.precision == pytest.approx(2 / 3) and s.recall == pytest.approx(2 / 5)
    valid = np.array([[1, 1, 1, 1], [0, 0, 0, 0]], dtype=bool)  # drop the second row
    v = mask_precision_recall(pred, true, valid)
    assert v.precision == pytest.approx(1 / 2) and v.recall == pytest.approx(1 / 2)
    none = mask_precision_recall(np.zeros((1, 2, 2), bool), np.zeros((1, 2, 2), bool))
    assert np.isnan(none.precision) and np.isnan(none.recall)
    assert mask_precision_recall(pred.astype(np.uint8) * 255, true).precision == s.precision


def test_mask_precision_recall_rejects_bad_input() -> None:
    with pytest.raises(InvalidInputError, match="differs"):
        mask_precision_recall(np.zeros((1, 2, 2), bool), np.zeros((1, 2, 3), bool))
    with pytest.raises(InvalidInputError, match="bool masks"):
        mask_precision_recall(np.full((1, 2, 2), 0.5), np.zeros((1, 2, 2), bool))
    with pytest.raises(InvalidInputError, match="\\(N, H, W\\)"):
        mask_precision_recall(np.zeros(4, bool), np.zeros(4, bool))


def test_true_change_from_depths_hand_checked() -> None:
    before = np.array([[[10.0, 10.0, 10.0, np.nan]]], np.float32)
    after = np.array([[[10.5, 11.5, np.nan, 12.0]]], np.float32)
    # +0.5 no; +1.5 yes; surface gone yes; nothing seen before: no.
    assert true_change_masks_from_depths(before, after).tolist() == [[[False, True, True, False]]]
    with pytest.raises(InvalidInputError, match="matching"):
        true_change_masks_from_depths(before, after[:, :, :2])
    with pytest.raises(InvalidInputError, match="threshold"):
        true_change_masks_from_depths(before, after, threshold_mm=-1)


def test_true_change_masks_from_meshes() -> None:
    # Tissue removed for x < 0: the surface drops from 20 to 22 mm there.
    before = plane(20.0)
    after = trimesh.util.concatenate([plane(22.0, x_range=(-60, 0)), plane(20.0, x_range=(0, 60))])
    masks = true_change_masks(before, after, CAM, IDENTITY)
    assert masks.shape == (1, *CAM.shape)
    assert np.array_equal(masks[0], CAM.rays_cam()[..., 0] < 0)


# ------------------------------------------------------------------------- evaluate_methods


def test_evaluate_methods_scores_masks_and_rejects_bad_input() -> None:
    gt = plane(20.0)
    true = np.zeros((1, *CAM.shape), bool)
    true[0, :10] = True
    pred = np.zeros_like(true)
    pred[0, :5] = True
    r = evaluate_methods(
        gt, {"updated": gt}, CAM, IDENTITY, BOX, 1, CFG, {"updated": ChangeMaskInput(pred, true)}
    )
    assert r["methods"]["updated"]["mask_precision"] == 1.0
    assert r["methods"]["updated"]["mask_recall"] == pytest.approx(0.5)
    assert r["label"] == "bite 1" and set(r["methods"]["updated"]) == set(METRIC_KEYS)
    with pytest.raises(InvalidInputError, match="no method"):
        evaluate_methods(gt, {}, CAM, IDENTITY, BOX, 1, CFG)
    with pytest.raises(InvalidInputError, match="without a mesh"):
        evaluate_methods(
            gt, {"a": gt}, CAM, IDENTITY, BOX, 1, CFG, {"b": ChangeMaskInput(pred, true)}
        )
    with pytest.raises(InvalidInputError, match="step"):
        evaluate_methods(gt, {"a": gt}, CAM, IDENTITY, BOX, -1, CFG)
    with pytest.raises(InvalidInputError, match="empty"):
        evaluate_methods(gt, {"a": trimesh.Trimesh()}, CAM, IDENTITY, BOX, 1, CFG)


# ------------------------------------------------------------------------- files and CLI


def _scene(tmp_path: Path) -> dict[str, Path]:
    """Meshes and sequences on disk: GT at 20 mm; updated shifted 0.7 mm; preop unchanged."""
    paths = {
        "prev_gt": tmp_path / "gt0.ply",
        "gt": tmp_path / "gt1.ply",
        "updated": tmp_path / "updated.ply",
        "preop": tmp_path / "preop.ply",
    }
    after = trimesh.util.concatenate([plane(22.0, x_range=(-60, 0)), plane(20.0, x_range=(0, 60))])
    plane(20.0).export(paths["prev_gt"])
    after.export(paths["gt"])
    plane(20.7).export(paths["updated"])
    plane(20.0).export(paths["preop"])
    # Tracked poses are 5 mm off the true ones: the evaluation must use the true poses.
    true_T = [np.eye(4), look_at([1, 0, 0], [1, 0, 20], up=[0, -1, 0])]
    frames = []
    for i, T in enumerate(true_T):
        tracked = T.copy()
        tracked[:3, 3] += [5.0, 0.0, 0.0]
        frames.append(Frame(index=i, T_world_from_cam=tracked, T_world_from_cam_true=T))
    paths["seq"] = write_sequence(tmp_path / "eval_seq", CAM, frames)
    masks = np.zeros((2, *CAM.shape), bool)
    masks[:, :, : CAM.width // 2] = True  # x < 0 for the first pose
    paths["masks"] = tmp_path / "masks.npz"
    np.savez(paths["masks"], masks=masks)
    return paths


def test_evaluate_step_from_files_uses_true_poses(tmp_path: Path) -> None:
    p = _scene(tmp_path)
    box = [-4.0, -3.0, 15.0, 4.0, 3.0, 25.0]
    r = evaluate_step(
        p["gt"], {"updated": p["updated"], "no_update": p["preop"]}, p["seq"], box, 1, CFG
    )
    assert r["protocol"]["eval_poses"].endswith("poses_true.txt")
    gt_mesh = load_mesh(p["gt"], "gt")
    true_T = np.stack([np.eye(4), look_at([1, 0, 0], [1, 0, 20], up=[0, -1, 0])])
    d = render_depths(gt_mesh, CAM, true_T)
    expect = correspondence_error(
        d,
        render_depths(load_mesh(p["preop"], "p"), CAM, true_T),
        CAM,
        true_T,
        RoiBox.from_values(box),
    )
    cell = r["methods"]["no_update"]
    assert cell["n_points"] == expect.n_points and cell["mean_mm"] == pytest.approx(expect.mean_mm)
    assert cell["mask_precision"] is None and r["methods"]["updated"]["mask_precision"] is None


def _analytic_change(eye_x_mm: list[float]) -> np.ndarray:
    """The scene's change seen from cameras at (x, 0, 0) looking down +z: the tissue at
    z = 20 mm is gone for world x < 0, so a pixel changed where its ray meets z = 20 at
    x < 0 (the surface behind, at 22 mm, is then 2 mm deeper)."""
    rays = CAM.rays_cam()
    u = rays[..., 0] / rays[..., 2]
    return np.stack([x + 20.0 * u < 0 for x in eye_x_mm])


def test_change_masks_are_scored_where_they_were_made(tmp_path: Path) -> None:
    """A mask lies in the image of the pose its method used (the tracked one, 5 mm off the
    true one here) and is scored against what the method's start model lacked."""
    p = _scene(tmp_path)
    box = [-4.0, -3.0, 15.0, 4.0, 3.0, 25.0]
    tracked_x, true_x = [5.0, 6.0], [0.0, 1.0]
    exact = tmp_path / "exact.npz"
    np.savez(exact, masks=_analytic_change(tracked_x))
    at_true = tmp_path / "at_true.npz"
    true_T = np.stack([np.eye(4), look_at([1, 0, 0], [1, 0, 20], up=[0, -1, 0])])
    np.savez(at_true, masks=_analytic_change(true_x), T_world_from_cam=true_T)
    shifted = tmp_path / "shifted.npz"  # a detector whose masks sit at the true poses
    np.savez(shifted, masks=_analytic_change(true_x))
    methods = {name: p["updated"] for name in ("exact", "at_true", "shifted", "done")}
    r = evaluate_step(
        p["gt"],
        methods,
        p["seq"],
        box,
        1,
        CFG,
        {"exact": exact, "at_true": at_true, "shifted": shifted, "done": exact},
        p["seq"],
        {"exact": p["prev_gt"], "at_true": p["prev_gt"], "shifted": p["prev_gt"], "done": p["gt"]},
    )
    cells = r["methods"]
    for name in ("exact", "at_true"):  # right where made: only edge pixels may differ
        assert cells[name]["mask_precision"] > 0.99 and cells[name]["mask_recall"] > 0.99
    # At the tracked poses the change is x < -5 / 20 (x < -6 / 20) of the image, the
    # masks made at the true poses say x < 0 (x < -1 / 20): all of the truth, and more.
    truth, pred = _analytic_change(tracked_x), _analytic_change(true_x)
    assert cells["shifted"]["mask_recall"] > 0.99
    assert cells["shifted"]["mask_precision"] == pytest.approx(truth.sum() / pred.sum(), abs=0.02)
    assert cells["shifted"]["mask_precision"] < 0.8
    # A model that already held the step's surface lacked nothing: every mask pixel is false.
    assert cells["done"]["mask_recall"] is None and cells["done"]["mask_precision"] == 0.0


def test_evaluate_step_rejects_bad_files(tmp_path: Path) -> None:
    p = _scene(tmp_path)
    box = [-4.0, -3.0, 15.0, 4.0, 3.0, 25.0]
    with pytest.raises(InvalidInputError, match="nope.ply.*not found"):
        evaluate_step(p["gt"], {"updated": tmp_path / "nope.ply"}, p["seq"], box, 1, CFG)
    empty = tmp_path / "empty.ply"
    empty.write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with pytest.raises(InvalidInputError, match="empty"):
        evaluate_step(p["gt"], {"updated": empty}, p["seq"], box, 1, CFG)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01 not a mesh")
    with pytest.raises(InvalidInputError, match="garbage.ply"):
        evaluate_step(p["gt"], {"updated": garbage}, p["seq"], box, 1, CFG)
    with pytest.raises(InvalidInputError, match="no method"):
        evaluate_step(p["gt"], {}, p["seq"], box, 1, CFG)
    with pytest.raises(InvalidInputError, match="sequence.json"):
        evaluate_step(p["gt"], {"updated": p["updated"]}, tmp_path, box, 1, CFG)
    with pytest.raises(InvalidInputError, match="change_sequence_path"):
        evaluate_step(
            p["gt"], {"updated": p["updated"]}, p["seq"], box, 1, CFG, {"updated": p["masks"]}
        )
    bad = tmp_path / "bad_poses.npz"
    np.savez(bad, masks=np.zeros((2, *CAM.shape), bool), T_world_from_cam=np.eye(4)[None])
    for masks, starts, match in (
        ({"other": p["masks"]}, {"other": p["prev_gt"]}, "has no mesh"),
        ({"updated": p["masks"]}, {"other": p["prev_gt"]}, "no start surface"),
        ({"updated": bad}, {"updated": p["prev_gt"]}, "bad_poses.npz.*T_world_from_cam"),
    ):
        with pytest.raises(InvalidInputError, match=match):
            evaluate_step(
                p["gt"], {"updated": p["updated"]}, p["seq"], box, 1, CFG, masks, p["seq"], starts
            )


def test_load_change_masks_formats_and_errors(tmp_path: Path) -> None:
    import cv2

    masks = np.zeros((2, 4, 5), bool)
    masks[0, 1, 2] = True
    folder = tmp_path / "pngs"
    folder.mkdir()
    for i, m in enumerate(masks):
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.where(m, 255, 0).astype(np.uint8))
    assert np.array_equal(load_change_masks(folder, 2, (4, 5)), masks)
    np.savez(tmp_path / "m.npz", masks=masks)
    assert np.array_equal(load_change_masks(tmp_path / "m.npz", 2, (4, 5)), masks)
    with pytest.raises(InvalidInputError, match="expected 3 masks"):
        load_change_masks(tmp_path / "m.npz", 3, (4, 5))
    np.savez(tmp_path / "k.npz", other=masks)
    with pytest.raises(InvalidInputError, match="key 'masks'"):
        load_change_masks(tmp_path / "k.npz", 2, (4, 5))
    np.save(tmp_path / "plain.npy", masks)
    with pytest.raises(InvalidInputError, match=".npz archive"):
        load_change_masks(tmp_path / "plain.npy", 2, (4, 5))
    with pytest.raises(InvalidInputError, match="missing"):
        load_change_masks(tmp_path / "nothing.npz", 2, (4, 5))
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(InvalidInputError, match="no PNG"):
        load_change_masks(tmp_path / "emptydir", 2, (4, 5))


# ------------------------------------------------------------------------- tables


def _cell(mean: float, **kw: float | None) -> dict:
    c = {k: 0.1 for k in METRIC_KEYS}
    c.update(
        mean_mm=mean,
        std_mm=0.2,
        n_points=100,
        n_gt_in_box=110,
        mask_precision=None,
        mask_recall=None,
    )
    c.update(kw)
    return c


def _step(step: int, methods: dict) -> dict:
    return {
        "format": "endoscopic-chisel/step-metrics",
        "version": 1,
        "step": step,
        "label": "x",
        "methods": methods,
        "protocol": {"roi_box_mm": [0, 0, 0, 1, 1, 1]},
    }


def test_table_round_trip(tmp_path: Path) -> None:
    steps = [
        _step(
            2,
            {
                "updated": _cell(3.4),
                "no_update": _cell(4.1),
                "depth_ablation": _cell(1.8),
                "registration_ablation": _cell(5.5, mask_precision=0.7, mask_recall=0.6),
            },
        ),
        _step(0, {"updated": _cell(0.23)}),
        _step(
            1, {"registration_ablation": _cell(6.3), "updated": _cell(2.4), "no_update": _cell(1.9)}
        ),
    ]
    table = assemble_table(steps, "demo")
    assert [s["step"] for s in table["steps"]] == [0, 1, 2]
    assert [s["label"] for s in table["steps"]] == ["preop", "bite 1", "bite 2"]
    assert list(table["steps"][2]["methods"]) == [
        "no_update",
        "updated",
        "depth_ablation",
        "registration_ablation",
    ]
    paths = write_table(tmp_path / "out", table)
    back = read_metrics(paths["json"])
    assert back == table and back["format"] == METRICS_FORMAT
    rows = list(csv.DictReader(io.StringIO(paths["csv"].read_text())))
    assert {(r["step"], r["method"]) for r in rows} == {
        (str(s["step"]), m) for s in table["steps"] for m in s["methods"]
    }
    assert (
        float(next(r for r in rows if r["step"] == "2" and r["method"] == "updated")["mean_mm"])
        == 3.4
    )
    assert next(r for r in rows if r["step"] == "0")["mask_precision"] == ""
    md = paths["md"].read_text()
    for token in (
        "preop",
        "bite 1",
        "bite 2",
        "no_update",
        "updated",
        "depth_ablation",
        "registration_ablation",
    ):
        assert token in md
    assert "3.400 ± 0.200 (n=100)" in md
    assert md == metrics_to_markdown(table) and paths["csv"].read_text() == metrics_to_csv(table)


def test_table_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match="no step"):
        assemble_table([], "x")
    with pytest.raises(InvalidInputError, match="twice"):
        assemble_table([_step(1, {"u": _cell(1)}), _step(1, {"u": _cell(2)})], "x")
    bad = _cell(1.0)
    del bad["chamfer_mm"]
    with pytest.raises(InvalidInputError, match="chamfer_mm"):
        assemble_table([_step(1, {"u": bad})], "x")
    with pytest.raises(InvalidInputError, match="mean_mm"):
        assemble_table([_step(1, {"u": _cell(-1.0)})], "x")
    with pytest.raises(InvalidInputError, match="not a metrics.json"):
        validate_metrics({"format": "nope", "version": 1, "experiment": "x", "steps": []})
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InvalidInputError, match="invalid JSON"):
        read_metrics(tmp_path / "bad.json")
    with pytest.raises(InvalidInputError, match="missing"):
        read_metrics(tmp_path / "none.json")


def test_aggregate_seeds(tmp_path: Path) -> None:
    t1 = assemble_table([_step(1, {"updated": _cell(2.0, mask_recall=0.5)})], "table")
    t2 = assemble_table(
        [_step(1, {"updated": _cell(4.0)}), _step(2, {"updated": _cell(1.0)})], "table"
    )
    agg = aggregate_seeds([t1, t2], ["seed 0", "seed 1"])
    m = agg["steps"][0]["methods"]["updated"]
    assert m["mean_mm"] == {"mean": 3.0, "std": 1.0, "min": 2.0, "max": 4.0, "n": 2}
    assert m["mask_recall"]["n"] == 1 and m["mask_precision"] is None
    assert agg["steps"][1]["methods"]["updated"]["mean_mm"]["n"] == 1
    paths = write_seed_table(tmp_path, agg)
    assert json.loads(paths["json"].read_text()) == agg
    assert "3.000 ± 1.000 (2)" in paths["md"].read_text()
    assert "bite 2" in paths["csv"].read_text()
    with pytest.raises(InvalidInputError, match="labels"):
        aggregate_seeds([t1], ["a", "b"])
    with pytest.raises(InvalidInputError, match="no metrics"):
        aggregate_seeds([])


def test_sweep_round_trip(tmp_path: Path) -> None:
    runs = [
        (
            30.0,
            assemble_table(
                [_step(1, {"updated": _cell(2.0)}), _step(2, {"updated": _cell(3.0)})], "s"
            ),
        ),
        (
            10.0,
            assemble_table(
                [_step(1, {"updated": _cell(4.0)}), _step(2, {"updated": _cell(5.0)})], "s"
            ),
        ),
    ]
    table = tabulate_sweep("frames", runs)
    assert table.values() == [10.0, 30.0] and table.last_step() == 2
    back = read_sweep_csv(write_sweep_csv(tmp_path / "s.csv", table))
    assert back == table
    with pytest.raises(InvalidInputError, match="twice"):
        tabulate_sweep("frames", [runs[0], runs[0]])
    with pytest.raises(InvalidInputError, match="no sweep run"):
        tabulate_sweep("frames", [])
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InvalidInputError, match="expected columns"):
        read_sweep_csv(tmp_path / "bad.csv")


def test_cli_evaluate_table_sweep_seeds(tmp_path: Path) -> None:
    p = _scene(tmp_path)
    roi = "-4,-3,15,4,3,25"
    for step, gt in ((0, p["prev_gt"]), (1, p["gt"])):
        rc = cli_main(
            [
                "evaluate",
                "--gt-mesh",
                str(gt),
                "--method",
                f"updated={p['updated']}",
                f"no_update={p['preop']}",
                "--eval-sequence",
                str(p["seq"]),
                f"--roi={roi}",
                "--step",
                str(step),
                "--samples",
                "2000",
                "--out",
                str(tmp_path / f"s{step}.json"),
                *(
                    [
                        "--change-masks",
                        f"updated={p['masks']}",
                        "--change-sequence",
                        str(p["seq"]),
                        "--start-surfaces",
                        f"updated={p['prev_gt']}",
                    ]
                    if step == 1
                    else []
                ),
            ]
        )
        assert rc == 0
    s0 = json.loads((tmp_path / "s0.json").read_text())
    assert s0["step"] == 0 and s0["methods"]["no_update"]["mean_mm"] == 0.0
    # The left image half, scored at the tracked poses (5 mm off): all of the change there.
    s1 = json.loads((tmp_path / "s1.json").read_text())["methods"]["updated"]
    assert s1["mask_recall"] > 0.99 and 0.3 < s1["mask_precision"] < 0.8
    assert (
        cli_main(
            [
                "evaluate",
                "table",
                "--inputs",
                str(tmp_path / "s1.json"),
                str(tmp_path / "s0.json"),
                "--out-dir",
                str(tmp_path / "t"),
                "--experiment",
                "cli",
            ]
        )
        == 0
    )
    table = read_metrics(tmp_path / "t" / "metrics.json")
    assert table["experiment"] == "cli" and [s["step"] for s in table["steps"]] == [0, 1]
    assert (tmp_path / "t" / "metrics.csv").is_file() and (tmp_path / "t" / "metrics.md").is_file()
    mj = str(tmp_path / "t" / "metrics.json")
    assert (
        cli_main(
            [
                "evaluate",
                "sweep",
                "--param",
                "frames",
                "--run",
                f"10={mj}",
                "--out",
                str(tmp_path / "sw.csv"),
            ]
        )
        == 0
    )
    assert read_sweep_csv(tmp_path / "sw.csv").values() == [10.0]
    assert (
        cli_main(["evaluate", "seeds", "--inputs", mj, mj, "--out-dir", str(tmp_path / "agg")]) == 0
    )
    assert (tmp_path / "agg" / "metrics_seeds.md").is_file()
    # Errors: reported with the option named, exit code 1, earlier output intact.
    before = (tmp_path / "s1.json").read_bytes()
    assert (
        cli_main(["evaluate", "--gt-mesh", str(p["gt"]), "--out", str(tmp_path / "s1.json")]) == 1
    )
    assert (
        cli_main(
            [
                "evaluate",
                "--gt-mesh",
                str(p["gt"]),
                "--method",
                "updated",
                "--eval-sequence",
                str(p["seq"]),
                f"--roi={roi}",
                "--step",
                "1",
                "--out",
                str(tmp_path / "s1.json"),
            ]
        )
        == 1
    )
    assert (
        cli_main(
            [
                "evaluate",
                "--gt-mesh",
                str(p["gt"]),
                "--method",
                f"updated={tmp_path / 'x.ply'}",
                "--eval-sequence",
                str(p["seq"]),
                f"--roi={roi}",
                "--step",
                "1",
                "--out",
                str(tmp_path / "s1.json"),
            ]
        )
        == 1
    )
    assert (
        cli_main(
            [
                "evaluate",
                "sweep",
                "--param",
                "frames",
                "--run",
                f"ten={mj}",
                "--out",
                str(tmp_path / "sw2.csv"),
            ]
        )
        == 1
    )
    assert (tmp_path / "s1.json").read_bytes() == before


# --------------------------------------------------------------------------------------
# Volumetric scores of the removal (chisel.eval.volume)


def _box_mask(shape: tuple[int, int, int], lo: tuple[int, ...], hi: tuple[int, ...]) -> np.ndarray:
    m = np.zeros(shape, bool)
    m[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = True
    return m


def test_removal_dice_matches_box_overlap_and_hd95_a_kdtree() -> None:
    from scipy.spatial import cKDTree

    from chisel.eval.volume import _boundary, dice, hd95_mm, removal_scores

    shape = (40, 40, 40)
    a = _box_mask(shape, (5, 5, 5), (25, 25, 25))  # 20^3 voxels
    b = _box_mask(shape, (9, 5, 5), (29, 25, 25))  # shifted by 4 voxels along x
    # Overlap 16 x 20 x 20: Dice = 2 * 6400 / 16000.
    assert dice(a, b) == pytest.approx(2 * 16 * 400 / (2 * 8000))
    assert dice(a, a) == 1.0 and dice(np.zeros(shape, bool), np.zeros(shape, bool)) is None
    # HD95 against a k-d tree over the boundary voxels' centres (0.5 mm voxels).
    pa, pb = np.argwhere(_boundary(a)) * 0.5, np.argwhere(_boundary(b)) * 0.5
    d = np.concatenate([cKDTree(pb).query(pa)[0], cKDTree(pa).query(pb)[0]])
    assert hd95_mm(a, b, 0.5) == pytest.approx(np.percentile(d, 95))
    assert hd95_mm(a, a, 0.5) == 0.0 and hd95_mm(a, np.zeros(shape, bool), 0.5) is None
    s = removal_scores(a, b, 0.5)
    assert s.model_mm3 == pytest.approx(8000 * 0.125) and s.truth_mm3 == s.model_mm3
    assert s.precision == pytest.approx(16 / 20) and s.recall == pytest.approx(16 / 20)
    # Which way a method errs: carving a third of the removal and nothing else, or all of
    # it and twice as much again elsewhere, both score Dice 0.5; precision and recall tell.
    third = _box_mask(shape, (5, 5, 5), (25, 25, 10))  # 20 x 20 x 5 of the 20^3 truth
    less = removal_scores(third, a, 0.5)
    assert less.dice == pytest.approx(2 * 2000 / 10000)
    assert less.precision == 1.0 and less.recall == pytest.approx(2000 / 8000)
    more = removal_scores(a | _box_mask(shape, (5, 5, 25), (25, 25, 40)), a, 0.5)  # + 20x20x15
    assert more.precision == pytest.approx(8000 / 14000) and more.recall == 1.0


def test_model_and_true_removal_on_the_model_grid() -> None:
    from chisel.eval.volume import model_removal, removal_scores, true_removal
    from chisel.model import TsdfModel

    # CT: 1 mm voxels, tissue (label 1) everywhere, a 4 mm cube removed at the step.
    pre = np.ones((20, 20, 20), np.uint8)
    now = pre.copy()
    now[8:12, 8:12, 8:12] = 0
    T_ct = np.eye(4)
    # Model: 0.5 mm voxels over the same box; the "updated" model frees the same cube.
    m0 = TsdfModel.empty(np.zeros(3), np.full(3, 19.0), 0.5, 2.0)
    m0.tsdf[:] = -1.0
    m0.weight[:] = 1.0
    m1 = m0.copy()
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in m0.shape], indexing="ij"), -1) * 0.5
    cube = np.all((ijk >= 7.5) & (ijk < 11.5), axis=-1)  # nearest CT voxels 8..11
    m1.tsdf[cube] = 1.0
    truth = true_removal(pre, now, T_ct, m0)
    got = model_removal(m0, m1)
    np.testing.assert_array_equal(truth, cube)
    s = removal_scores(got, truth, 0.5)
    assert s.dice == 1.0 and s.hd95_mm == 0.0
    assert s.truth_mm3 == pytest.approx(cube.sum() * 0.125)
    # No update: nothing removed, Dice 0, HD95 undefined.
    s0 = removal_scores(model_removal(m0, m0), truth, 0.5)
    assert s0.dice == 0.0 and s0.hd95_mm is None
    assert s0.precision is None and s0.recall == 0.0  # nothing carved: no precision to speak of
    assert (s.precision, s.recall) == (1.0, 1.0)


def test_removal_scores_each_method_against_its_own_preop_grid(tmp_path, monkeypatch) -> None:
    # The sweep-only build's grid differs from the CT build's: each method's removal is
    # scored on the grid of the model its steps started from (default experiment, seed 4).
    import types

    import chisel.io.ct
    from chisel.eval.step import _removals
    from chisel.model import TsdfModel

    pre = np.ones((20, 20, 20), np.uint8)
    now = pre.copy()
    now[8:12, 8:12, 8:12] = 0
    labels = {"pre.nii": pre, "now.nii": now}
    monkeypatch.setattr(
        chisel.io.ct,
        "read_ct_volume",
        lambda p, kind: types.SimpleNamespace(
            data=labels[Path(p).name], T_world_from_voxel=np.eye(4)
        ),
    )
    paths = {}
    for name, lo, hi in (("ct", 0.0, 19.0), ("sweep", 1.0, 17.0)):
        m0 = TsdfModel.empty(np.full(3, lo), np.full(3, hi), 0.5, 2.0)
        m0.tsdf[:] = -1.0
        m0.weight[:] = 1.0
        m1 = m0.copy()
        ijk = np.stack(np.meshgrid(*[np.arange(s) for s in m0.shape], indexing="ij"), -1)
        xyz = ijk * 0.5 + lo
        m1.tsdf[np.all((xyz >= 7.5) & (xyz < 11.5), axis=-1)] = 1.0
        m0.save(tmp_path / f"{name}_0.npz")
        m1.save(tmp_path / f"{name}_1.npz")
        paths[name] = (tmp_path / f"{name}_0.npz", tmp_path / f"{name}_1.npz")
    ct_paths = (tmp_path / "pre.nii", tmp_path / "now.nii")
    got = _removals(
        {k: v[1] for k, v in paths.items()}, {k: v[0] for k, v in paths.items()}, ct_paths
    )
    assert got["ct"].dice == 1.0 and got["sweep"].dice == 1.0
    assert got["sweep"].truth_mm3 == pytest.approx(got["ct"].truth_mm3)
    # One preop model for both: the sweep's model is not on its grid.
    with pytest.raises(InvalidInputError, match="not on the preoperative model's grid"):
        _removals({k: v[1] for k, v in paths.items()}, paths["ct"][0], ct_paths)


def test_seen_free_is_what_a_frame_sees_in_front_of_its_depth() -> None:
    """A wall at z = 10 mm with a window (depth 20 mm inside it), one camera at the origin
    looking down +z: a point is seen free in front of the wall, behind it only through the
    window, never within the margin of the surface, outside the image or behind the camera."""
    from chisel.eval.volume import seen_free

    cam = Camera.from_fov(64, 48, 70.0)
    T = look_at(np.zeros(3), np.array([0.0, 0.0, 10.0]), np.array([0.0, -1.0, 0.0]))
    rays = cam.rays_cam()
    depth = np.full(cam.shape, 10.0, np.float32)
    # The window: pixels whose ray meets the plane z = 10 within 2 mm of the axis.
    window = np.max(np.abs(rays[..., :2] * 10.0), axis=-1) < 2.0
    depth[window] = 20.0
    depth[0, :] = np.nan  # a row that sees nothing
    c = T[:3, 3]
    x_side = 4.0  # off the window: its rays meet the wall 2.7-4 mm from the axis
    pts = (
        np.array(
            [
                [0.0, 0.0, 5.0],  # in front of the wall: free
                [0.0, 0.0, 15.0],  # behind the wall, through the window: free
                [x_side, 0.0, 15.0],  # behind the wall, off the window
                [x_side, 0.0, 9.9],  # within the margin of the wall's surface
                [x_side, 0.0, 9.5],  # in front of it by more than the margin: free
                [0.0, 0.0, -5.0],  # behind the camera
                [50.0, 0.0, 5.0],  # outside the image
            ]
        )
        + c
    )
    got = seen_free(pts, cam, T[None], depth[None], margin_mm=0.25)
    np.testing.assert_array_equal(got, [True, True, False, False, True, False, False])
    # Two frames: a second one placed so that it sees the off-window point in front of its own
    # wall; one frame that sees it free is enough.
    T2 = T.copy()
    T2[:3, 3] += [x_side, 0.0, 12.0]
    got2 = seen_free(pts[2:3], cam, np.stack([T, T2]), np.stack([depth, depth]), 0.25)
    assert got2.tolist() == [True]
    with pytest.raises(InvalidInputError, match="depths_mm"):
        seen_free(pts, cam, T[None], depth[None, :10], 0.25)


def test_seen_free_ignores_a_point_the_lens_polynomial_folds_back_into_the_image() -> None:
    """Barrel distortion k1 = -0.18 (the simulator's endoscope) folds points far off axis
    back into the image: Camera.project puts a point at 65 deg from the axis inside it. The
    pixel fusion and carving use refuses it (beyond the lens model's valid radius), so a
    frame looking the other way does not 'see' it free."""
    from chisel.eval.volume import seen_free

    cam = Camera.from_fov(64, 48, 70.0, dist=np.array([-0.18, 0.0, 0.0, 0.0, 0.0]))
    p_cam = np.array([np.tan(np.radians(65.0)), 0.0, 1.0]) * 5.0
    uv, _ = cam.project(p_cam[None])
    assert 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height  # folded back inside
    T = np.eye(4)
    depth = np.full(cam.shape, 100.0, np.float32)  # a far wall: anything in view is free
    assert seen_free(p_cam[None], cam, T[None], depth[None], 0.25).tolist() == [False]
    on_axis = np.array([[0.0, 0.0, 5.0]])
    assert seen_free(on_axis, cam, T[None], depth[None], 0.25).tolist() == [True]
