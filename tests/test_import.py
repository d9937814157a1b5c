"""Importers: foreign-format data built from a synthetic scene come back as its truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_import_scene import (
    FIELD_STOP,
    HAND_EYE,
    RAW_CAMERA,
    WORLD_FROM_TRACKER,
    make_scene,
    shade,
    tracker_poses,
    write_images,
    write_matrix_rows,
    write_tum,
    write_video,
)

from chisel.cli import main as chisel_main
from chisel.core.errors import InvalidInputError, PoseError
from chisel.core.geometry import Camera, make_transform, rotation_angle_deg
from chisel.io.calibration import read_calibration, write_opencv_calibration
from chisel.io.import_frames import FrameConfig, FrameFiles, import_images, import_video
from chisel.io.import_poses import PoseConfig, match_poses_by_time, read_pose_file
from chisel.io.import_reference import import_reference
from chisel.io.sequence import Sequence
from chisel.io.undistort import circle_mask, make_undistortion


@pytest.fixture(scope="module")
def scene():
    return make_scene(6)


def _interior(camera_mask: np.ndarray, px: int = 2) -> np.ndarray:
    """The mask eroded by ``px`` pixels: away from the field-stop rim."""
    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.erode(camera_mask.astype(np.uint8), k) > 0


def test_video_tum_timestamps_metres_undistorted(scene, tmp_path) -> None:
    """Video (MJPG) + TUM in metres matched by timestamp -> the scene in mm, undistorted."""
    n = len(scene.poses)
    write_video(tmp_path / "endo.avi", scene.raw_rgb, fps=10.0)
    # Pose samples at 50 Hz on the tracker clock, shifted from the video by 1.3 s; only
    # the samples at frame times carry the frames' true poses (others are NaN = lost).
    frame_t = 1.3 + np.arange(n) / 10.0
    times = np.sort(np.concatenate([frame_t, frame_t + 0.02, frame_t - 0.04]))
    P = np.full((len(times), 4, 4), np.nan)
    for i, t in enumerate(frame_t):
        P[np.argmin(np.abs(times - t))] = scene.poses[i]
    write_tum(tmp_path / "traj.tum", times, P, scale=1e-3)
    write_opencv_calibration(tmp_path / "calib.yaml", RAW_CAMERA)
    depth_dir = tmp_path / "depth"
    depth_dir.mkdir()
    for i, d in enumerate(scene.raw_depth):
        np.save(depth_dir / f"{i}.npy", np.nan_to_num(d, nan=0.0).astype(np.float32))

    report = import_video(
        tmp_path / "endo.avi",
        tmp_path / "traj.tum",
        tmp_path / "calib.yaml",
        tmp_path / "seq",
        pose_cfg=PoseConfig(
            units="m", match="timestamp", frame_time_offset_s=1.3, time_tolerance_s=0.005
        ),
        files=FrameFiles(depth_dir=depth_dir),
    )
    seq = Sequence(tmp_path / "seq")
    assert report.num_frames == len(seq) == n and seq.undistorted and not seq.camera.has_distortion
    np.testing.assert_allclose(seq.poses, scene.poses, atol=1e-6)  # mm; m->mm and quaternions
    # The fitted field stop is the drawn one (sub-pixel).
    c = report.field_stop
    assert (
        abs(c.cx - FIELD_STOP.cx) < 0.5
        and abs(c.cy - FIELD_STOP.cy) < 0.5
        and abs(c.r - FIELD_STOP.r) < 0.6
    )
    # Independent truth: render the scene directly with the new pinhole camera.
    und = make_undistortion(RAW_CAMERA)
    np.testing.assert_allclose(seq.camera.K, und.camera.K)
    inner = _interior(seq.camera_mask, 2)
    assert inner.sum() > 0.3 * inner.size
    for i in range(n):
        rgb_true, depth_true = shade(scene.raycaster, seq.camera, scene.poses[i])
        diff = np.abs(seq.rgb(i).astype(float) - rgb_true.astype(float))[inner]
        assert diff.mean() < 6.0, diff.mean()  # MJPG + bilinear resampling
        depth = seq.depth_mm(i)
        assert np.isfinite(depth[inner]).all()
        err = np.abs(depth - depth_true)[inner]
        # Nearest resampling: ~0.08 / 0.23 mm here; the camera shifted by 0.5 px gives 0.12 / 0.38.
        assert np.median(err) < 0.1 and np.percentile(err, 95) < 0.3
    # Outside the camera mask there is nothing.
    assert seq.mask(0) is not None and not seq.mask(0)[~seq.camera_mask].any()


def test_images_hand_eye_index_no_undistort(scene, tmp_path) -> None:
    """Image folder + N x 16 tracker poses + hand-eye + registration, raw frames kept."""
    P = tracker_poses(scene.poses, WORLD_FROM_TRACKER, HAND_EYE)
    write_matrix_rows(tmp_path / "poses.txt", P)
    np.savetxt(tmp_path / "hand_eye.txt", HAND_EYE)
    np.save(tmp_path / "reg.npy", WORLD_FROM_TRACKER)
    (tmp_path / "calib.json").write_text(json.dumps(RAW_CAMERA.to_dict()))
    write_images(tmp_path / "frames", scene.raw_rgb)
    rc = chisel_main(
        [
            "import",
            "images",
            str(tmp_path / "frames"),
            "--poses",
            str(tmp_path / "poses.txt"),
            "--calib",
            str(tmp_path / "calib.json"),
            "--out",
            str(tmp_path / "seq"),
            "--hand-eye",
            str(tmp_path / "hand_eye.txt"),
            "--world-from-tracker",
            str(tmp_path / "reg.npy"),
            "--no-undistort",
            "--field-stop-circle",
            f"{FIELD_STOP.cx},{FIELD_STOP.cy},{FIELD_STOP.r}",
            "--mask-margin-px",
            "0",
        ]
    )
    assert rc == 0
    seq = Sequence(tmp_path / "seq")
    np.testing.assert_allclose(seq.poses, scene.poses, atol=1e-9)
    np.testing.assert_array_equal(seq.camera.dist, RAW_CAMERA.dist)
    assert not seq.undistorted
    for i in range(len(seq)):
        np.testing.assert_array_equal(seq.rgb(i), scene.raw_rgb[i])  # PNG is lossless
    np.testing.assert_array_equal(seq.camera_mask, circle_mask(RAW_CAMERA.shape, FIELD_STOP))


def test_undistortion_moves_a_point_where_the_pinhole_camera_projects_it() -> None:
    """A blob drawn at the distorted projection lands at the new camera's projection."""
    und = make_undistortion(RAW_CAMERA)
    rng = np.random.default_rng(3)
    for _ in range(5):
        X = np.array([*rng.uniform(-6, 6, 2), rng.uniform(12, 20)])
        uv_raw = RAW_CAMERA.project(X)[0]
        uv_new = und.camera.project(X)[0]
        if not (6 < uv_new[0] < 90 and 6 < uv_new[1] < 74):
            continue
        u, v = RAW_CAMERA.pixel_grid()
        blob = np.exp(-((u - uv_raw[0]) ** 2 + (v - uv_raw[1]) ** 2) / (2 * 1.2**2))
        img = np.repeat((255 * blob)[..., None], 3, axis=2).astype(np.uint8)
        out = und.image(img)[..., 0].astype(float)
        out[out < 20] = 0
        uu, vv = und.camera.pixel_grid()
        centroid = np.array([(uu * out).sum(), (vv * out).sum()]) / out.sum()
        assert np.linalg.norm(centroid - uv_new) < 0.3, (centroid, uv_new)
        np.testing.assert_allclose(und.points_to_undistorted(uv_raw[None])[0], uv_new, atol=1e-6)
        np.testing.assert_allclose(und.points_to_raw(uv_new[None])[0], uv_raw, atol=1e-6)


