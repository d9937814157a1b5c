"""The benchmark scripts run end to end on tiny inputs and keep their output contract.

Each script prints ``name: value`` lines with its headline figure last; other tools and
the issue notes read those names. Only the form is checked here, never a speed: speed
goals are met in benchmarks/, not in timed tests.
"""

from __future__ import annotations

import dataclasses
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from benchmark_module import load_benchmark

from chisel.depth import DEFAULT_CHECKPOINT

ROOT = Path(__file__).resolve().parents[1]
LINE = re.compile(r"^([a-z][a-z0-9_]*): (\S.*)$")


def run_script(script: str, *args: str, timeout_s: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout_s,
    )


def run_bench(script: str, *args: str) -> list[tuple[str, str]]:
    """Run ``benchmarks/<script>`` and return its ``(name, value)`` lines in order."""
    r = run_script(script, *args)
    assert r.returncode == 0, f"{script} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    pairs = [m.groups() for m in map(LINE.match, r.stdout.splitlines()) if m]
    assert pairs, f"{script} printed no name: value line:\n{r.stdout[-3000:]}"
    return pairs


def number(value: str) -> float:
    x = float(value)
    assert math.isfinite(x), value
    return x


def check_contract(pairs: list[tuple[str, str]], headline: str, required: list[str]) -> dict:
    """The headline comes last and is a positive number; every required name is there."""
    assert pairs[-1][0] == headline, f"last line is {pairs[-1]}, expected {headline}"
    assert number(pairs[-1][1]) > 0
    figures = dict(pairs)
    missing = [name for name in required if name not in figures]
    assert not missing, f"missing figures: {missing}"
    return figures


def test_bench_render_prints_variant_depth_fps_and_rgbd_fps_last() -> None:
    # Fewer frames than the 100 after which memory growth is normally read: that path
    # used to crash.
    pairs = run_bench("bench_render.py", "--frames", "3", "--depth-frames", "8", "--batch", "4")
    figures = check_contract(
        pairs,
        "rgbd_fps",
        ["variant", "depth_fps", "rgb_render_ms", "rgb_mitsuba_direct_ms", "rss_growth_mb"],
    )
    assert figures["variant"] in ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
    assert number(figures["depth_fps"]) > 0
    assert number(figures["rgb_speedup_vs_mitsuba_direct_wall"]) > 0
    if figures["variant"] != "scalar_rgb":
        # The primary rays alone cost less than the whole colour frame.
        assert number(figures["rgb_primary_rays_ms"]) < number(figures["rgb_render_ms"])
        assert number(figures["rgbd_fps_bound_primary_rays"]) > 0


def test_bench_render_refuses_zero_frames() -> None:
    r = run_script("bench_render.py", "--frames", "0")
    assert r.returncode == 2 and "--frames" in r.stderr


def test_bench_update_prints_fusion_ratio_and_update_fps_last() -> None:
    pairs = run_bench(
        "bench_update.py",
        "--width", "64", "--height", "48", "--voxel-mm", "1.0",
        "--preop-frames", "4", "--frames", "4", "--repeats", "1",
    )  # fmt: skip
    figures = check_contract(
        pairs,
        "update_fps",
        ["fusion_ratio_vs_open3d", "batch_update_fps", "update_fps_from_ct",
         "update_fps_from_ct_shading", "shading_fps_ratio", "update_fps_from_ct_shading_stream",
         "shading_stream_fps_ratio", "peak_rss_mib"],
    )  # fmt: skip
    assert number(figures["fusion_ratio_vs_open3d"]) > 0
    assert number(figures["shading_fps_ratio"]) > 0
    assert figures["update_shading_stream_same_model"] == "True"
    # It times the update as the shipped experiments run it (config/config.yaml).
    assert figures["noise_with_depth"] == "True"
    assert number(figures["noise_with_depth_fps_ratio"]) > 0


