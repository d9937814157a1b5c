import numpy as np
import pytest

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, invert_rigid, look_at, rotation_angle_deg
from chisel.io.sequence import Frame, Sequence, write_sequence
from sim.cli import main as sim_main


def _write(path, with_true: bool = True) -> None:
    cam = Camera.from_fov(32, 24, 80)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(5):
        T = look_at([i, 0.5 * i, 0], [i, 0, 30], up=[0, -1, 0])
        depth = rng.uniform(5, 20, cam.shape).astype(np.float32)
        rgb = rng.integers(0, 255, (*cam.shape, 3), dtype=np.uint8)
        frames.append(Frame(i, T, rgb, depth, None, T if with_true else None))
    circle = np.ones(cam.shape, bool)
    circle[0] = False
    write_sequence(path, cam, frames, camera_mask=circle)


def test_retrack_keeps_frames_and_redraws_poses(tmp_path) -> None:
    _write(tmp_path / "in")
    assert (
        sim_main(["retrack", "--sequence", str(tmp_path / "in"), "--out", str(tmp_path / "exact")])
        == 0
    )
    src, exact = Sequence(tmp_path / "in"), Sequence(tmp_path / "exact")
    np.testing.assert_array_equal(exact.poses, src.true_poses)
    args = ["--handeye-mm", "1.5", "--handeye-deg", "2.0", "--seed", "3"]
    assert (
        sim_main(
            ["retrack", "--sequence", str(tmp_path / "in"), "--out", str(tmp_path / "n"), *args]
        )
        == 0
    )
    noisy = Sequence(tmp_path / "n")
    np.testing.assert_array_equal(noisy.true_poses, src.true_poses)
    for i in range(len(src)):
        np.testing.assert_array_equal(noisy.rgb(i), src.rgb(i))
        np.testing.assert_array_equal(noisy.depth_mm(i), src.depth_mm(i))
        np.testing.assert_array_equal(noisy.mask(i), src.mask(i))
        # A pure hand-eye error: the camera-frame offset has exactly the requested size.
        E = invert_rigid(src.true_poses[i]) @ noisy.poses[i]
        assert np.linalg.norm(E[:3, 3]) == pytest.approx(1.5, abs=1e-9)
        assert rotation_angle_deg(E[:3, :3]) == pytest.approx(2.0, abs=1e-6)


def test_retrack_needs_true_poses(tmp_path) -> None:
    from sim.config import TrackingConfig
    from sim.retrack import retrack_sequence

    _write(tmp_path / "real", with_true=False)
    with pytest.raises(InvalidInputError, match="no true poses"):
        retrack_sequence(tmp_path / "real", tmp_path / "out", TrackingConfig(), 0)
    assert not (tmp_path / "out").exists()
