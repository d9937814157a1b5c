from pathlib import Path

import numpy as np
import pytest

from chisel.core.errors import FormatVersionError, InvalidInputError
from chisel.model import MODEL_FORMAT, TsdfModel


def _model(color: bool) -> TsdfModel:
    rng = np.random.default_rng(0)
    m = TsdfModel.empty([-3.0, -2.0, 1.0], [3.0, 2.0, 5.0], 0.5, 1.5, with_color=color)
    m.tsdf[...] = rng.uniform(-1, 1, m.shape).astype(np.float32)
    m.weight[...] = rng.integers(0, 5, m.shape).astype(np.float32)
    if color:
        m.color[...] = rng.integers(0, 256, (*m.shape, 3), dtype=np.uint8)
    return m


@pytest.mark.parametrize("color", [False, True])
def test_save_load_round_trip(tmp_path: Path, color: bool) -> None:
    m = _model(color)
    object.__setattr__(m, "step", 3)
    path = m.save(tmp_path / "m.npz")
    back = TsdfModel.load(path)
    assert back.shape == m.shape == (13, 9, 9)
    np.testing.assert_array_equal(back.tsdf, m.tsdf)
    np.testing.assert_array_equal(back.weight, m.weight)
    np.testing.assert_array_equal(back.T_world_from_voxel, m.T_world_from_voxel)
    assert back.voxel_size_mm == 0.5 and back.trunc_mm == 1.5 and back.step == 3
    if color:
        np.testing.assert_array_equal(back.color, m.color)
    else:
        assert back.color is None
    # Voxel centres: index (0, 0, 0) is the box corner; the last index the far corner.
    np.testing.assert_allclose(back.bounds_mm[0], [-3, -2, 1])
    np.testing.assert_allclose(back.bounds_mm[1], [3, 2, 5])
    # No temporary files left beside the output.
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]


def _write_raw(path: Path, **over: object) -> None:
    m = _model(False)
    fields = {
        "format": np.array(MODEL_FORMAT),
        "version": np.array(1),
        "tsdf": m.tsdf,
        "weight": m.weight,
        "T_world_from_voxel": m.T_world_from_voxel,
        "voxel_size_mm": np.array(0.5),
        "trunc_mm": np.array(1.5),
    }
    fields.update(over)
    with open(path, "wb") as fh:
        np.savez(fh, **fields)


def test_incompatible_version_is_refused(tmp_path: Path) -> None:
    _write_raw(tmp_path / "v2.npz", version=np.array(2))
    with pytest.raises(FormatVersionError, match="version 2"):
        TsdfModel.load(tmp_path / "v2.npz")


def test_wrong_format_is_refused(tmp_path: Path) -> None:
    _write_raw(tmp_path / "other.npz", format=np.array("something-else"))
    with pytest.raises(FormatVersionError, match="something-else"):
        TsdfModel.load(tmp_path / "other.npz")


def test_missing_field_and_bad_files(tmp_path: Path) -> None:
    m = _model(False)
    with open(tmp_path / "nofield.npz", "wb") as fh:
        np.savez(fh, format=np.array(MODEL_FORMAT), version=np.array(1), tsdf=m.tsdf)
    with pytest.raises(InvalidInputError, match="lacks field"):
        TsdfModel.load(tmp_path / "nofield.npz")
    with pytest.raises(InvalidInputError, match="missing"):
        TsdfModel.load(tmp_path / "absent.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InvalidInputError, match="cannot read"):
        TsdfModel.load(tmp_path / "junk.npz")
    # Object arrays need pickle: refused.
    with open(tmp_path / "pickle.npz", "wb") as fh:
        np.savez(fh, format=np.array([{"a": 1}], dtype=object))
    with pytest.raises(InvalidInputError, match="pickle"):
        TsdfModel.load(tmp_path / "pickle.npz")


def test_fields_of_the_wrong_kind_are_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "array.npy", np.zeros(3))
    (tmp_path / "array.npy").rename(tmp_path / "array.npz")
    with pytest.raises(InvalidInputError, match="not a model file"):
        TsdfModel.load(tmp_path / "array.npz")
    cases = [
        ({"voxel_size_mm": np.array([0.5, 0.5])}, InvalidInputError, "single number"),
        ({"step": np.array(-5)}, InvalidInputError, "step must be an integer >= 0"),
        ({"step": np.array(1.7)}, InvalidInputError, "step must be an integer >= 0"),
        ({"version": np.array("1")}, FormatVersionError, "model version '1'"),
        ({"tsdf": np.full((4, 4, 4), np.nan, np.float32)}, InvalidInputError, "tsdf must be"),
        ({"tsdf": np.full((4, 4, 4), 2.0, np.float32)}, InvalidInputError, "within \\[-1, 1\\]"),
        ({"weight": np.full((4, 4, 4), -1.0, np.float32)}, InvalidInputError, "weight must be"),
    ]
    for i, (fields, error, message) in enumerate(cases):
        _write_raw(tmp_path / f"m{i}.npz", **fields)
        with pytest.raises(error, match=message):
            TsdfModel.load(tmp_path / f"m{i}.npz")


def test_a_box_too_large_for_int64_is_refused_not_overflowed() -> None:
    with pytest.raises(InvalidInputError, match="too large"):
        TsdfModel.empty([-1e9, -1e9, -1e9], [1e9, 1e9, 1e9], 0.5, 1.0)


def test_failed_save_keeps_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "m.npz"
    _model(False).save(path)
    before = path.read_bytes()

    def boom(*a: object, **k: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(OSError, match="disk full"):
        _model(True).save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]


def test_construction_checks() -> None:
    z = np.zeros((4, 4, 4), np.float32)
    T = np.diag([0.5, 0.5, 0.5, 1.0])
    with pytest.raises(InvalidInputError, match="float32"):
        TsdfModel(z.astype(np.float64), z, T, 0.5, 1.0)
    with pytest.raises(InvalidInputError, match="weight"):
        TsdfModel(z, z[:3], T, 0.5, 1.0)
    with pytest.raises(InvalidInputError, match="trunc_mm"):
        TsdfModel(z, z, T, 0.5, 0.25)
    with pytest.raises(InvalidInputError, match="axis-aligned"):
        TsdfModel(z, z, np.eye(4), 0.5, 1.0)
    with pytest.raises(InvalidInputError, match="color"):
        TsdfModel(z, z, T, 0.5, 1.0, color=np.zeros((4, 4, 4, 3), np.float32))
    with pytest.raises(InvalidInputError, match="empty box"):
        TsdfModel.empty([0, 0, 0], [0, 1, 1], 0.5, 1.0)
    with pytest.raises(InvalidInputError, match="too large"):
        TsdfModel.empty([0, 0, 0], [1000, 1000, 1000], 0.1, 1.0)


def test_copy_is_deep() -> None:
    m = _model(True)
    c = m.copy()
    c.tsdf[0, 0, 0] = 5.0
    c.color[0, 0, 0] = 7
    assert m.tsdf[0, 0, 0] != 5.0 and not np.array_equal(m.color, c.color)