def test_bench_dataset_prints_ratio_last_and_names_its_generator() -> None:
    # The toy generator keeps this quick; without --phantom-cmd the benchmark runs sim
    # dataset's own default (the anatomy generator), which it must say.
    toy = f"{sys.executable} -m sim.synthetic"
    pairs = run_bench(
        "bench_dataset.py", "--seeds", "0", "--frames", "2", "--preop-frames", "2",
        "--bites", "1", "--spp", "1", "--width", "64", "--height", "48", "--phantom-cmd", toy,
    )  # fmt: skip
    figures = check_contract(
        pairs,
        "dataset_vs_render_ratio",
        ["cpu_simd", "phantom_cmd", "dataset_frames", "render_rgbd_fps", "dataset_fps",
         "rss_peak_first_phantom_mb", "rss_peak_last_phantom_mb", "rss_growth_mb"],
    )  # fmt: skip
    assert figures["phantom_cmd"] == toy
    assert number(figures["dataset_frames"]) == 2 + 1 * 2  # the preop sweep and one step


def test_bench_phantoms_prints_phantom_s_last() -> None:
    pairs = run_bench("bench_phantoms.py", "--seed", "0")
    figures = check_contract(pairs, "phantom_s", ["triangles_step0", "removed_mm3"])
    assert number(figures["triangles_step0"]) > 0 and number(figures["removed_mm3"]) > 0


@pytest.mark.slow
def test_bench_depth_prints_accuracy_and_infer_fps_last() -> None:
    fx = str(ROOT / "config" / "sim_eval_effects.yaml")
    pairs = run_bench(
        "bench_depth.py", "--seeds", "0", "--frames", "2", "--effects-config", fx,
        "--baseline", str(DEFAULT_CHECKPOINT),
    )  # fmt: skip
    names = ["abs_rel", "delta_1_25", "infer_fps_eager", "abs_rel_effects", "baseline_abs_rel"]
    figures = check_contract(pairs, "infer_fps", [*names, "baseline_abs_rel_effects"])
    assert 0 <= number(figures["delta_1_25"]) <= 1
    # The baseline here is the same checkpoint: the same frames give the same figures.
    assert figures["baseline_abs_rel"] == figures["abs_rel"]
    assert figures["baseline_abs_rel_effects"] == figures["abs_rel_effects"]


@pytest.mark.slow
def test_bench_depth_train_prints_train_min_last() -> None:
    pairs = run_bench("bench_depth_train.py", "--phantoms", "2", "--epochs", "1")
    figures = check_contract(pairs, "train_min", ["val_abs_rel", "best_epoch", "dataset_min"])
    assert number(figures["val_abs_rel"]) > 0


def test_bench_depth_train_refuses_a_single_phantom() -> None:
    r = run_script("bench_depth_train.py", "--phantoms", "1")
    assert r.returncode == 2 and "validation holds out whole phantoms" in r.stderr


