"""Hostile configuration values: each is refused with one error naming the key or option,
expected vs actual, before anything is read or written (docs/bad-inputs.md).

The Open3D settings of the registration reached Open3D unchecked (``--ransac-max-iter -1``
died allocating, ``--seed 2147483648`` of a ``TypeError``), and nonsense like a RANSAC
confidence of 5 was accepted; a dataset's ``phantom_seed`` of ``1e400`` died of
``OverflowError`` and ``1000.9`` read as phantom 1000; ``evaluate --samples`` past a C
``long`` died in numpy; ``build --ct-weight 1e300`` wrote weights of inf.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from chisel.build import BuildConfig
from chisel.change import ChangeConfig
from chisel.cli import main
from chisel.core.config import config_from_dict, read_yaml_mapping
from chisel.core.errors import ConfigError, InvalidInputError
from chisel.depth.data import find_sequences, read_dataset_index
from chisel.depth.prior_data import read_step_dataset
from chisel.eval.surface import SurfaceMetricConfig
from chisel.registration import RegistrationConfig
from chisel.update_config import UpdateConfig

ROOT = Path(__file__).resolve().parents[1]


def refused(argv: list[str], capsys: pytest.CaptureFixture[str], *words: str) -> str:
    """``chisel`` exits 1 with one line ``chisel <cmd>: error: ...`` holding ``words``."""
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1, err
    assert err.startswith(f"chisel {argv[0]}: error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err
    return err


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    """Inputs that only need to exist: the values are refused before they are read."""
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "sequence.json").write_text("{}")
    model = tmp_path / "model.npz"
    model.write_bytes(b"not read")
    ct = tmp_path / "ct.nii.gz"
    ct.write_bytes(b"not read")
    return {"seq": seq, "model": model, "ct": ct, "root": tmp_path}


# ------------------------------------------------------------------ registration, change
# (field, bad value, expected range in the message): every numeric field, both sides.
REGISTRATION_BAD = [
    ("voxel_mm", 0.0, "in [0.001, 1000] mm"),
    ("voxel_mm", 1e-9, "in [0.001, 1000] mm"),  # Open3D: "voxel_size is too small"
    ("voxel_mm", 1e300, "in [0.001, 1000] mm"),
    ("icp_max_dist_mm", (3.0, -1.0), "one or more distances in (0, 1000] mm"),
    ("icp_max_dist_mm", (), "one or more distances in (0, 1000] mm"),
    ("icp_max_dist_mm", (1e6,), "one or more distances in (0, 1000] mm"),
    ("tukey_k_mm", 0.0, "in (0, 1000] mm"),
    ("tukey_k_mm", 1e4, "in (0, 1000] mm"),
    ("icp_max_iter", -1, "in [1, 10000]"),
    ("icp_max_iter", 0, "in [1, 10000]"),
    ("icp_max_iter", 2**31, "in [1, 10000]"),
    ("fitness_dist_mm", -1.5, "in (0, 1000] mm"),
    ("fitness_dist_mm", 1e5, "in (0, 1000] mm"),
    ("min_fitness", 1.5, "in [0, 1]"),
    ("min_fitness", -0.1, "in [0, 1]"),
    ("max_correction_mm", -1.0, "in (0, 1000] mm"),
    ("max_correction_mm", 0.0, "in (0, 1000] mm"),
    ("max_correction_mm", 1e5, "in (0, 1000] mm"),
    ("max_correction_deg", -1.0, "in (0, 180] deg"),
    ("max_correction_deg", 360.0, "in (0, 180] deg"),
    ("ransac_max_iter", -1, "in [1, 10000000]"),
    ("ransac_max_iter", 0, "in [1, 10000000]"),
    ("ransac_max_iter", 2**31, "in [1, 10000000]"),
    ("ransac_confidence", 5.0, "in (0, 1]"),
    ("ransac_confidence", 0.0, "in (0, 1]"),
    ("pose_prior", -1.0, "in [0, 1]"),
    ("pose_prior", 5.0, "in [0, 1]"),
    ("tracking_accuracy_mm", 0.0, "in (0, 1000] mm"),
    ("tracking_accuracy_mm", 1e4, "in (0, 1000] mm"),
    ("tracking_accuracy_deg", -3.0, "in (0, 180] deg"),
    ("tracking_accuracy_deg", 200.0, "in (0, 180] deg"),
    ("max_scale_change", 0.0, "in (0, 1)"),
    ("max_scale_change", 1.0, "in (0, 1)"),
    ("seed", -1, "in [0, 2147483647]"),
    ("seed", 2**31, "in [0, 2147483647]"),
]

CHANGE_BAD = [
    ("threshold_mm", 0.0, "in (0, 1000] mm"),
    ("threshold_mm", 1e300, "in (0, 1000] mm"),
    ("open_px", -1, ">= 0"),
    ("close_px", -1, ">= 0"),
    ("open_px", 10**9, "at most 16384 px (the widest image read)"),
    ("close_px", 16385, "at most 16384 px (the widest image read)"),
    ("min_area_px", -1, "in [0, 67108864] px"),
    ("min_area_px", 10**20, "in [0, 67108864] px"),
    ("min_views", -1, "in [0, 10000]"),
    ("min_views", 10**20, "in [0, 10000]"),
    ("min_agreement", 1.5, "in [0, 1]"),
    ("visible_mm", 0.0, "in (0, 1000] mm"),
    ("visible_mm", 1e9, "in (0, 1000] mm"),
    ("contradict_fraction", -1.0, "in [0, 1]"),
    ("contradict_fraction", 1.5, "in [0, 1]"),
    ("noise_k", -1.0, "in [0, 100]"),
    ("noise_k", 1e300, "in [0, 100]"),
]

UPDATE_BAD = [
    ("max_points", 99, "in [100, 67108864] points per frame"),
    ("max_points", 10**30, "in [100, 67108864] points per frame"),
    ("sequence_points", 10, "in [100, 67108864] points per frame"),
    ("hand_eye_frames", 0, ">= 1"),
    ("noisy_votes", 0, "in [1, 255]"),
    ("noisy_votes", 256, "in [1, 255]"),
    ("noisy_layer_mm", 0.0, "> 0 mm"),
    ("noisy_max_depth_mm", -5.0, "> 0 mm"),
    ("occluder_margin_px", -1.0, ">= 0 pixels and at most 16384"),
    ("occluder_margin_px", 1e9, ">= 0 pixels and at most 16384"),
    ("rim_px", -1, ">= 0 pixels and at most 16384"),
    ("rim_px", 10**10, ">= 0 pixels and at most 16384"),  # OpenCV: "Can't parse 'ksize'"
]


def _bounded(cls: type, key: str, name: str, bad: object, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        cls(**{name: bad})
    assert info.value.source == key
    assert info.value.problem.startswith(f"must be {expected}")
    assert f", got {bad}" in info.value.problem


@pytest.mark.parametrize(("name", "bad", "expected"), REGISTRATION_BAD)
def test_every_registration_setting_is_bounded(name: str, bad: object, expected: str) -> None:
    _bounded(RegistrationConfig, f"registration.{name}", name, bad, expected)


@pytest.mark.parametrize(("name", "bad", "expected"), CHANGE_BAD)
def test_every_change_setting_is_bounded(name: str, bad: object, expected: str) -> None:
    _bounded(ChangeConfig, f"change.{name}", name, bad, expected)


@pytest.mark.parametrize(("name", "bad", "expected"), UPDATE_BAD)
def test_every_update_setting_is_bounded(name: str, bad: object, expected: str) -> None:
    _bounded(UpdateConfig, name, name, bad, expected)


def test_defaults_limits_and_the_shipped_configs_still_validate() -> None:
    """The positive control: defaults, the values at each limit, and every experiment's
    ``update:`` section (config/*.yaml) pass."""
    assert RegistrationConfig() == RegistrationConfig(**vars(RegistrationConfig()))
    RegistrationConfig(
        voxel_mm=0.001, icp_max_dist_mm=(1000.0, 0.1), tukey_k_mm=1000.0, icp_max_iter=10_000,
        fitness_dist_mm=0.01, min_fitness=0.0, max_correction_mm=1000.0,
        max_correction_deg=180.0, ransac_max_iter=10_000_000, ransac_confidence=1.0,
        pose_prior=0.0, tracking_accuracy_mm=1000.0, tracking_accuracy_deg=180.0,
        max_scale_change=0.99, seed=2**31 - 1,
    )  # fmt: skip
    RegistrationConfig(voxel_mm=1000.0, ransac_max_iter=1, icp_max_iter=1, pose_prior=1.0, seed=0)
    ChangeConfig(
        threshold_mm=1000.0, open_px=0, close_px=16384, min_area_px=8192 * 8192,
        min_views=10_000, min_agreement=1.0, visible_mm=1000.0, contradict_fraction=0.0,
        noise_k=100.0,
    )  # fmt: skip
    ChangeConfig(contradict_fraction=1.0, noise_k=0.0, min_views=0)
    UpdateConfig(
        max_points=100, sequence_points=8192 * 8192, hand_eye_frames=1, noisy_votes=255,
        occluder_margin_px=16.0, rim_px=16384,
    )  # fmt: skip
    UpdateConfig(noisy_votes=1, rim_px=0, occluder_margin_px=0.0)
    shipped = sorted((ROOT / "config").glob("*.yaml"))
    assert shipped
    for path in shipped:
        section = read_yaml_mapping(path).get("update", {})
        config_from_dict(UpdateConfig, section, "update")
    assert SurfaceMetricConfig().n_samples == 50_000
    assert SurfaceMetricConfig(n_samples=10_000_000).n_samples == 10_000_000
    assert SurfaceMetricConfig(n_samples=100).n_samples == 100
    assert BuildConfig().ct_weight == 1.0
    assert BuildConfig(ct_weight=1e6).ct_weight == 1e6
    assert BuildConfig(ct_weight=1e-6).ct_weight == 1e-6


@pytest.mark.parametrize(
    ("flag", "value", "key", "expected"),
    [
        ("--ransac-max-iter", "-1", "registration.ransac_max_iter", "in [1, 10000000], got -1"),
        ("--seed", "2147483648", "registration.seed", "in [0, 2147483647], got 2147483648"),
        ("--ransac-confidence", "5", "registration.ransac_confidence", "in (0, 1], got 5"),
        ("--icp-max-iter", "-1", "registration.icp_max_iter", "in [1, 10000], got -1"),
        ("--max-correction-mm", "-1", "registration.max_correction_mm", "got -1"),
        ("--pose-prior", "-1", "registration.pose_prior", "in [0, 1], got -1"),
        ("--contradict-fraction", "-1", "change.contradict_fraction", "in [0, 1], got -1"),
        ("--rim-px", "10000000000", "rim_px", "at most 16384 (the widest image read)"),
    ],
)
def test_update_flags_out_of_range_are_refused_before_anything_is_read(
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    flag: str,
    value: str,
    key: str,
    expected: str,
) -> None:
    out = files["root"] / "u.npz"
    argv = ["update", "--model", str(files["model"]), "--sequence", str(files["seq"])]
    refused([*argv, "--out", str(out), flag, value], capsys, f"{key}: must be ", expected)
    assert not out.exists()


@pytest.mark.parametrize(
    ("yaml_text", "key", "expected"),
    [
        ("registration:\n  ransac_confidence: 5\n", "registration.ransac_confidence", "(0, 1]"),
        ("registration:\n  icp_max_iter: -1\n", "registration.icp_max_iter", "[1, 10000]"),
        ("registration:\n  max_correction_mm: -1\n", "registration.max_correction_mm", "(0, "),
        ("registration:\n  pose_prior: -1\n", "registration.pose_prior", "[0, 1]"),
        ("registration:\n  ransac_max_iter: -1\n", "registration.ransac_max_iter", "[1, "),
        ("registration:\n  seed: 2147483648\n", "registration.seed", "[0, 2147483647]"),
        ("change:\n  contradict_fraction: -1\n", "change.contradict_fraction", "[0, 1]"),
        ("noisy_votes: 0\n", "noisy_votes", "[1, 255]"),
    ],
)
def test_update_config_file_out_of_range_names_the_file_and_key(
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    yaml_text: str,
    key: str,
    expected: str,
) -> None:
    cfg = files["root"] / "update.yaml"
    cfg.write_text(yaml_text)
    out = files["root"] / "u.npz"
    argv = ["update", "--model", str(files["model"]), "--sequence", str(files["seq"])]
    refused(
        [*argv, "--out", str(out), "--config", str(cfg)],
        capsys,
        f"update.yaml: {key}: must be in {expected}",
    )
    assert not out.exists()


# ------------------------------------------------------------------------- phantom seeds
PHANTOM_SEED_BAD = {
    "overflow": "1e400",  # json reads infinity; int() died of OverflowError
    "fraction": "1000.9",  # int() truncated it to phantom 1000
    "integral_float": "1000.0",
    "bool": "true",
    "string": '"1000"',
    "negative": "-1",
    "past_int64": str(2**63),
}


@pytest.mark.parametrize("raw", PHANTOM_SEED_BAD.values(), ids=PHANTOM_SEED_BAD.keys())
def test_a_phantom_seed_that_is_not_an_int64_names_the_file_and_entry(
    tmp_path: Path, raw: str
) -> None:
    (tmp_path / "s").mkdir()
    index = tmp_path / "dataset.json"
    index.write_text(f'{{"sequences": [{{"path": "s", "phantom_seed": {raw}, "step": 0}}]}}')
    shape = r"sequences\[0\]: phantom_seed must be an integer in \[0, 2\*\*63 - 1\]"
    for read in (read_dataset_index, lambda p: find_sequences([p]), read_step_dataset):
        arg = [index] if read is read_step_dataset else index
        with pytest.raises(InvalidInputError, match=shape) as info:
            read(arg)  # type: ignore[operator]
        assert info.value.source == f"{index} sequences[0]"
        assert not isinstance(info.value, OverflowError)


def test_a_step_of_1e400_is_one_error_naming_the_entry(tmp_path: Path) -> None:
    # The step is read leniently (int() of it, as before), but infinity is no step.
    (tmp_path / "s").mkdir()
    index = tmp_path / "dataset.json"
    index.write_text('{"sequences": [{"path": "s", "phantom_seed": 1000, "step": 1e400}]}')
    with pytest.raises(InvalidInputError, match=r"sequences\[0\]: step must be an integer"):
        read_step_dataset([index])


def test_phantom_seeds_within_int64_are_read(tmp_path: Path) -> None:
    (tmp_path / "s").mkdir()
    index = tmp_path / "dataset.json"
    for seed in (0, 1000, 2**63 - 1):
        index.write_text(
            json.dumps({"sequences": [{"path": "s", "phantom_seed": seed, "step": 0}]})
        )
        assert [r.seed for r in read_dataset_index(index)] == [seed]
        assert [r.seed for r in read_step_dataset([index])] == [seed]


# ------------------------------------------------------------------ evaluate --samples
@pytest.mark.parametrize("samples", ["99999999999999999999", "10000001", "99", "0", "-5"])
def test_evaluate_samples_out_of_range_is_refused_naming_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], samples: str
) -> None:
    out = tmp_path / "m.json"
    refused(
        ["evaluate", "--samples", samples, "--out", str(out)],
        capsys,
        f"--samples: must be an integer in [100, 10000000], got {samples}",
    )
    assert not out.exists()


def test_surface_metric_config_refuses_a_non_integer_sample_count() -> None:
    for bad in (150.5, True, 10**20):
        with pytest.raises(InvalidInputError, match=r"n_samples: must be an integer in \[100"):
            SurfaceMetricConfig(n_samples=bad)  # type: ignore[arg-type]


# ---------------------------------------------------------------------- build --ct-weight
@pytest.mark.parametrize("weight", ["1e300", "1e39", "2e6", "0", "-1", "1e-9"])
def test_build_ct_weight_out_of_range_is_refused_before_anything_is_written(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str], weight: str
) -> None:
    out = files["root"] / "preop.npz"
    argv = ["build", "--from-ct", str(files["ct"]), "--sequence", str(files["seq"])]
    refused(
        [*argv, "--out", str(out), "--ct-weight", weight],
        capsys,
        "ct_weight: must be in [1e-06, 1e+06] (weights are float32; a frame adds 1), got ",
    )
    assert not out.exists()
    assert sorted(p.name for p in files["root"].iterdir()) == ["ct.nii.gz", "model.npz", "seq"]
