import json

import numpy as np
import pytest

from chisel.core.errors import DepthUnitsError, FormatVersionError, InvalidInputError, PoseError
from chisel.core.geometry import Camera, look_at
from chisel.io.sequence import Frame, Sequence, SequenceWriter, check_depth_mm, write_sequence


def make_frames(cam: Camera, n: int, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        depth = rng.uniform(5, 30, cam.shape).astype(np.float32)
        depth[0, :3] = np.nan
        T = look_at([i, 0, 0], [i, 0, 20], up=[0, -1, 0])
        frames.append(
            Frame(
                i,
                T,
                rng.integers(0, 255, (*cam.shape, 3), dtype=np.uint8),
                depth,
                rng.random(cam.shape) > 0.2,
                T,
            )
        )
    return frames


def test_round_trip(tmp_path) -> None:
    cam = Camera.from_fov(40, 30, 80, dist=np.array([0.1, -0.01, 0.001, 0.0, 0.0]))
    frames = make_frames(cam, 3)
    circle = np.ones(cam.shape, bool)
    circle[0, 0] = False
    write_sequence(tmp_path / "seq", cam, frames, meta={"phantom_seed": 3}, camera_mask=circle)
    seq = Sequence(tmp_path / "seq")
    assert len(seq) == 3 and seq.meta == {"phantom_seed": 3}
    np.testing.assert_array_equal(seq.camera.K, cam.K)
    np.testing.assert_array_equal(seq.camera.dist, cam.dist)
    for f, g in zip(frames, seq, strict=True):
        np.testing.assert_array_equal(f.rgb, g.rgb)
        np.testing.assert_array_equal(f.depth_mm, g.depth_mm)  # NaN round trip
        np.testing.assert_array_equal(f.mask & circle, g.mask)
        np.testing.assert_array_equal(f.T_world_from_cam, g.T_world_from_cam)
        np.testing.assert_array_equal(f.T_world_from_cam_true, g.T_world_from_cam_true)
    assert np.load(tmp_path / "seq/depth/000000.npy")[0, 0] == 0.0  # 0 = invalid on disk


def test_failed_write_keeps_previous(tmp_path) -> None:
    cam = Camera.from_fov(40, 30, 80)
    frames = make_frames(cam, 2)
    write_sequence(tmp_path / "seq", cam, frames)
    before = (tmp_path / "seq/poses.txt").read_text()
    bad = Frame(2, np.full((4, 4), np.nan))
    with pytest.raises(PoseError):
        write_sequence(tmp_path / "seq", cam, [*frames, bad])
    assert (tmp_path / "seq/poses.txt").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_mixed_presence_rejected(tmp_path) -> None:
    cam = Camera.from_fov(40, 30, 80)
    f0, f1 = make_frames(cam, 2)
    with pytest.raises(InvalidInputError, match="some frames only"):
        with SequenceWriter(tmp_path / "s", cam) as w:
            w.add(f0)
            w.add(Frame(1, f1.T_world_from_cam, f1.rgb, None))
    assert not (tmp_path / "s").exists()


def test_reader_errors(tmp_path) -> None:
    cam = Camera.from_fov(40, 30, 80)
    write_sequence(tmp_path / "seq", cam, make_frames(cam, 2))
    with pytest.raises(InvalidInputError, match="sequence.json is missing"):
        Sequence(tmp_path)
    header = json.loads((tmp_path / "seq/sequence.json").read_text())
    header["version"] = 99
    (tmp_path / "seq/sequence.json").write_text(json.dumps(header))
    with pytest.raises(FormatVersionError, match="99"):
        Sequence(tmp_path / "seq")
    header["version"] = 1
    header["num_frames"] = 3
    (tmp_path / "seq/sequence.json").write_text(json.dumps(header))
    with pytest.raises(PoseError, match="2 poses"):
        Sequence(tmp_path / "seq")
    header["num_frames"] = 2
    (tmp_path / "seq/sequence.json").write_text(json.dumps(header))
    (tmp_path / "seq/rgb/000001.png").write_bytes(b"\x89PNG\r\n\x1a\ntruncated")
    seq = Sequence(tmp_path / "seq")
    with pytest.raises(InvalidInputError, match="000001.png.*(decode|truncated PNG)"):
        seq.rgb(1)


def test_depth_checks() -> None:
    with pytest.raises(DepthUnitsError, match="metres"):
        check_depth_mm(np.full((4, 4), 0.02), "d")
    with pytest.raises(InvalidInputError, match="no valid pixel"):
        check_depth_mm(np.zeros((4, 4)), "d")
    out = check_depth_mm(np.array([[0.0, 10.0]]), "d")
    assert np.isnan(out[0, 0]) and out[0, 1] == 10.0


def test_atomic_files_get_normal_permissions(tmp_path) -> None:
    import os
    import stat

    from chisel.core.atomic import atomic_write_text

    atomic_write_text(tmp_path / "a.txt", "x")
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o666 & ~umask