def test_bench_carve_oracle_sources_put_true_depth_where_the_network_decides() -> None:
    from chisel.depth_source import (
        GroundTruthDepth,
        is_estimate,
        is_metric,
        reliable_pixels,
        wants_prior,
    )
    from chisel.io.sequence import Frame
    from chisel.update_config import UpdateConfig
    from chisel.updater import is_precise

    oracle = load_benchmark("bench_carve_oracle")
    true = np.full((4, 5), 20.0, np.float32)
    true[1:3, 1:3] = 30.0  # a window 10 mm deep
    prior = np.full((4, 5), 20.5, np.float32)
    decided = np.zeros((4, 5), bool)
    decided[1:3, 1:4] = True  # the network says "changed" on the window and one column more
    mask = np.ones((4, 5), bool)
    mask[0, 0] = False

    class Network:
        last_change_probability: np.ndarray | None = None

        def __call__(self, frame: Frame, prior_mm: np.ndarray) -> np.ndarray:
            self.last_change_probability = np.where(decided, 0.9, 0.1).astype(np.float32)
            return prior_mm + 1.0

    frame = Frame(0, np.eye(4), np.zeros((4, 5, 3), np.uint8), true, mask)
    source = oracle.DecisionTrueDepth(Network())
    expected = np.where(decided, true, prior)
    expected[0, 0] = np.nan
    np.testing.assert_array_equal(source(frame, prior_mm=prior), expected)
    noisy = oracle.TrueDepthAsEstimate()
    np.testing.assert_array_equal(noisy(frame), true)
    assert wants_prior(source) and is_metric(source) and is_metric(noisy)
    # Both are carved as a network is; the frame's true depth alone is carved as precise.
    cfg = UpdateConfig()
    assert not is_precise(1.0, cfg, is_estimate(source))
    assert not is_precise(1.0, cfg, is_estimate(noisy))
    assert is_precise(1.0, cfg, is_estimate(GroundTruthDepth()))
    # The oracle reliability head: the network's own depth, reliable where it lies within
    # the tolerance of the truth (here: 1.5 mm off everywhere but the window, 8.5 mm there).
    reliable = oracle.OracleReliable(Network(), tol_mm=1.6)
    np.testing.assert_array_equal(reliable(frame, prior_mm=prior), prior + 1.0)
    assert reliable.last_reliable_px is not None
    np.testing.assert_array_equal(reliable.last_reliable_px, np.abs(prior + 1.0 - true) <= 1.6)
    assert reliable.last_reliable_px.sum() == 16 and is_estimate(reliable)
    assert reliable_pixels(reliable, frame, true.shape) is not None
    # The frame's pose, as a tracker without error would report it.
    moved = oracle.with_true_pose(dataclasses.replace(frame, T_world_from_cam_true=2 * np.eye(4)))
    np.testing.assert_array_equal(moved.T_world_from_cam, 2 * np.eye(4))


def test_bench_carve_oracle_above_noise_sees_only_what_the_network_threshold_lets_through() -> None:
    from chisel.depth_source import is_estimate, is_metric, wants_prior
    from chisel.io.sequence import Frame

    oracle = load_benchmark("bench_carve_oracle")
    prior = np.full((4, 5), 20.0, np.float32)
    true = prior.copy()
    true[1, 1:4] = 30.0  # a cut 10 mm deep
    true[2, 1:4] = 22.0  # and a shallow one, 2 mm
    mask = np.ones((4, 5), bool)
    mask[1, 3] = False  # an instrument over one pixel of the deep cut
    source = oracle.TrueDepthAboveNoise({0: 3.0, 1: 1.5})
    deep_only = np.where(true - prior > 3.0, true, prior)
    deep_only[1, 3] = np.nan
    out = source(Frame(0, np.eye(4), None, true, mask), prior_mm=prior)
    np.testing.assert_array_equal(out, deep_only)
    # A lower threshold lets the shallow cut through too; a frame the network's run did not
    # use has no threshold and sees nothing.
    np.testing.assert_array_equal(source(Frame(1, np.eye(4), None, true), prior_mm=prior), true)
    np.testing.assert_array_equal(source(Frame(2, np.eye(4), None, true), prior_mm=prior), prior)
    assert wants_prior(source) and is_metric(source) and is_estimate(source)


@pytest.mark.parametrize(
    ("method", "sources", "message"),
    [
        ("updated", ("network", "decision_true_depth"), "only with --method change_aware"),
        ("updated", ("network", "network_oracle_reliable"), "only with --method change_aware"),
        ("change_aware", ("network", "above_noise_true_depth"), "only with --method updated or"),
        ("updated_sweep", ("network", "decision_true_depth"), "only with --method change_aware"),
        ("updated", ("above_noise_true_depth", "true_depth"), "needs network too"),
    ],
)
def test_bench_carve_oracle_refuses_a_source_the_row_cannot_drive(
    method: str, sources: tuple[str, ...], message: str
) -> None:
    oracle = load_benchmark("bench_carve_oracle")
    with pytest.raises(SystemExit, match=message):
        oracle.check_sources(method, sources)
    oracle.check_sources(method, oracle.DEFAULT_SOURCES[method])  # the defaults are accepted
    oracle.check_sources("updated_sweep", ("network", "above_noise_true_depth"))


