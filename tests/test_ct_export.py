"""The updated CT (``chisel export-ct``) against analytic truth: a block of tissue, a box
removed in the model; exactly the CT voxels inside the box become air, with the
partial-volume ramp at the new boundary."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from chisel.cli import main
from chisel.core.errors import InvalidInputError
from chisel.ct_export import removed_dice, updated_ct
from chisel.io.ct import CtVolume, read_ct_volume, write_ct_volume
from chisel.model import TsdfModel

CT_SHAPE = (16, 14, 12)
# LPS voxel -> world: x axis flipped (negative determinant), 1 mm voxels
T_CT = np.array([[-1.0, 0, 0, 20.0], [0, 1.0, 0, -5.0], [0, 0, 1.0, 3.0], [0, 0, 0, 1.0]])
# removed box in world mm; its two x faces sit 0.3 mm from voxel centres (partial volume),
# the others half way between centres
BOX_LO = np.array([11.0 - 0.3 - 4.0, -5.0 + 3.5, 3.0 + 2.5])
BOX_HI = np.array([11.0 - 0.3, -5.0 + 8.5, 3.0 + 7.5])
TRUNC_MM = 2.0


def _box_sdf(p: np.ndarray) -> np.ndarray:
    """Signed distance to the box, + inside (free space), - outside (tissue), mm."""
    q = np.maximum(BOX_LO - p, p - BOX_HI)  # > 0 outside along an axis
    outside = np.linalg.norm(np.maximum(q, 0), axis=-1)
    inside = np.minimum(np.max(q, axis=-1), 0)
    return -(outside + inside)


def _model(voxel_mm: float = 0.25, shift_mm: float = 0.0) -> TsdfModel:
    lo = np.array([3.0, -6.0, 2.0]) + shift_mm
    n = (np.array([20.0, 16.0, 14.0]) / voxel_mm).astype(int)
    T = np.diag([voxel_mm] * 3 + [1.0])
    T[:3, 3] = lo
    ijk = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), axis=-1)
    p = ijk * voxel_mm + lo
    tsdf = np.clip(_box_sdf(p) / TRUNC_MM, -1, 1).astype(np.float32)
    return TsdfModel(
        tsdf=tsdf,
        weight=np.ones(tuple(n), np.float32),
        T_world_from_voxel=T,
        voxel_size_mm=voxel_mm,
        trunc_mm=TRUNC_MM,
    )


def _ct_world() -> np.ndarray:
    ijk = np.stack(np.meshgrid(*[np.arange(k) for k in CT_SHAPE], indexing="ij"), axis=-1)
    return ijk @ T_CT[:3, :3].T + T_CT[:3, 3]


def test_label_ct_exactly_the_box_becomes_air():
    ct = CtVolume(np.ones(CT_SHAPE, np.uint8), T_CT, "label")
    res = updated_ct(ct, _model())
    truth = _box_sdf(_ct_world()) > 0
    assert truth.sum() == 4 * 5 * 5
    assert np.array_equal(res.removed, truth)
    assert np.array_equal(res.volume.data, np.where(truth, 0, 1).astype(np.uint8))
    assert res.volume.data.dtype == np.uint8
    assert removed_dice(res.removed, truth) == 1.0


def test_intensity_ct_air_inside_partial_volume_at_the_boundary():
    hu = np.full(CT_SHAPE, 40, np.int16)
    ct = CtVolume(hu, T_CT, "intensity")
    res = updated_ct(ct, _model())
    d = _box_sdf(_ct_world())
    truth = d > 0
    assert np.array_equal(res.removed, truth)
    # analytic partial volume: f = clip(0.5 - d / 1 mm, 0, 1) on removed voxels and their
    # tissue neighbours; HU = -1000 + 1040 f
    expected = np.rint(-1000 + 1040 * np.clip(0.5 - d, 0, 1)).astype(np.int16)
    from scipy import ndimage

    rim = ndimage.binary_dilation(truth)
    want = np.where(rim, expected, hu)
    assert np.array_equal(res.volume.data, want)
    # along x the box spans 6.7..10.7 mm, centres at integers: removed centre 7 is 0.3 mm
    # inside (f = 0.2 -> -792 HU), tissue centre 11 is 0.3 mm outside (f = 0.8 -> -168 HU,
    # the new boundary's partial volume), centre 6 is 0.7 mm outside (f = 1, unchanged);
    # the other faces lie half way between centres: exactly air / unchanged tissue
    assert set(np.unique(res.volume.data[truth]).tolist()) == {-1000, -792}
    assert set(np.unique(res.volume.data[~truth]).tolist()) == {-168, 40}


def test_export_ct_cli_keeps_grid_header_and_orientation(tmp_path: Path):
    src = tmp_path / "ct.nii.gz"
    write_ct_volume(src, np.full(CT_SHAPE, 40, np.int16), T_CT)
    _model().save(tmp_path / "m.npz")
    out = tmp_path / "updated.nii.gz"
    argv = ["export-ct", "--model", str(tmp_path / "m.npz"), "--ct", str(src), "--out", str(out)]
    assert main([*argv, "--kind", "intensity"]) == 0  # all 40 HU: auto would say labels
    a, b = nib.load(src), nib.load(out)
    assert b.shape == a.shape and b.get_data_dtype() == a.get_data_dtype()
    assert np.allclose(a.affine, b.affine) and nib.aff2axcodes(b.affine) == ("R", "P", "S")
    assert int(b.header["sform_code"]) == int(a.header["sform_code"]) == 1
    got = read_ct_volume(out)
    assert np.array_equal(got.data < -480, _box_sdf(_ct_world()) > 0)
    # label CT through NRRD
    write_ct_volume(tmp_path / "lab.nrrd", np.ones(CT_SHAPE, np.uint8), T_CT)
    argv = ["export-ct", "--model", str(tmp_path / "m.npz"), "--ct", str(tmp_path / "lab.nrrd")]
    assert main([*argv, "--out", str(tmp_path / "lab_out.nrrd")]) == 0
    lab = read_ct_volume(tmp_path / "lab_out.nrrd")
    assert np.allclose(lab.T_world_from_voxel, T_CT)
    assert np.array_equal(lab.data == 0, _box_sdf(_ct_world()) > 0)


def test_bad_input_is_refused_naming_the_file_and_nothing_is_written(tmp_path: Path, capsys):
    ct_path = tmp_path / "ct.nii.gz"
    write_ct_volume(ct_path, np.ones(CT_SHAPE, np.uint8), T_CT)
    ct = read_ct_volume(ct_path)
    # a model on another CT: its grid is 500 mm away
    far = _model(voxel_mm=0.5, shift_mm=500.0)
    with pytest.raises(InvalidInputError, match="does not overlap") as info:
        updated_ct(ct, far, model_source="far.npz")
    assert "far.npz" in str(info.value)
    # a CT cropped to a corner: the model's tissue lies mostly outside it
    small = CtVolume(np.ones((3, 3, 3), np.uint8), T_CT, "label", source="small.nii.gz")
    with pytest.raises(InvalidInputError, match="does not cover") as info:
        updated_ct(small, _model(voxel_mm=0.5))
    assert "small.nii.gz" in str(info.value)
    # through the CLI: 4-D CT, NaN affine, another CT's model; no output left behind
    _model(voxel_mm=0.5).save(tmp_path / "m.npz")
    far.save(tmp_path / "far.npz")
    four = tmp_path / "4d.nii.gz"
    img = nib.Nifti1Image(np.ones((*CT_SHAPE, 2), np.uint8), np.eye(4))
    img.set_qform(np.eye(4), code=1)
    nib.save(img, four)
    nan = tmp_path / "nan.nii"
    write_ct_volume(nan, np.ones(CT_SHAPE, np.uint8), T_CT)
    raw = bytearray(nan.read_bytes())
    raw[280:296] = np.array([np.nan, 0, 0, 0], "<f4").tobytes()
    nan.write_bytes(bytes(raw))
    for model, ct_file, match in [
        ("m.npz", four, "4-D"),
        ("m.npz", nan, "NaN"),
        ("far.npz", ct_path, "does not overlap"),
    ]:
        out = tmp_path / "out.nii.gz"
        argv = ["export-ct", "--model", str(tmp_path / model), "--ct", str(ct_file)]
        assert main([*argv, "--out", str(out)]) == 1
        err = capsys.readouterr().err
        assert match in err and (model if "overlap" in match else str(ct_file)) in err, err
        assert not out.exists()
        assert not list(tmp_path.glob(".out.nii.gz*"))


def test_removed_dice():
    a = np.zeros((4, 4, 4), bool)
    b = a.copy()
    assert removed_dice(a, b) == 1.0
    a[0, 0, :2] = True
    b[0, 0, 1:3] = True
    assert removed_dice(a, b) == pytest.approx(0.5)


# a slab of CT tissue that the preoperative model already holds as free space (CT detail
# thinner than the model's voxels), away from the removed box
SLAB_LO = np.array([11.0 - 0.3 - 4.0, -5.0 + 9.5, 3.0 + 0.5])
SLAB_HI = np.array([11.0 - 0.3, -5.0 + 11.5, 3.0 + 2.5])


def _slab_sdf(p: np.ndarray) -> np.ndarray:
    q = np.maximum(SLAB_LO - p, p - SLAB_HI)
    return -(np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(np.max(q, axis=-1), 0))


def _sdf_model(sdf, voxel_mm: float = 0.25) -> TsdfModel:
    m = _model(voxel_mm)
    ijk = np.stack(np.meshgrid(*[np.arange(k) for k in m.shape], indexing="ij"), axis=-1)
    p = ijk * voxel_mm + m.T_world_from_voxel[:3, 3]
    tsdf = np.clip(sdf(p) / TRUNC_MM, -1, 1).astype(np.float32)
    return TsdfModel(tsdf, m.weight, m.T_world_from_voxel, voxel_mm, TRUNC_MM)


def test_preop_model_free_space_is_not_removed(tmp_path: Path):
    # The update carved the box; the slab was never tissue in the preoperative model.
    ct = CtVolume(np.ones(CT_SHAPE, np.uint8), T_CT, "label")
    preop = _sdf_model(_slab_sdf)
    updated = _sdf_model(lambda p: np.maximum(_box_sdf(p), _slab_sdf(p)))
    box = _box_sdf(_ct_world()) > 0
    slab = _slab_sdf(_ct_world()) > 0
    assert box.sum() == 100 and slab.sum() > 0 and not np.any(box & slab)
    assert np.array_equal(updated_ct(ct, updated).removed, box | slab)  # without: both
    assert np.array_equal(updated_ct(ct, updated, preop=preop).removed, box)
    assert not updated_ct(ct, preop, preop=preop).removed.any()  # no update, nothing removed
    # the CLI's --preop-model
    write_ct_volume(tmp_path / "lab.nii.gz", ct.data, T_CT)
    updated.save(tmp_path / "u.npz")
    preop.save(tmp_path / "p.npz")
    argv = ["export-ct", "--model", str(tmp_path / "u.npz"), "--ct", str(tmp_path / "lab.nii.gz")]
    out = tmp_path / "out.nii.gz"
    assert main([*argv, "--preop-model", str(tmp_path / "p.npz"), "--out", str(out)]) == 0
    assert np.array_equal(read_ct_volume(out).data == 0, box)


def test_tissue_an_update_fused_beyond_the_ct_is_no_sign_of_another_ct() -> None:
    """An update may fuse tissue past the CT's box (the endoscope sees beyond it). Given
    the preoperative model, the CT must cover that model's tissue; the updated model's
    extra tissue outside does not refuse the export, and nothing outside is removed."""
    ct = CtVolume(np.ones(CT_SHAPE, np.uint8), T_CT, "label", source="ct.nii.gz")
    box = _model(voxel_mm=0.5)
    pad = ((0, 16), (0, 0), (0, 0))  # 8 mm more along +x, where the CT ends at 20.5 mm

    def padded(tsdf: float, weight: float) -> TsdfModel:
        return replace(
            box,
            tsdf=np.pad(box.tsdf, pad, constant_values=tsdf),
            weight=np.pad(box.weight, pad, constant_values=weight),
        )

    preop = padded(1.0, 0.0)  # the sweep never looked there
    updated = padded(-1.0, 1.0)  # the update fused tissue there
    with pytest.raises(InvalidInputError, match="does not cover the model's grid"):
        updated_ct(ct, updated, model_source="updated.npz")
    result = updated_ct(ct, updated, model_source="updated.npz", preop=preop)
    # The pad lies beyond the CT: the export is that of the model without it.
    alone = updated_ct(ct, preop, model_source="preop.npz", preop=preop)
    assert np.array_equal(result.removed, alone.removed)
    assert np.array_equal(result.volume.data, alone.volume.data)
    # A preoperative model whose own tissue the CT does not cover is still refused.
    with pytest.raises(InvalidInputError, match="preoperative model's observed tissue"):
        updated_ct(ct, updated, model_source="updated.npz", preop=updated)