def test_slerp_and_nearest_matching() -> None:
    R0 = np.eye(3)
    R1 = Rotation.from_euler("z", 20, degrees=True).as_matrix()
    P = np.stack([make_transform(R0, [0, 0, 0]), make_transform(R1, [4, 0, 0])])
    t = np.array([10.0, 10.1])
    out = match_poses_by_time(t, P, np.array([10.025, 10.0, 10.1, 10.05, 9.9]), 0.08, "slerp")
    assert rotation_angle_deg(out[0, :3, :3]) == pytest.approx(5.0, abs=1e-9)
    np.testing.assert_allclose(out[0, :3, 3], [1.0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(out[1], P[0])
    np.testing.assert_allclose(out[2], P[1])
    assert rotation_angle_deg(out[3, :3, :3]) == pytest.approx(10.0, abs=1e-9)
    assert np.isnan(out[4]).all()  # before the first sample: nothing to interpolate
    # Gap wider than 2 x tolerance: no interpolation.
    assert np.isnan(match_poses_by_time(t, P, np.array([10.05]), 0.04, "slerp")).all()
    near = match_poses_by_time(t, P, np.array([10.03, 10.07, 10.2]), 0.035, "nearest")
    np.testing.assert_allclose(near[0], P[0])
    np.testing.assert_allclose(near[1], P[1])
    assert np.isnan(near[2]).all()
    # A NaN sample is skipped: the nearest *valid* one within tolerance wins.
    Pn = P.copy()
    Pn[1] = np.nan
    assert np.isnan(match_poses_by_time(t, Pn, np.array([10.09]), 0.05, "nearest")).all()
    np.testing.assert_allclose(match_poses_by_time(t, Pn, np.array([10.04]), 0.05)[0], P[0])
    with pytest.raises(PoseError, match="increase"):
        match_poses_by_time(t[::-1], P, np.array([10.0]), 0.1)


def test_video_slerp_between_samples(scene, tmp_path) -> None:
    """Frames halfway between two pose samples get the SLERP of the two."""
    n = 4
    write_video(tmp_path / "v.avi", scene.raw_rgb[:n], fps=5.0)
    write_opencv_calibration(tmp_path / "c.xml", RAW_CAMERA)
    R = make_transform(Rotation.from_euler("y", 8, degrees=True).as_matrix(), [0.0, 0.0, 0.0])
    S = make_transform(np.eye(3), [0.5, -1.0, 2.0])
    times, samples = [], []
    for i in range(n):  # a sample 10 ms before and after each frame time
        times += [i / 5.0 - 0.01, i / 5.0 + 0.01]
        samples += [np.linalg.inv(S) @ scene.poses[i] @ R.T, S @ scene.poses[i] @ R]
    write_tum(tmp_path / "t.txt", np.array(times), np.stack(samples))
    import_video(
        tmp_path / "v.avi",
        tmp_path / "t.txt",
        tmp_path / "c.xml",
        tmp_path / "seq",
        pose_cfg=PoseConfig(match="timestamp", interpolation="slerp", time_tolerance_s=0.011),
        frame_cfg=FrameConfig(field_stop="none"),
    )
    # Halfway between S^-1 T R^-1 and S T R (R a rotation, S a shift) is T itself.
    np.testing.assert_allclose(Sequence(tmp_path / "seq").poses, scene.poses[:n], atol=1e-9)


def test_pose_file_formats_agree(scene, tmp_path) -> None:
    P = scene.poses
    write_matrix_rows(tmp_path / "rows.txt", P)
    (tmp_path / "blocks.txt").write_text(
        "# blocks of 4 rows\n"
        + "\n\n".join("\n".join(",".join(f"{v:.17g}" for v in r) for r in T) for T in P)
    )
    np.save(tmp_path / "poses.npy", P)
    write_tum(tmp_path / "tum.txt", np.arange(len(P), dtype=float), P)
    for name in ("rows.txt", "blocks.txt", "poses.npy"):
        np.testing.assert_array_equal(read_pose_file(tmp_path / name).poses, P)
    tum = read_pose_file(tmp_path / "tum.txt")
    np.testing.assert_allclose(tum.poses, P, atol=1e-12)
    np.testing.assert_array_equal(tum.timestamps_s, np.arange(len(P)))
    assert read_pose_file(tmp_path / "rows.txt").timestamps_s is None


def test_calibration_formats_agree(tmp_path) -> None:
    write_opencv_calibration(tmp_path / "c.yaml", RAW_CAMERA)
    write_opencv_calibration(tmp_path / "c.xml", RAW_CAMERA)
    K, d = RAW_CAMERA.K, RAW_CAMERA.dist
    (tmp_path / "ros.yaml").write_text(
        "image_width: 96\nimage_height: 80\ncamera_name: endo\n"
        f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {K.ravel().tolist()}\n"
        f"distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: {d.tolist()}\n"
    )
    (tmp_path / "c.json").write_text(
        json.dumps(
            {
                "fx": K[0, 0],
                "fy": K[1, 1],
                "cx": K[0, 2],
                "cy": K[1, 2],
                "dist": d[:4].tolist(),
                "width": 96,
                "height": 80,
            }
        )
    )
    for name in ("c.yaml", "c.xml", "ros.yaml", "c.json"):
        cam = read_calibration(tmp_path / name).camera_for(96, 80)
        np.testing.assert_allclose(cam.K, K, rtol=1e-12)
        np.testing.assert_allclose(cam.dist, d if name != "c.json" else [*d[:4], 0.0])
    # Same aspect ratio at twice the resolution: scaled about pixel-centre conventions.
    cam2 = read_calibration(tmp_path / "c.yaml").camera_for(192, 160, rescale=True)
    assert cam2.fx == pytest.approx(2 * RAW_CAMERA.fx)
    assert cam2.cx == pytest.approx(2 * RAW_CAMERA.cx + 0.5)


def test_depth_png_scale_masks_and_frame_range(scene, tmp_path) -> None:
    """16-bit depth PNGs in 1/100 mm, tool masks to exclude, every 2nd frame from 1."""
    write_images(tmp_path / "rgb", scene.raw_rgb, ext="png")
    (tmp_path / "depth").mkdir()
    (tmp_path / "tools").mkdir()
    tool_masks = []
    for i, d in enumerate(scene.raw_depth):
        cv2.imwrite(
            str(tmp_path / "depth" / f"d{i:03d}.png"),
            np.rint(np.nan_to_num(d) * 100).astype(np.uint16),
        )
        tool = np.zeros(RAW_CAMERA.shape, np.uint8)
        tool[50:, 10 * i : 10 * i + 20] = 255  # a "tool" entering from the bottom
        tool_masks.append(tool > 0)
        cv2.imwrite(str(tmp_path / "tools" / f"m{i:03d}.png"), tool)
    write_matrix_rows(tmp_path / "p.txt", scene.poses)
    write_opencv_calibration(tmp_path / "c.yaml", RAW_CAMERA)
    report = import_images(
        tmp_path / "rgb",
        tmp_path / "p.txt",
        tmp_path / "c.yaml",
        tmp_path / "seq",
        frame_cfg=FrameConfig(
            undistort=False,
            depth_scale_mm=0.01,
            mask_invert=True,
            start=1,
            step=2,
            field_stop_circle=FIELD_STOP,
            mask_margin_px=0.0,
        ),
        files=FrameFiles(depth_dir=tmp_path / "depth", mask_dir=tmp_path / "tools"),
    )
    seq = Sequence(tmp_path / "seq")
    assert report.num_frames == len(seq) == 3 and seq.meta["source_frame_index"] == [1, 3, 5]
    stop = circle_mask(RAW_CAMERA.shape, FIELD_STOP)
    for k, i in enumerate([1, 3, 5]):
        np.testing.assert_array_equal(seq.poses[k], scene.poses[i])
        np.testing.assert_allclose(
            seq.depth_mm(k), scene.raw_depth[i], atol=0.006
        )  # 1/100 mm steps
        np.testing.assert_array_equal(seq.mask(k), stop & ~tool_masks[i])


def test_drop_unposed_frames(scene, tmp_path) -> None:
    P = scene.poses.copy()
    P[2] = np.nan  # tracking lost
    P[4, 0, 3] = np.inf  # a broken row: named as what it is, not as lost tracking
    write_matrix_rows(tmp_path / "p.txt", P)
    write_images(tmp_path / "rgb", scene.raw_rgb)
    write_opencv_calibration(tmp_path / "c.yaml", RAW_CAMERA)
    report = import_images(
        tmp_path / "rgb",
        tmp_path / "p.txt",
        tmp_path / "c.yaml",
        tmp_path / "seq",
        pose_cfg=PoseConfig(drop_unposed=True),
        frame_cfg=FrameConfig(field_stop="none"),
    )
    seq = Sequence(tmp_path / "seq")
    assert report.dropped == [(2, "pose is NaN (tracking lost)"), (4, "pose is inf")]
    assert seq.meta["source_frame_index"] == [0, 1, 3, 5]
    np.testing.assert_array_equal(seq.poses, scene.poses[[0, 1, 3, 5]])


def test_mask_margin_wider_than_the_field_stop_is_refused(scene, tmp_path) -> None:
    # A margin past the radius used to give a mask of radius |r - margin| (r * r > 0).
    write_matrix_rows(tmp_path / "p.txt", scene.poses)
    write_images(tmp_path / "rgb", scene.raw_rgb)
    write_opencv_calibration(tmp_path / "c.yaml", RAW_CAMERA)
    margin = FIELD_STOP.r + 5.0
    with pytest.raises(InvalidInputError, match="not less than the field stop's radius") as info:
        import_images(
            tmp_path / "rgb",
            tmp_path / "p.txt",
            tmp_path / "c.yaml",
            tmp_path / "seq",
            frame_cfg=FrameConfig(field_stop_circle=FIELD_STOP, mask_margin_px=margin),
        )
    assert info.value.source == "mask_margin_px"
    assert not (tmp_path / "seq").exists()
    assert not circle_mask(RAW_CAMERA.shape, FIELD_STOP, margin).any()


def _write_reference_part(base, scene, idx, mask, with_depth):
    (base / "images").mkdir(parents=True)
    for k, i in enumerate(idx):
        cv2.imwrite(
            str(base / "images" / f"{k:06d}.jpg"),
            cv2.cvtColor(scene.raw_rgb[i], cv2.COLOR_RGB2BGR),
            [cv2.IMWRITE_JPEG_QUALITY, 98],
        )
    np.save(base / "trajectories.npy", scene.poses[idx])
    cv2.imwrite(str(base / "undistorted_mask.bmp"), np.where(mask, 255, 0).astype(np.uint8))
    if with_depth:
        (base / "depths").mkdir()
        for k, i in enumerate(idx):
            np.save(base / "depths" / f"{k:06d}.npy", np.nan_to_num(scene.raw_depth[i]) * 0.5)


def test_reference_layout(scene, tmp_path) -> None:
    """The published code's input.json layout: preop + 2 steps -> 3 sequences + surfaces."""
    # The reference's frames are already undistorted pinhole images: use the scene's
    # pixels as such with a zero-distortion camera of the same K.
    cam = Camera(96, 80, RAW_CAMERA.K)
    mask = circle_mask(cam.shape, FIELD_STOP)
    root = tmp_path / "p04_left"
    parts = {
        "preop_data": ("preop", [0, 1, 2], False),
        "1": ("bite1", [2, 3], True),
        "2": ("bite2", [4, 5], True),
    }
    args = {
        "intrinsics": f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}",
        "data_dir": str(root),
        "steps": 2,
    }
    for key, (folder, idx, depth) in parts.items():
        _write_reference_part(root / folder, scene, idx, mask, depth)
        args[key] = {"base_dir": folder}
    args["preop_data"]["seg"] = "seg.ply"
    seg = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    seg.export(root / "preop" / "seg.ply")
    (root / "input.json").write_text(json.dumps(args))

    result = import_reference(
        root / "input.json", tmp_path / "out", with_depth=True, depth_scale_mm=2.0
    )
    assert [p.name for p in result.parts] == ["preop", "step_1", "step_2"]
    manifest = json.loads((tmp_path / "out" / "reference.json").read_text())
    assert manifest["parts"][0]["surface"] == "preop_surface.ply"
    # Parsed and written anew (never copied byte for byte): the same triangles.
    copied = trimesh.load(tmp_path / "out" / "preop_surface.ply", force="mesh", process=False)
    np.testing.assert_allclose(copied.vertices, seg.vertices)
    np.testing.assert_array_equal(copied.faces, seg.faces)
    for part, (_key, (_folder, idx, depth)) in zip(result.parts, parts.items(), strict=True):
        seq = Sequence(tmp_path / "out" / part.sequence)
        assert seq.undistorted and len(seq) == len(idx) and seq.has_depth == depth
        np.testing.assert_array_equal(seq.poses, scene.poses[idx])
        np.testing.assert_allclose(seq.camera.K, cam.K)
        np.testing.assert_array_equal(seq.camera_mask, mask)
        for k, i in enumerate(idx):
            assert (
                np.abs(seq.rgb(k).astype(float) - scene.raw_rgb[i])[mask].mean() < 3.0
            )  # JPEG q98
            if depth:
                np.testing.assert_allclose(seq.depth_mm(k), scene.raw_depth[i], rtol=1e-6)


def test_cli_help_explains_formats_and_units(capsys) -> None:
    for sub in ("video", "images", "reference"):
        with pytest.raises(SystemExit) as exc:
            chisel_main(["import", sub, "--help"])
        assert exc.value.code == 0
        out = capsys.readouterr().out
        assert "mm" in out
    with pytest.raises(SystemExit):
        chisel_main(["import", "video", "--help"])
    out = capsys.readouterr().out
    for word in ("TUM", "timestamp", "slerp", "--pose-units", "T_world_from_cam", "field stop"):
        assert word in out, word


def test_cli_reports_bad_input_and_keeps_output(scene, tmp_path, capsys) -> None:
    write_images(tmp_path / "rgb", scene.raw_rgb)
    write_matrix_rows(tmp_path / "p.txt", scene.poses[:-1])  # one pose short
    write_opencv_calibration(tmp_path / "c.yaml", RAW_CAMERA)
    (tmp_path / "seq").mkdir()  # an earlier output (it has a sequence.json)
    (tmp_path / "seq" / "sequence.json").write_text("{}")
    (tmp_path / "seq" / "keep.txt").write_text("earlier result")
    rc = chisel_main(
        [
            "import",
            "images",
            str(tmp_path / "rgb"),
            "--poses",
            str(tmp_path / "p.txt"),
            "--calib",
            str(tmp_path / "c.yaml"),
            "--out",
            str(tmp_path / "seq"),
        ]
    )
    assert rc == 1
    err = capsys.readouterr().err
    assert "chisel import: error:" in err and "more frames than" in err and "p.txt" in err
    assert (tmp_path / "seq" / "keep.txt").read_text() == "earlier result"
