"""Bad inputs and faults: each entry of docs/bad-inputs.md has its test here.

Every test checks the exception class, that the message names the file or argument,
and (where something is written) that earlier output is left as it was.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from test_import_scene import (
    FIELD_STOP,
    RAW_CAMERA,
    make_scene,
    write_images,
    write_matrix_rows,
    write_tum,
    write_video,
)

from chisel.cli import main as chisel_main
from chisel.core.errors import (
    CameraError,
    DepthUnitsError,
    EmptyResultError,
    FormatVersionError,
    InvalidInputError,
    OutputError,
    PoseError,
)
from chisel.core.geometry import Camera
from chisel.io.calibration import read_calibration, write_opencv_calibration
from chisel.io.import_common import load_npy
from chisel.io.import_frames import FrameConfig, FrameFiles, import_images, import_video
from chisel.io.import_poses import PoseConfig, read_pose_file
from chisel.io.import_reference import import_reference
from chisel.io.sequence import Sequence, write_sequence

REPO = Path(__file__).resolve().parents[1]
NO_STOP = FrameConfig(field_stop="none")


@pytest.fixture(scope="module")
def scene():
    return make_scene(6)


@pytest.fixture()
def data(scene, tmp_path):
    """A good image-folder dataset; tests break one part of it."""
    write_images(tmp_path / "rgb", scene.raw_rgb)
    write_matrix_rows(tmp_path / "poses.txt", scene.poses)
    write_opencv_calibration(tmp_path / "calib.yaml", RAW_CAMERA)
    return tmp_path


def run_images(d: Path, **kw):
    kw.setdefault("frame_cfg", NO_STOP)
    return import_images(d / "rgb", d / "poses.txt", d / "calib.yaml", d / "seq", **kw)


# ------------------------------------------------------------------------------ units


def test_depth_in_metres(scene, data) -> None:
    (data / "depth").mkdir()
    for i, d in enumerate(scene.raw_depth):
        np.save(data / "depth" / f"{i}.npy", np.nan_to_num(d) / 1000.0)
    with pytest.raises(DepthUnitsError, match=r"depth[/\\]0\.npy.*metres"):
        run_images(data, files=FrameFiles(depth_dir=data / "depth"))
    assert not (data / "seq").exists()
    run_images(
        data,
        files=FrameFiles(depth_dir=data / "depth"),
        frame_cfg=FrameConfig(field_stop="none", depth_scale_mm=1000.0),
    )
    assert Sequence(data / "seq").has_depth


def test_translations_in_metres_declared_mm(scene, data) -> None:
    write_matrix_rows(data / "poses.txt", scene.poses, scale=1e-3)
    with pytest.raises(PoseError, match=r"poses\.txt.*look like metres.*--pose-units m"):
        run_images(data)
    run_images(data, pose_cfg=PoseConfig(units="m"))
    np.testing.assert_allclose(Sequence(data / "seq").poses, scene.poses, atol=1e-9)


def test_translations_in_mm_declared_metres(data) -> None:
    with pytest.raises(PoseError, match=r"poses\.txt.*look like millimetres"):
        run_images(data, pose_cfg=PoseConfig(units="m"))


# ----------------------------------------------------------------------------- counts


def test_more_frames_than_poses(scene, data) -> None:
    write_matrix_rows(data / "poses.txt", scene.poses[:5])
    with pytest.raises(PoseError, match=r"rgb: has more frames than .*poses\.txt has poses \(5\)"):
        run_images(data)


def test_fewer_frames_than_poses(scene, data) -> None:
    P = np.concatenate([scene.poses, scene.poses[:1]])
    write_matrix_rows(data / "poses.txt", P)
    with pytest.raises(PoseError, match=r"rgb: has 6 frames but .*poses\.txt has 7 poses"):
        run_images(data)


def test_video_shorter_than_its_pose_file(scene, data) -> None:
    write_video(data / "v.avi", scene.raw_rgb[:4])
    (data / "seq").mkdir()  # an earlier output (it has a sequence.json)
    (data / "seq" / "sequence.json").write_text("{}")
    (data / "seq" / "old.txt").write_text("keep")
    with pytest.raises(
        PoseError, match=r"v\.avi: has 4 frames but .*poses\.txt has 6 poses \(a truncated video"
    ):
        import_video(
            data / "v.avi", data / "poses.txt", data / "calib.yaml", data / "seq", frame_cfg=NO_STOP
        )
    assert (data / "seq" / "old.txt").read_text() == "keep"


def test_depth_folder_count_mismatch(scene, data) -> None:
    (data / "depth").mkdir()
    for i, d in enumerate(scene.raw_depth[:5]):
        np.save(data / "depth" / f"{i}.npy", np.nan_to_num(d))
    with pytest.raises(InvalidInputError, match=r"depth: has 5 files but .*rgb has 6 frames"):
        run_images(data, files=FrameFiles(depth_dir=data / "depth"))


def test_frame_time_count_mismatch(scene, data) -> None:
    write_tum(data / "t.txt", np.arange(6) / 10.0, scene.poses)
    (data / "times.csv").write_text(
        "frame,t\n" + "\n".join(f"{i},{i / 10.0}" for i in range(5)) + "\n"
    )
    with pytest.raises(
        InvalidInputError, match=r"times\.csv: has 5 frame times but .*rgb has more frames"
    ):
        import_images(
            data / "rgb",
            data / "t.txt",
            data / "calib.yaml",
            data / "seq",
            pose_cfg=PoseConfig(match="timestamp"),
            files=FrameFiles(frame_times_path=data / "times.csv"),
            frame_cfg=NO_STOP,
        )


# ------------------------------------------------------------------ corrupt / truncated


def _truncate(path: Path) -> None:
    b = path.read_bytes()
    path.write_bytes(b[: len(b) // 2])


def test_truncated_png(data) -> None:
    _truncate(data / "rgb" / "frame_3.png")
    with pytest.raises(InvalidInputError, match=r"frame_3\.png: truncated PNG"):
        run_images(data)


def test_truncated_jpeg_that_opencv_would_decode(scene, data) -> None:
    """OpenCV decodes a truncated JPEG with a grey fill and a warning only; we refuse it."""
    for p in (data / "rgb").iterdir():
        p.unlink()
    write_images(data / "rgb", scene.raw_rgb, ext="jpg")
    _truncate(data / "rgb" / "frame_2.jpg")
    assert cv2.imread(str(data / "rgb" / "frame_2.jpg")) is not None  # the trap
    with pytest.raises(InvalidInputError, match=r"frame_2\.jpg: truncated JPEG"):
        run_images(data)


def test_not_an_image(data) -> None:
    (data / "rgb" / "frame_1.png").unlink()
    (data / "rgb" / "frame_1.bmp").write_bytes(b"BM this is not a bitmap")
    with pytest.raises(InvalidInputError, match=r"frame_1\.bmp: cannot decode image"):
        run_images(data)


def test_corrupt_video(data) -> None:
    (data / "v.avi").write_bytes(os.urandom(4096))
    with pytest.raises(InvalidInputError, match=r"v\.avi: cannot open video"):
        import_video(data / "v.avi", data / "poses.txt", data / "calib.yaml", data / "seq")


def test_frames_of_different_sizes(scene, data) -> None:
    cv2.imwrite(str(data / "rgb" / "frame_4.png"), np.zeros((40, 48, 3), np.uint8))
    with pytest.raises(
        CameraError, match=r"frame 4: image is 48x40 \(WxH\) but the camera is 96x80"
    ):
        run_images(data)


# ------------------------------------------------------------------------------ poses


def test_nan_pose(scene, data) -> None:
    P = scene.poses.copy()
    P[3, 1, 2] = np.nan
    write_matrix_rows(data / "poses.txt", P)
    with pytest.raises(PoseError, match=r"poses\.txt: frame 3 of .*pose is NaN.*--drop-unposed"):
        run_images(data)
    assert not (data / "seq").exists()


def test_all_poses_nan(scene, data) -> None:
    write_matrix_rows(data / "poses.txt", np.full_like(scene.poses, np.nan))
    with pytest.raises(PoseError, match=r"poses\.txt: all 6 poses are NaN"):
        run_images(data)


def test_non_rigid_pose(scene, data) -> None:
    P = scene.poses.copy()
    P[2, :3, :3] *= 1.01  # a scaled rotation
    write_matrix_rows(data / "poses.txt", P)
    with pytest.raises(PoseError, match=r"poses\.txt: pose 2 is not rigid"):
        run_images(data)


def test_tum_quaternion_not_unit(tmp_path) -> None:
    (tmp_path / "t.txt").write_text("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0.5 0.5 0.5 0.2\n")
    with pytest.raises(PoseError, match=r"t\.txt:2: quaternion norm is 0\.8888, expected 1"):
        read_pose_file(tmp_path / "t.txt")


def test_pose_rows_of_different_lengths(tmp_path) -> None:
    (tmp_path / "p.txt").write_text(" ".join(["1"] * 16) + "\n" + " ".join(["1"] * 12) + "\n")
    with pytest.raises(
        PoseError, match=r"p\.txt:2: expected 16 numbers like the first row, got 12"
    ):
        read_pose_file(tmp_path / "p.txt")


def test_unknown_pose_layout(tmp_path) -> None:
    (tmp_path / "p.txt").write_text("1 2 3 4 5 6 7\n")
    with pytest.raises(PoseError, match=r"cannot tell the pose format from 7 columns"):
        read_pose_file(tmp_path / "p.txt")


def test_timestamp_matching_needs_timestamps(data) -> None:
    with pytest.raises(PoseError, match=r"poses\.txt: timestamp matching needs a TUM pose file"):
        run_images(data, pose_cfg=PoseConfig(match="timestamp", fps=10))


def test_no_frame_within_the_time_tolerance(scene, data) -> None:
    write_tum(data / "t.txt", 100.0 + np.arange(6) / 10.0, scene.poses)  # another clock
    with pytest.raises(
        PoseError, match=r"frame 0 of .*no valid pose within 0\.02 s of t = 0\.000000 s"
    ):
        import_images(
            data / "rgb",
            data / "t.txt",
            data / "calib.yaml",
            data / "seq",
            pose_cfg=PoseConfig(match="timestamp", fps=10),
            frame_cfg=NO_STOP,
        )
    with pytest.raises(PoseError, match=r"no selected frame of .* has a valid pose"):
        import_images(
            data / "rgb",
            data / "t.txt",
            data / "calib.yaml",
            data / "seq",
            pose_cfg=PoseConfig(match="timestamp", fps=10, drop_unposed=True),
            frame_cfg=NO_STOP,
        )


# ------------------------------------------------------------------------ calibration


def test_intrinsics_for_another_resolution(data) -> None:
    write_opencv_calibration(data / "calib.yaml", Camera.from_fov(192, 160, 100.0))
    with pytest.raises(
        CameraError,
        match=r"calib\.yaml: calibration is for 192x160 images but the frames are 96x80 \(pass rescale",
    ):
        run_images(data)
    write_opencv_calibration(data / "calib.yaml", Camera.from_fov(128, 80, 100.0))
    with pytest.raises(CameraError, match=r"different aspect ratio"):
        run_images(data)


def test_intrinsics_without_size_for_another_resolution(data) -> None:
    (data / "calib.json").write_text(json.dumps({"fx": 100, "fy": 100, "cx": 95.5, "cy": 79.5}))
    with pytest.raises(
        CameraError,
        match=r"calib\.json: principal point \(95\.5, 79\.5\) is far from the centre .* another resolution",
    ):
        import_images(data / "rgb", data / "poses.txt", data / "calib.json", data / "seq")


def test_unsupported_distortion_model(tmp_path) -> None:
    (tmp_path / "c.json").write_text(
        json.dumps(
            {"fx": 50, "fy": 50, "cx": 47.5, "cy": 39.5, "dist": [0.1, 0, 0, 0, 0, 0.3, 0, 0]}
        )
    )
    with pytest.raises(
        CameraError, match=r"c\.json: distortion has 8 coefficients with non-zero rational"
    ):
        read_calibration(tmp_path / "c.json")


def test_distortion_that_folds_over_or_is_absurd_is_refused(data) -> None:
    # k1 alone, barrel: the polynomial turns back inside the frame; a field stop that
    # keeps the frames' centre only makes the same lens usable.
    folds = Camera.from_fov(96, 80, 100.0, dist=np.array([-0.5, 0.0, 0.0, 0.0, 0.0]))
    write_opencv_calibration(data / "calib.yaml", folds)
    with pytest.raises(CameraError, match=r"calib\.yaml: the distortion model .* turns back"):
        run_images(data)
    assert not (data / "seq").exists()
    small_stop = FrameConfig(field_stop_circle=FIELD_STOP.__class__(47.5, 39.5, 20.0))
    run_images(data, frame_cfg=small_stop)
    assert Sequence(data / "seq").camera_mask is not None
    # A coefficient a million times too large (another normalisation) was accepted.
    absurd = Camera.from_fov(96, 80, 100.0, dist=np.array([1e6, 0.0, 0.0, 0.0, 0.0]))
    write_opencv_calibration(data / "calib.yaml", absurd)
    with pytest.raises(CameraError, match=r"calib\.yaml: .* scales image radii by"):
        run_images(data)


def test_calibration_without_camera_matrix(tmp_path) -> None:
    (tmp_path / "c.yaml").write_text("foo: 1\n")
    with pytest.raises(CameraError, match=r"c\.yaml: no camera matrix"):
        read_calibration(tmp_path / "c.yaml")
    with pytest.raises(CameraError, match=r"missing\.yaml: calibration file not found"):
        read_calibration(tmp_path / "missing.yaml")


# ----------------------------------------------------------------- masks and the ROI


def test_mask_of_wrong_size(scene, data) -> None:
    (data / "tools").mkdir()
    for i in range(6):
        cv2.imwrite(
            str(data / "tools" / f"{i}.png"), np.zeros((80, 96) if i != 2 else (40, 48), np.uint8)
        )
    with pytest.raises(CameraError, match=r"tools[/\\]2\.png: image is 48x40"):
        run_images(data, files=FrameFiles(mask_dir=data / "tools"))


def test_field_stop_that_keeps_nothing(data) -> None:
    with pytest.raises(InvalidInputError, match=r"camera mask keeps no pixel"):
        run_images(
            data, frame_cfg=FrameConfig(field_stop_circle=FIELD_STOP.__class__(-500.0, -500.0, 3.0))
        )


def test_empty_roi() -> None:
    from chisel.eval.metrics import RoiBox
    from chisel.eval.surface import sample_surface_in_box

    with pytest.raises(InvalidInputError, match=r"--roi: max corner .* must exceed min corner"):
        RoiBox.parse("0,0,0,10,-5,10")
    mesh = trimesh.creation.icosphere(2, radius=10.0)
    with pytest.raises(EmptyResultError, match=r"mesh: no surface inside the ROI box"):
        sample_surface_in_box(mesh, RoiBox.parse("100,100,100,110,110,110"), 100, seed=0)


# --------------------------------------------------------------- files from elsewhere


def test_pickled_npy_is_refused_with_a_way_out(tmp_path) -> None:
    np.save(
        tmp_path / "trajectories.npy",
        np.array([np.eye(4), np.eye(4)], dtype=object),
        allow_pickle=True,
    )
    with pytest.raises(
        InvalidInputError,
        match=r"trajectories\.npy: this \.npy holds Python objects .* np\.asarray\(arr, dtype=np\.float64\)",
    ):
        load_npy(tmp_path / "trajectories.npy")


def test_reference_layout_errors(scene, tmp_path) -> None:
    root = tmp_path / "ds"
    (root / "preop" / "images").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(root / "preop" / "images" / f"{i:06d}.jpg"), scene.raw_rgb[i])
    cv2.imwrite(str(root / "preop" / "undistorted_mask.bmp"), np.full((80, 96), 255, np.uint8))
    np.save(
        root / "preop" / "trajectories.npy",
        np.array(list(scene.poses[:3]), dtype=object),
        allow_pickle=True,
    )
    args = {"intrinsics": "52,52,47.5,39.5", "preop_data": {"base_dir": "preop"}, "steps": 0}
    (root / "input.json").write_text(json.dumps(args))
    with pytest.raises(
        InvalidInputError, match=r"trajectories\.npy: this \.npy holds Python objects"
    ):
        import_reference(root / "input.json", tmp_path / "out")
    np.save(root / "preop" / "trajectories.npy", scene.poses[:2])
    with pytest.raises(PoseError, match=r"trajectories\.npy: 2 poses but 3 images"):
        import_reference(root / "input.json", tmp_path / "out")
    np.save(root / "preop" / "trajectories.npy", scene.poses[:3])
    args["steps"] = 1
    (root / "input.json").write_text(json.dumps(args))
    with pytest.raises(
        InvalidInputError, match=r"input\.json: steps = 1 but there is no '1' entry"
    ):
        import_reference(root / "input.json", tmp_path / "out")
    args["steps"] = 0
    args["intrinsics"] = "52,52,47.5"
    (root / "input.json").write_text(json.dumps(args))
    with pytest.raises(CameraError, match=r"input\.json: intrinsics must be 4 numbers"):
        import_reference(root / "input.json", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_sequence_from_another_version(scene, tmp_path) -> None:
    from chisel.io.sequence import Frame

    write_sequence(tmp_path / "seq", RAW_CAMERA, [Frame(0, scene.poses[0])])
    header = json.loads((tmp_path / "seq" / "sequence.json").read_text())
    header["version"] = 2
    (tmp_path / "seq" / "sequence.json").write_text(json.dumps(header))
    with pytest.raises(
        FormatVersionError, match=r"sequence\.json: sequence version 2; this reader reads version 1"
    ):
        Sequence(tmp_path / "seq")


def test_model_from_another_version(tmp_path) -> None:
    from chisel.model import TsdfModel

    model = TsdfModel.empty([0, 0, 0], [4, 4, 4], 1.0, 2.0)
    model.save(tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz", allow_pickle=False) as z:
        fields = {k: z[k] for k in z.files}
    fields["version"] = np.array(99, dtype=np.int64)
    np.savez(tmp_path / "m2.npz", **fields)
    with pytest.raises(
        FormatVersionError, match=r"m2\.npz: model version 99; this reader reads version 1"
    ):
        TsdfModel.load(tmp_path / "m2.npz")


def test_ct_mesh_that_is_not_closed(tmp_path) -> None:
    """An open CT surface (cropped segmentation) is accepted: the preoperative model is
    fused from depth rendered off the surface, which needs no closed mesh. Only what the
    mesh has is modelled; looking through a hole sees nothing there."""
    from chisel.build import BuildConfig, build_preop_model
    from chisel.core.geometry import look_at
    from chisel.io.ct import load_ct_surface

    sphere = trimesh.creation.icosphere(3, radius=20.0)
    keep = sphere.triangles_center[:, 2] < 8.0  # cut a cap off: an open bowl
    open_mesh = trimesh.Trimesh(sphere.vertices, sphere.faces[keep])
    assert not open_mesh.is_watertight
    open_mesh.export(tmp_path / "open.ply")
    mesh = load_ct_surface(tmp_path / "open.ply")
    assert len(mesh.faces) == keep.sum()
    cam = Camera.from_fov(32, 24, 90.0)
    poses = np.stack([look_at([x, 0, 0], [x, 0, -20], up=[0, 1, 0]) for x in (-2.0, 0.0, 2.0)])
    model = build_preop_model(mesh, cam, poses, BuildConfig(voxel_size_mm=1.0, trunc_mm=3.0))
    assert (model.weight > 0).any() and np.isfinite(model.tsdf).all()
    up = np.stack([look_at([0, 0, 0], [0, 0, 20], up=[0, 1, 0])])  # through the hole
    with pytest.raises(EmptyResultError, match=r"not visible from any preoperative pose"):
        build_preop_model(mesh, cam, up, BuildConfig(voxel_size_mm=1.0, trunc_mm=3.0))


# ---------------------------------------------------------------------------- faults


def test_unwritable_output_parent_is_a_file(data) -> None:
    (data / "blocker").write_text("a file, not a folder")
    with pytest.raises(InvalidInputError, match=r"cannot create output folder"):
        import_images(
            data / "rgb",
            data / "poses.txt",
            data / "calib.yaml",
            data / "blocker" / "seq",
            frame_cfg=NO_STOP,
        )
    assert (data / "blocker").read_text() == "a file, not a folder"


@pytest.mark.skipif(
    os.name != "posix" or os.geteuid() == 0, reason="root ignores folder permissions"
)
def test_read_only_output_folder(data) -> None:
    run_images(data)
    before = (data / "seq" / "poses.txt").read_bytes()
    os.chmod(data, 0o555)
    try:
        with pytest.raises(InvalidInputError, match=r"is not writable"):
            run_images(data)
    finally:
        os.chmod(data, 0o755)
    assert (data / "seq" / "poses.txt").read_bytes() == before


@pytest.mark.parametrize("where", ["np.save", "cv2.imwrite"])
def test_disk_full_keeps_the_previous_output(scene, data, monkeypatch, where) -> None:
    """ENOSPC in the middle of writing: OutputError (an OSError with errno ENOSPC), the
    earlier sequence intact, no temporary folder left behind."""
    (data / "depth").mkdir()
    for i, d in enumerate(scene.raw_depth):
        np.save(data / "depth" / f"{i}.npy", np.nan_to_num(d))
    run_images(data, files=FrameFiles(depth_dir=data / "depth"))
    before = {
        p.relative_to(data / "seq"): p.read_bytes()
        for p in (data / "seq").rglob("*")
        if p.is_file()
    }
    import chisel.io.sequence as seqmod

    calls = {"n": 0}
    if where == "np.save":
        real = np.save

        def full(*a, **k):
            calls["n"] += 1
            if calls["n"] == 4:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(*a, **k)

        monkeypatch.setattr(seqmod.np, "save", full)
    else:
        real_imwrite = cv2.imwrite

        def full_imwrite(path, img, *a):
            calls["n"] += 1
            return False if calls["n"] == 3 else real_imwrite(path, img, *a)  # OpenCV's way

        monkeypatch.setattr(seqmod.cv2, "imwrite", full_imwrite)
    with pytest.raises(OutputError, match=r"seq: cannot write output") as exc:
        run_images(data, files=FrameFiles(depth_dir=data / "depth"))
    assert isinstance(exc.value, OSError)
    if where == "np.save":
        assert exc.value.errno == errno.ENOSPC
    monkeypatch.undo()
    after = {
        p.relative_to(data / "seq"): p.read_bytes()
        for p in (data / "seq").rglob("*")
        if p.is_file()
    }
    assert after == before
    assert [p.name for p in data.iterdir() if p.name.startswith(".seq")] == []


def test_cli_turns_disk_full_into_an_error_message(data, monkeypatch, capsys) -> None:
    import chisel.io.sequence as seqmod

    argv = [
        "import",
        "images",
        str(data / "rgb"),
        "--poses",
        str(data / "poses.txt"),
        "--calib",
        str(data / "calib.yaml"),
        "--out",
        str(data / "seq"),
        "--field-stop",
        "none",
    ]
    assert chisel_main(argv) == 0
    monkeypatch.setattr(seqmod.cv2, "imwrite", lambda *a, **k: False)  # OpenCV on a full disk
    assert chisel_main(argv) == 1
    err = capsys.readouterr().err
    assert "chisel import: error:" in err and "seq: cannot write output" in err
    monkeypatch.undo()
    assert len(Sequence(data / "seq")) == 6  # the first import is intact


def _wait_for(predicate, timeout_s: float) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_import_killed_mid_write_keeps_the_previous_sequence(scene, tmp_path) -> None:
    """SIGKILL while ``chisel import`` writes frames: the earlier sequence stays readable
    and unchanged; rerunning the import then replaces it."""
    frames = [scene.raw_rgb[i % 6] for i in range(240)]
    write_images(tmp_path / "rgb", frames)
    write_matrix_rows(tmp_path / "p.txt", np.stack([scene.poses[i % 6] for i in range(240)]))
    write_opencv_calibration(tmp_path / "c.yaml", RAW_CAMERA)
    write_images(tmp_path / "rgb_old", scene.raw_rgb)
    write_matrix_rows(tmp_path / "p_old.txt", scene.poses)
    import_images(
        tmp_path / "rgb_old",
        tmp_path / "p_old.txt",
        tmp_path / "c.yaml",
        tmp_path / "seq",
        frame_cfg=NO_STOP,
    )
    before = (tmp_path / "seq" / "poses.txt").read_bytes()
    cmd = [
        sys.executable,
        "-m",
        "chisel",
        "import",
        "images",
        str(tmp_path / "rgb"),
        "--poses",
        str(tmp_path / "p.txt"),
        "--calib",
        str(tmp_path / "c.yaml"),
        "--out",
        str(tmp_path / "seq"),
        "--field-stop",
        "none",
    ]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:

        def writing() -> bool:
            tmps = list(tmp_path.glob(".seq.tmp-*/rgb/*.png"))
            return len(tmps) >= 5

        assert _wait_for(writing, 60.0), "the import never started writing"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    seq = Sequence(tmp_path / "seq")
    assert len(seq) == 6 and (tmp_path / "seq" / "poses.txt").read_bytes() == before
    seq.rgb(5)
    # Rerun: completes and replaces the old sequence (the killed run's hidden temp folder
    # is left behind; it is safe to delete).
    assert subprocess.run(cmd, cwd=REPO, capture_output=True).returncode == 0
    assert len(Sequence(tmp_path / "seq")) == 240


def test_calibration_that_is_binary_or_holds_text_is_one_camera_error(tmp_path: Path) -> None:
    binary = tmp_path / "calib.yaml"
    binary.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(CameraError, match="not a text file") as info:
        read_calibration(binary)
    assert info.value.source == str(binary)
    text_k = tmp_path / "calib.json"
    text_k.write_text('{"K": [[1, "a", 0], [0, 1, 0], [0, 0, 1]], "dist": [0, 0, 0, 0, 0]}')
    with pytest.raises(CameraError, match="camera matrix must be numbers"):
        read_calibration(text_k)