def test_bench_carve_oracle_takes_away_each_part_of_the_tracking_error() -> None:
    """Frames tracked as T_true @ E @ J (sim.tracking's model), scipy rotations as truth."""
    from scipy.spatial.transform import Rotation

    from chisel.io.sequence import Frame

    oracle = load_benchmark("bench_carve_oracle")
    rng = np.random.default_rng(3)

    def rigid(deg: float, mm: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * math.radians(deg)).as_matrix()
        T[:3, 3] = rng.normal(size=3) * mm
        return T

    E = rigid(0.5, 0.5)  # a constant hand-eye error
    true = [rigid(30.0, 20.0) for _ in range(9)]
    jitter = [np.eye(4) if i % 3 else rigid(0.1, 0.2) for i in range(9)]  # 3 of 9 jitter
    frames = [
        Frame(i, T @ E @ J, T_world_from_cam_true=T)
        for i, (T, J) in enumerate(zip(true, jitter, strict=True))
    ]
    parts = {p: oracle.remove_tracking_error(frames, p) for p in oracle.POSE_ERRORS}
    for i, (f, T) in enumerate(zip(frames, true, strict=True)):
        np.testing.assert_array_equal(parts["all"][i].T_world_from_cam, T)
        np.testing.assert_array_equal(parts["translation"][i].T_world_from_cam[:3, 3], T[:3, 3])
        np.testing.assert_array_equal(
            parts["translation"][i].T_world_from_cam[:3, :3], f.T_world_from_cam[:3, :3]
        )
        np.testing.assert_array_equal(parts["rotation"][i].T_world_from_cam[:3, :3], T[:3, :3])
        np.testing.assert_array_equal(
            parts["rotation"][i].T_world_from_cam[:3, 3], f.T_world_from_cam[:3, 3]
        )
        # E is undone exactly (the median over frames ignores the jittered third), and each
        # frame keeps its own jitter, carried through E: T @ E @ J @ E^-1.
        np.testing.assert_allclose(
            parts["hand_eye"][i].T_world_from_cam, T @ E @ jitter[i] @ np.linalg.inv(E), atol=1e-9
        )
    with pytest.raises(SystemExit, match="frame 0: no true pose"):
        oracle.remove_tracking_error([Frame(0, np.eye(4))], "hand_eye")


def test_bench_fidelity_figures_from_a_table() -> None:
    """The goal figures of bench_fidelity.py, from a two-step table written by hand."""
    fid = load_benchmark("bench_fidelity")

    def cell(mean: float, **kw: float | None) -> dict:
        return {"mean_mm": mean, "missing_fraction": 0.0, **kw}

    metrics = {
        "steps": [
            {"step": 0, "methods": {"updated": cell(0.05)}},
            {"step": 1, "methods": {
                "no_update": cell(2.0),
                "updated": cell(1.0, mask_precision=0.8, mask_recall=0.6, removed_dice=0.7),
                "depth_ablation": cell(0.25, removed_dice=0.9, removed_hd95_mm=0.5),
                "change_aware": cell(0.5, mask_precision=0.9, mask_recall=0.8, removed_dice=0.85),
            }},
            {"step": 2, "methods": {
                "no_update": cell(4.0),
                "updated": cell(4.4, mask_precision=None, mask_recall=0.9, removed_dice=0.8),
                "depth_ablation": cell(0.4, removed_dice=0.95, removed_hd95_mm=1.2),
                "change_aware": cell(1.0, mask_precision=0.95, mask_recall=0.9, removed_dice=0.82),
            }},
        ]
    }  # fmt: skip
    f = fid.seed_figures(metrics)
    assert f["exact_max_mean_mm"] == 0.4 and f["exact_last_step_ratio"] == pytest.approx(0.1)
    assert f["exact_removed_dice_min"] == 0.9 and f["exact_removed_hd95_max_mm"] == 1.2
    assert f["updated_ratio_steps2_max"] == pytest.approx(1.1)
    assert f["updated_ratio_max"] == pytest.approx(1.1)
    assert f["updated_mask_recall_min"] == 0.6 and f["updated_removed_dice_min"] == 0.7
    assert math.isnan(f["updated_mask_precision_min"])  # a step with no mask to score
    assert not fid.meets("updated_mask_precision_min", f["updated_mask_precision_min"])
    assert fid.meets("exact_last_step_ratio", 0.1) and not fid.meets("exact_max_mean_mm", 0.4)
    other = {**f, "updated_ratio_max": 0.7, "exact_removed_dice_min": 0.8}
    assert fid.worst({0: f, 1: other}, "updated_ratio_max") == pytest.approx(1.1)
    assert fid.worst({0: f, 1: other}, "exact_removed_dice_min") == 0.8
    # the change-aware row is scored alike, against issue 20's bounds
    assert f["change_aware_ratio_steps2_max"] == pytest.approx(0.25)
    assert f["change_aware_ratio_max"] == pytest.approx(0.25)
    assert f["change_aware_mask_precision_min"] == 0.9
    assert f["change_aware_mask_recall_min"] == 0.8 and f["change_aware_removed_dice_min"] == 0.82
    assert fid.meets("change_aware_ratio_steps2_max", 0.25)
    assert not fid.meets("change_aware_mask_recall_min", 0.8)  # 0.85 there, 0.7 for updated
    assert fid.meets("updated_mask_recall_min", 0.8)
    assert fid.parse_seeds("0-2,5") == [0, 1, 2, 5]


