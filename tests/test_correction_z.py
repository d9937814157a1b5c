"""How well a step's frames determine its hand-eye correction
(chisel.registration.correction_z, reported under sequence_registration.hand_eye)."""

from __future__ import annotations

import numpy as np
import pytest
import test_updater_scenes as sc
from scipy.spatial.transform import Rotation

from chisel.batch import update_step
from chisel.core.geometry import rotation_angle_deg
from chisel.depth_source import CallableDepth
from chisel.registration import correction_z, robust_mean_transform


def _rigid(rotvec_rad: np.ndarray, shift_mm: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec_rad).as_matrix()
    T[:3, 3] = shift_mm
    return T


def _scattered(n: int, sigma_deg: float, sigma_mm: float, seed: int) -> list[np.ndarray]:
    """n corrections around a true 1 deg / 0.5 mm one, Gaussian per axis."""
    rng = np.random.default_rng(seed)
    F0 = _rigid(np.radians([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]))
    return [
        F0 @ _rigid(np.radians(rng.normal(0.0, sigma_deg, 3)), rng.normal(0.0, sigma_mm, 3))
        for _ in range(n)
    ]


@pytest.mark.parametrize(("sigma_deg", "sigma_mm"), [(0.2, 0.1), (2.0, 0.8)])
def test_z_is_the_size_over_the_standard_error_of_a_median(sigma_deg, sigma_mm) -> None:
    # Analytic: the standard error of the median of n Gaussian samples is
    # 1.2533 sigma / sqrt(n); with many samples the scatter pins sigma down to ~1 %.
    n = 4000
    Fs = _scattered(n, sigma_deg, sigma_mm, seed=1)
    F = robust_mean_transform(Fs)
    z_rot, z_shift = correction_z(F, Fs)
    angle_deg = rotation_angle_deg(F)
    assert z_rot == pytest.approx(angle_deg / (1.2533 * sigma_deg / np.sqrt(n)), rel=0.05)
    assert z_shift == pytest.approx(
        np.linalg.norm(F[:3, 3]) / (1.2533 * sigma_mm / np.sqrt(n)), rel=0.05
    )


def test_under_no_true_correction_z_follows_a_chi_distribution() -> None:
    # With no true correction, F is noise: z over many draws has the median of a chi
    # distribution with 3 degrees of freedom (1.538), not the exact-depth case's tens.
    rng = np.random.default_rng(2)
    zs = []
    for _ in range(300):
        Fs = [
            _rigid(np.radians(rng.normal(0.0, 4.0, 3)), rng.normal(0.0, 0.8, 3)) for _ in range(20)
        ]
        zs.append(correction_z(robust_mean_transform(Fs), Fs)[0])
    assert np.median(zs) == pytest.approx(1.538, rel=0.15)


def test_too_few_or_identical_corrections() -> None:
    Fs = _scattered(2, 0.1, 0.1, seed=3)
    assert correction_z(robust_mean_transform(Fs), Fs) == (0.0, 0.0)
    F0 = _rigid(np.radians([0.0, 1.0, 0.0]), np.array([0.0, 0.3, 0.0]))
    assert correction_z(F0, [F0, F0, F0]) == (np.inf, np.inf)
    assert correction_z(np.eye(4), [np.eye(4)] * 3) == (0.0, 0.0)


def test_the_step_report_says_whether_the_frames_agree_on_the_hand_eye_correction() -> None:
    tissue, cam = sc.tissue_mesh(), sc.camera()
    model = sc.preop_model(tissue, cam)
    bitten, P = sc.bitten_mesh(tissue), sc.poses(8, seed=2)
    src = CallableDepth(lambda f: f.depth_mm * 0.037)
    # One constant 1 mm / 1 deg hand-eye error, exact depth up to scale: the frames agree.
    same = np.stack([T @ sc.pose_error(1.0, 1.0, seed=10) for T in P])
    _, rep = update_step(model, cam, sc.frames(bitten, cam, P, same), src)
    he = rep.sequence_registration["hand_eye"]
    assert he["z_rotation"] > 10.0 and he["z_translation"] > 10.0
    # Each frame off by its own 1 mm / 1 deg: their corrections scatter around none.
    own = np.stack([T @ sc.pose_error(1.0, 1.0, seed=10 + i) for i, T in enumerate(P)])
    _, rep = update_step(model, cam, sc.frames(bitten, cam, P, own), src)
    he = rep.sequence_registration["hand_eye"]
    assert he["z_rotation"] < 3.0 and he["z_translation"] < 3.0
