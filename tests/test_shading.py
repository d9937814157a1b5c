"""Shading alignment: the log shading against the closed form for planes, the masked NCC
against scikit-image's implementation of the same (Padfield's), and a frame rendered at a
known pose pulled back onto it from a pose turned by a known angle."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from skimage.registration._masked_phase_cross_correlation import cross_correlate_masked

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera
from chisel.core.raycast import MeshRaycaster
from chisel.io.sequence import Frame
from chisel.shading import (
    DISPLAY_GAMMA,
    ShadingConfig,
    log_luminance,
    log_shading,
    masked_ncc,
    shading_shift,
    shading_translation,
    step_correction,
    translation_for_shift,
)


@pytest.mark.parametrize("normal", [[0.0, 0.0, -1.0], [0.3, -0.2, -1.0]])
def test_log_shading_of_a_plane_is_closed_form(normal: list[float]) -> None:
    # A light at the camera centre and a plane n . X = d: cos = d / |P|, so the log
    # shading is log(d) - 3 log|P| at every pixel whose neighbours see the plane too.
    cam = Camera.from_fov(64, 48, 70)
    n = np.asarray(normal) / np.linalg.norm(normal)
    d = 12.0
    rays = cam.rays_cam()
    # X = z * ray on the plane -n . X = d (the plane faces the camera)
    z = d / -(rays @ n)
    s, ok = log_shading(z.astype(np.float32), rays)
    P = z[..., None] * rays
    expected = np.log(d) - 3.0 * np.log(np.linalg.norm(P, axis=-1))
    assert ok[1:-1, 1:-1].all() and not ok[0].any() and not ok[:, -1].any()
    np.testing.assert_allclose(s[ok], expected[ok], atol=2e-4)


def test_log_shading_marks_pixels_beside_a_hole_invalid() -> None:
    cam = Camera.from_fov(32, 24, 70)
    z = np.full((24, 32), 10.0, np.float32)
    z[10, 12] = np.nan
    _, ok = log_shading(z, cam.rays_cam())
    assert not ok[9:12, 12].any() and not ok[10, 11:14].any()
    assert ok[5, 5] and ok[10, 20]


def test_masked_ncc_matches_scikit_image() -> None:
    rng = np.random.default_rng(3)
    H, W, S = 37, 52, 6
    a, b = rng.normal(size=(H, W)), rng.normal(size=(H, W))
    ma, mb = rng.random((H, W)) > 0.3, rng.random((H, W)) > 0.4
    ncc, n = masked_ncc(a, ma, b, mb, S)
    ref = cross_correlate_masked(a, b, ma, mb, mode="full", overlap_ratio=0.0)
    # scikit-image's index (H - 1 + k) pairs a(u) with b(u - k): ours is the flip.
    ref = ref[H - 1 - S : H + S, W - 1 - S : W + S][::-1, ::-1]
    # ours sums the values in single precision (scikit-image in double): 2e-8 here.
    np.testing.assert_allclose(ncc, ref, atol=2e-7)
    # the overlap of one shift, counted by hand
    dy, dx = 2, -3
    both = ma[: H - dy, -dx:] & mb[dy:, : W + dx]
    assert n[dy + S, dx + S] == both.sum()


def test_translation_for_shift_is_exact_at_its_depth() -> None:
    cam = Camera.from_fov(320, 256, 90)
    dx, dy, z = 7.0, -4.0, 11.0
    C = translation_for_shift(cam, dx, dy, z)
    np.testing.assert_allclose(C[:3, :3], np.eye(3))
    assert C[2, 3] == 0.0
    # a point at depth z that the old camera saw at (u + dx, v + dy) ...
    u, v = 100.0, 200.0
    X = z * np.linalg.solve(cam.K, [u + dx, v + dy, 1.0])
    # ... the corrected camera (T @ C) sees at (u, v)
    x_new = X - C[:3, 3]
    uv = cam.K @ (x_new / x_new[2])
    np.testing.assert_allclose(uv[:2], [u, v], atol=1e-9)


def _bumpy_surface() -> trimesh.Trimesh:
    # A wall with bumps of a few mm at ~14 mm: shading structure finer than the high pass.
    x, y = np.meshgrid(np.linspace(-30, 30, 241), np.linspace(-30, 30, 241))
    z = 14.0 + 1.2 * np.sin(x / 1.7) * np.cos(y / 2.3) + 0.8 * np.sin((x + 2 * y) / 3.1)
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    i = np.arange(240)[:, None] * 241 + np.arange(240)[None]
    faces = np.concatenate(
        [np.stack([i, i + 1, i + 241], -1), np.stack([i + 1, i + 242, i + 241], -1)]
    ).reshape(-1, 3)
    return trimesh.Trimesh(verts, faces, process=False)


def _frame_at(mesh: trimesh.Trimesh, cam: Camera, T: np.ndarray) -> np.ndarray:
    """8-bit frame of a matte surface lit from the lens, shaded with trimesh's own ray
    hits and face normals (not the depth map's normals that the alignment uses)."""
    d_cam = cam.rays_cam().reshape(-1, 3)
    d_world = d_cam @ T[:3, :3].T
    origins = np.broadcast_to(T[:3, 3], d_world.shape)
    loc, ray, tri = mesh.ray.intersects_location(origins, d_world, multiple_hits=False)
    radiance = np.zeros(len(d_cam))
    v = loc - T[:3, 3]
    r = np.linalg.norm(v, axis=1)
    cos = np.abs((mesh.face_normals[tri] * v).sum(1)) / r
    radiance[ray] = cos / r**2
    linear = radiance / radiance.max()
    return np.repeat((255 * linear ** (1 / DISPLAY_GAMMA)).reshape(cam.height, cam.width, 1), 3, -1)


def _shift(x_mm: float, y_mm: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, 3] = x_mm, y_mm
    return T


def test_a_shifted_pose_is_pulled_back_onto_the_frame() -> None:
    # The tracker's error at an endoscope's working distance, sideways by 0.4-0.5 mm
    # (5-7 px here): the frame's shading brings the camera back to within ~1 px.
    mesh = _bumpy_surface()
    cam = Camera.from_fov(160, 128, 80)
    T_true = np.eye(4)
    rgb = np.round(_frame_at(mesh, cam, T_true)).astype(np.uint8)
    rc = MeshRaycaster(mesh.vertices, mesh.faces)
    for error in (_shift(0.4, -0.3), _shift(-0.5, 0.0)):
        T_tracked = T_true @ error
        t = shading_translation(
            rgb,
            rc.render_depth(cam, T_tracked),
            cam,
            cfg=ShadingConfig(shading_max_shift_px=12, shading_sigma_px=6.0),
        )
        assert t is not None
        left = (T_tracked @ translation_for_shift(cam, 0, 0, 1.0))[:3, 3] + t - T_true[:3, 3]
        # one pixel at 14 mm is 0.15 mm at this lens
        assert np.linalg.norm(left) < 0.15 < np.linalg.norm(error[:3, 3]) / 2, (t, left)


def test_step_correction_is_the_median_translation() -> None:
    ts = [np.array([0.3, -0.1, 0.0]), np.array([0.2, 0.0, 0.0]), np.array([5.0, 4.0, 0.0])]
    F = step_correction(ts)
    np.testing.assert_allclose(F[:3, 3], [0.3, 0.0, 0.0])
    np.testing.assert_allclose(F[:3, :3], np.eye(3))
    np.testing.assert_allclose(step_correction([]), np.eye(4))


def test_no_signal_gives_no_translation() -> None:
    cam = Camera.from_fov(64, 48, 70)
    z = np.full((48, 64), 10.0, np.float32)
    flat = np.full((48, 64, 3), 128, np.uint8)
    assert shading_translation(flat, z, cam) is None
    # nothing of the frame is valid: no shift at all
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    sh = shading_shift(rgb, z, cam, mask=np.zeros((48, 64), bool))
    with pytest.raises(InvalidInputError, match="shading.shading_max_shift_px"):
        ShadingConfig(shading_max_shift_px=0)
    with pytest.raises(InvalidInputError, match="shading.shading_sigma_px"):
        ShadingConfig(shading_sigma_px=float("nan"))
    assert (sh.dx_px, sh.dy_px, sh.ncc, sh.n_px) == (0, 0, 0.0, 0)
    assert shading_translation(rgb, np.full((48, 64), np.nan, np.float32), cam) is None


def test_the_update_config_reaches_the_alignment() -> None:
    # The updater's hook (the streaming and the batch path both call it) must pass its
    # own search window and gate, not the function's defaults: a window narrower than the
    # error finds none (the best shift lies on its edge), a wide one finds it.
    from chisel.update_config import UpdateConfig
    from chisel.updater import shading_translation_of

    mesh = _bumpy_surface()
    cam = Camera.from_fov(160, 128, 80)
    # sensor noise keeps the match below a perfect correlation, so a gate can refuse it
    noise = np.random.default_rng(1).normal(0.0, 12.0, (128, 160, 1))
    rgb = np.clip(np.round(_frame_at(mesh, cam, np.eye(4)) + noise), 0, 255).astype(np.uint8)
    T_tracked = _shift(0.5, 0.0)
    R = MeshRaycaster(mesh.vertices, mesh.faces).render_depth(cam, T_tracked)
    frame = Frame(0, T_tracked, rgb=rgb)
    narrow = UpdateConfig(shading=ShadingConfig(align_by_shading=True, shading_max_shift_px=2))
    assert shading_translation_of(frame, R, cam, narrow) is None
    wide = UpdateConfig(shading=ShadingConfig(align_by_shading=True, shading_max_shift_px=12))
    t = shading_translation_of(frame, R, cam, wide)
    assert t is not None and t[0] < -0.3
    gated = UpdateConfig(
        shading=ShadingConfig(align_by_shading=True, shading_max_shift_px=12, shading_min_ncc=0.99)
    )
    assert shading_translation_of(frame, R, cam, gated) is None
    assert shading_translation_of(Frame(0, T_tracked), R, cam, wide) is None


@pytest.fixture(scope="module")
def room() -> dict:
    from test_updater_scenes import camera, poses, preop_model, tissue_mesh

    tissue = tissue_mesh()
    cam = camera(192, 160)
    model = preop_model(tissue, cam)
    true_poses = poses(8, seed=5)
    error = _shift(0.9, -0.6)  # the same camera-side error in every frame: a hand-eye error
    frames = [
        Frame(
            i,
            T @ error,
            rgb=np.round(_frame_at(tissue, cam, T)).astype(np.uint8),
            T_world_from_cam_true=T,
        )  # fmt: skip
        for i, T in enumerate(true_poses)
    ]
    return {"cam": cam, "model": model, "frames": frames, "error_mm": 1.08, "tissue": tissue}


def _lateral_error_mm(T: np.ndarray, T_true: np.ndarray) -> float:
    return float(np.linalg.norm((np.linalg.inv(T_true) @ T)[:2, 3]))


def test_a_step_is_pulled_onto_its_shading_in_batch_and_streaming(room: dict) -> None:
    from chisel.batch import plan_step
    from chisel.depth_source import GroundTruthDepth
    from chisel.update_config import UpdateConfig
    from chisel.updater import ChiselUpdater

    cam, model, frames = room["cam"], room["model"], room["frames"]
    cfg = UpdateConfig(shading=ShadingConfig(align_by_shading=True), register=False)
    exact = GroundTruthDepth()
    # the depth source only needs depth to exist; the pose comes from the shading alone
    frames = [
        Frame(f.index, f.T_world_from_cam, f.rgb, np.full(cam.shape, 20.0, np.float32), None,
              f.T_world_from_cam_true)
        for f in frames
    ]  # fmt: skip
    for T_used, f in zip(
        [inp.T_world_from_cam for inp in plan_step(model, cam, frames, exact, cfg).inputs],
        frames, strict=True,
    ):  # fmt: skip
        assert f.T_world_from_cam_true is not None
        assert _lateral_error_mm(f.T_world_from_cam, f.T_world_from_cam_true) > 1.0
        assert _lateral_error_mm(T_used, f.T_world_from_cam_true) < 0.3
    off = plan_step(model, cam, frames, exact, replace(cfg, shading=ShadingConfig()))
    assert all(
        np.array_equal(inp.T_world_from_cam, f.T_world_from_cam)
        for inp, f in zip(off.inputs, frames, strict=True)
    )
    # Streaming: a frame is corrected by the frames two or more before it (the shift of
    # the frame just before is measured meanwhile, on its own thread): the first two keep
    # their tracked poses, and from the third on the running median holds. Frame by frame
    # and through process_stream, the same poses and the same model.
    runs = []
    for stream in (False, True):
        upd = ChiselUpdater(model, cam, exact, cfg)
        upd.begin_step()
        reports = (
            list(upd.process_stream(frames, keep_maps=True))
            if stream
            else [upd.process(f, keep_maps=True) for f in frames]
        )
        runs.append(([r.mask_T_world_from_cam for r in reports], upd.end_step(), upd.model))
    (streamed, step, model_1), (streamed_2, step_2, model_2) = runs
    for T, T2 in zip(streamed, streamed_2, strict=True):
        np.testing.assert_array_equal(T, T2)
    for T_used, f in list(zip(streamed, frames, strict=True))[:2]:
        np.testing.assert_array_equal(T_used, f.T_world_from_cam)
    for T_used, f in list(zip(streamed, frames, strict=True))[2:]:
        assert f.T_world_from_cam_true is not None
        assert _lateral_error_mm(T_used, f.T_world_from_cam_true) < 0.3
    np.testing.assert_array_equal(model_1.tsdf, model_2.tsdf)
    assert step.pose_correction == step_2.pose_correction
    assert step.pose_correction is not None and step.pose_correction["frames_found"] >= 6


def test_the_cli_corrects_a_metric_source_and_reports_it(
    room: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`chisel update` reads the frames' RGB when the option is on, even for a metric depth
    source (whose frames it otherwise reads without), and reports the correction; a
    sequence with no RGB is refused, naming the sequence."""
    import json

    from chisel.cli import main
    from chisel.io.sequence import write_sequence

    cam, frames = room["cam"], room["frames"]
    rc = MeshRaycaster.from_trimesh(room["tissue"])
    with_depth = [
        replace(f, depth_mm=rc.render_depth(cam, f.T_world_from_cam_true)) for f in frames
    ]
    write_sequence(tmp_path / "seq", cam, with_depth)
    write_sequence(tmp_path / "grey", cam, [replace(f, rgb=None) for f in with_depth])
    room["model"].save(tmp_path / "m0.npz")
    common = ["update", "--model", str(tmp_path / "m0.npz"), "--depth-source", "gt",
              "--no-register", "--align-by-shading", "--no-progress"]  # fmt: skip
    assert main([*common, "--sequence", str(tmp_path / "seq"), "--out",
                 str(tmp_path / "m1.npz"), "--report", str(tmp_path / "r.json"),
                 "--masks", str(tmp_path / "masks.npz")]) == 0  # fmt: skip
    correction = json.loads((tmp_path / "r.json").read_text())["pose_correction"]
    assert correction["by"] == "shading" and correction["frames_found"] >= 6
    # the frames' error is T_tracked = T_true @ _shift(0.9, -0.6): the correction undoes it
    assert np.allclose(correction["translation_mm"][:2], [-0.9, 0.6], atol=0.3)
    # the masks are made in the corrected camera's image, and say so for their scoring
    with np.load(tmp_path / "masks.npz") as z:
        mask_poses = z["T_world_from_cam"]
    for f, T in zip(frames, mask_poses, strict=True):
        F = np.linalg.inv(f.T_world_from_cam) @ T
        assert np.allclose(F[:3, :3], np.eye(3), atol=1e-9)
        assert np.allclose(F[:3, 3], correction["translation_mm"], atol=1e-3)
    capsys.readouterr()
    assert main([*common, "--sequence", str(tmp_path / "grey"), "--out",
                 str(tmp_path / "m2.npz")]) == 1  # fmt: skip
    assert "grey: update.shading.align_by_shading needs the frames' RGB" in capsys.readouterr().err
    assert not (tmp_path / "m2.npz").exists()


def test_log_luminance_of_every_8_bit_sum_is_the_formula() -> None:
    # the table look-up against the per-pixel formula, in double precision
    total = np.arange(3 * 255 + 1)
    rgb = np.stack(
        [np.minimum(total, 255), np.clip(total - 255, 0, 255), np.clip(total - 510, 0, 255)], -1
    )
    lum = log_luminance(rgb.astype(np.uint8)[None])
    np.testing.assert_allclose(lum[0], DISPLAY_GAMMA * np.log(total / 3.0 + 1.0), rtol=1e-6)
    np.testing.assert_allclose(log_luminance(rgb[None].astype(np.float32)), lum, rtol=1e-6)