def test_bench_change_depth_streams_as_shipped_and_prints_abs_rel_last(tmp_path: Path) -> None:
    # A one-phantom, one-bite evaluation dataset at 64 x 48 (about 10 s to render).
    data = tmp_path / "eval"
    r = subprocess.run(
        [sys.executable, "-m", "sim", "dataset", "--seeds", "0", "--out", str(data),
         "--bites", "1", "--phantom-args", "--procedure uncinectomy", "--frames", "4",
         "--preop-frames", "2", "--spp", "1", "--width", "64", "--height", "48"],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    pairs = run_bench("bench_change_depth.py", "--data", str(data), "--stream-update")
    modes = ("no_registration", "registration", "registration_shading")
    figures = check_contract(
        pairs,
        "change_aware_abs_rel",
        ["frames", "change_aware_vs_tracked_abs_rel_near_change", "prior_vs_tracked_abs_rel_unchanged",
         "monocular_vs_true_abs_rel_near_change", "change_aware_mask_precision", "cpu_simd",
         "noise_with_depth", "stream_render_plus_infer_fps_median"]
        + [f"stream_update_{m}_{k}" for m in modes for k in ("fps", "frame_by_frame_fps")],
    )  # fmt: skip
    assert int(figures["frames"].split()[0]) == 4  # the step's four frames, none skipped
    # The prior is the tracked-pose target wherever nothing changed: no error there.
    assert number(figures["prior_vs_tracked_abs_rel_unchanged"]) == 0.0
    assert number(figures["prior_vs_tracked_abs_rel_near_change"]) > 0.0
    # The shipped row's stream follows config/config.yaml (the threshold grows with depth).
    assert figures["noise_with_depth"] == "True"
    assert all(number(figures[f"stream_update_{m}_fps"]) > 0 for m in modes)


def test_bench_change_bounds_next_surface_and_figures_against_closed_forms() -> None:
    """The next surface behind a layer is the far slab's face; each figure of a frame with
    a known change takes the value worked out by hand."""
    import trimesh

    from chisel.core.geometry import Camera
    from chisel.core.raycast import SurfaceQueries

    bench = load_benchmark("bench_change_bounds")
    near_slab = trimesh.creation.box(bounds=[[-50, -50, 10], [50, 50, 12]])
    far_slab = trimesh.creation.box(bounds=[[-50, -50, 20], [50, 50, 25]])
    surface = SurfaceQueries.from_trimesh(trimesh.util.concatenate([near_slab, far_slab]))
    camera = Camera(width=32, height=24, K=np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]))
    z = bench.next_surface_depth(surface, camera.rays_cam(), np.eye(4))
    np.testing.assert_allclose(z, 20.0, atol=1e-3)  # z-depth of the far slab's face
    alone = SurfaceQueries.from_trimesh(near_slab)
    assert np.all(np.isnan(bench.next_surface_depth(alone, camera.rays_cam(), np.eye(4))))

    # A 40x40 frame at 10 mm; a 10x10 window opened to 20 mm (the target at the tracked
    # pose); the image shows the window shifted by 2 px (the tracking error).
    prior = np.full((40, 40), 10.0, np.float32)
    target = prior.copy()
    target[15:25, 15:25] = 20.0
    image = prior.copy()
    image[15:25, 17:27] = 20.0
    nxt = np.full((40, 40), 20.0, np.float32)
    label, label_true = target > prior + 1.0, image > prior + 1.0
    f = bench.frame_figures(prior, nxt, target, image, label, label_true)
    near = 26 * 26  # the window dilated by 8 px
    assert f["label_iou_tracked_true"] == pytest.approx(80 / 120)
    assert f["label_recall_true_of_tracked"] == pytest.approx(0.8)
    assert f["next_layer_within_0p5mm"] == 1.0
    assert f["prior_near_abs_rel"] == pytest.approx(100 * 0.5 / near)
    # 20 pixels too deep (10/10 off) and 20 too shallow (10/20 off) near the window.
    assert f["image_exact_near_abs_rel"] == pytest.approx((20 * 1.0 + 20 * 0.5) / near)
    assert f["next_layer_where_changed_near_abs_rel"] == 0.0
    assert f["next_layer_best_near_abs_rel"] == 0.0


def test_bench_shading_alignment_parallax_depth_and_misalignment_in_closed_form() -> None:
    """The parallax depth is the depth of the pattern's structure; a sideways translation
    t of a view of a plane at z misaligns it by f t / z pixels."""
    from chisel.core.geometry import Camera

    bench = load_benchmark("bench_shading_alignment")
    rng = np.random.default_rng(1)
    z = np.full((48, 64), 8.0)
    z[:, 32:] = 20.0
    pattern = np.full(z.shape, 0.3)
    # Structure only at 20 mm, two columns inside it so that its edge lies there too.
    pattern[:, 34:] = rng.normal(size=(48, 30))
    inv = bench.parallax_inverse_depth(pattern, np.ones(z.shape, bool), z)
    np.testing.assert_allclose(inv, [1 / 20, 1 / 20], rtol=1e-12)
    stripes = np.tile(np.sin(np.arange(64) / 2.0), (48, 1))  # no structure along y
    assert bench.parallax_inverse_depth(stripes, np.ones(z.shape, bool), z) is None

    cam = Camera.from_fov(64, 48, 70)
    plane = np.full((48, 64), 12.0)
    T = np.eye(4)
    T[0, 3] = 0.3
    assert bench.misalignment_px(plane, cam, np.eye(4), T) == pytest.approx(cam.fx * 0.3 / 12)
    assert bench.misalignment_px(plane, cam, np.eye(4), np.eye(4)) == pytest.approx(0.0)
    assert math.isnan(bench.misalignment_px(np.full((48, 64), np.nan), cam, np.eye(4), T))

    # Through a distorting lens (the simulator's k1 = -0.18): no move, no misalignment;
    # a sideways move displaces each pixel as OpenCV's own projection of its point does.
    import cv2

    lens = Camera(64, 48, cam.K, np.array([-0.18, 0.04, 4e-4, -3e-4, 0.0]))
    assert bench.misalignment_px(plane, lens, np.eye(4), np.eye(4)) == pytest.approx(0.0, abs=1e-6)
    P = lens.backproject(plane.astype(np.float32)).reshape(-1, 3)
    uv, _ = cv2.projectPoints(P - [0.3, 0.0, 0.0], np.zeros(3), np.zeros(3), lens.K, lens.dist)
    u, v = np.meshgrid(np.arange(64.0), np.arange(48.0))
    moved = np.hypot(uv[:, 0, 0] - u.ravel(), uv[:, 0, 1] - v.ravel())
    assert bench.misalignment_px(plane, lens, np.eye(4), T) == pytest.approx(np.median(moved))
