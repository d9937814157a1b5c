"""CT volumes land in the LPS world the way SimpleITK (the reader ITK and 3D Slicer share)
puts them, in every orientation; the files the project writes read correctly elsewhere.

References: SimpleITK's world is LPS; its index -> physical point mapping is computed by
ITK from the file's header, independently of :mod:`chisel.io.ct`. Files under test are
written with nibabel or SimpleITK directly (not with the code under test), except where
the writer itself is under test.
"""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
import trimesh
from scipy.spatial.transform import Rotation
from skimage.measure import marching_cubes

from chisel.core.errors import InvalidInputError
from chisel.io.ct import load_ct_surface, read_ct_volume, write_ct_volume

SHAPE = (7, 9, 11)


def _rotation(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


# name -> RAS affine of the file (what NIfTI stores)
RAS_AFFINES: dict[str, np.ndarray] = {}
for _name, _M, _t in [
    ("ras", np.diag([0.5, 0.6, 0.7]), [-10.0, 20.0, 30.0]),
    ("lps", np.diag([-0.5, -0.6, 0.7]), [10.0, -20.0, 30.0]),
    ("flipped_z", np.diag([0.5, 0.6, -0.7]), [1.0, 2.0, 3.0]),
    ("permuted", np.array([[0, 0, 0.8], [0.5, 0, 0], [0, -0.6, 0]]), [5.0, -5.0, 0.0]),
    ("oblique", _rotation(1) @ np.diag([0.5, 0.6, 0.7]), [-3.0, 4.0, 12.0]),
    ("oblique_mirrored", _rotation(2) @ np.diag([-0.5, 0.6, 0.7]), [7.0, 1.0, -2.0]),
]:
    _A = np.eye(4)
    _A[:3, :3] = _M
    _A[:3, 3] = _t
    RAS_AFFINES[_name] = _A


def _data() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(-1000, 1000, size=SHAPE).astype(np.int16)


def _save_nifti(path: Path, data: np.ndarray, ras: np.ndarray, sform: int, qform: int) -> None:
    img = nib.Nifti1Image(data, ras)
    img.set_sform(ras, code=sform)
    img.set_qform(ras, code=qform)
    nib.save(img, path)


def _sitk_world(img: sitk.Image, ijk: np.ndarray) -> np.ndarray:
    return np.array([img.TransformIndexToPhysicalPoint([int(v) for v in p]) for p in ijk])


IJK = np.array([[0, 0, 0], [6, 0, 0], [0, 8, 0], [0, 0, 10], [3, 4, 5], [6, 8, 10]])


@pytest.mark.parametrize("name", sorted(RAS_AFFINES))
@pytest.mark.parametrize(("sform", "qform"), [(1, 1), (2, 0), (0, 1)])
def test_nifti_voxels_land_where_simpleitk_puts_them(tmp_path, name, sform, qform):
    path = tmp_path / f"{name}.nii.gz"
    data = _data()
    _save_nifti(path, data, RAS_AFFINES[name], sform, qform)
    vol = read_ct_volume(path)
    ref = sitk.ReadImage(str(path))
    ours = (vol.T_world_from_voxel @ np.c_[IJK, np.ones(len(IJK))].T).T[:, :3]
    assert np.allclose(ours, _sitk_world(ref, IJK), atol=1e-4)
    # the same voxel holds the same value (SimpleITK's array is indexed [k, j, i])
    assert np.array_equal(vol.data, sitk.GetArrayFromImage(ref).transpose(2, 1, 0))
    assert vol.kind == "intensity"


@pytest.mark.parametrize("name", ["ras", "oblique", "oblique_mirrored"])
def test_nrrd_voxels_land_where_simpleitk_puts_them(tmp_path, name):
    """An NRRD written by SimpleITK (LPS) is read into the same world points."""
    lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ RAS_AFFINES[name]
    spacing = np.linalg.norm(lps[:3, :3], axis=0)
    img = sitk.GetImageFromArray(_data().transpose(2, 1, 0))
    img.SetSpacing(spacing.tolist())
    img.SetDirection((lps[:3, :3] / spacing).ravel().tolist())
    img.SetOrigin(lps[:3, 3].tolist())
    path = tmp_path / "ct.nrrd"
    sitk.WriteImage(img, str(path))
    vol = read_ct_volume(path)
    ref = sitk.ReadImage(str(path))
    ours = (vol.T_world_from_voxel @ np.c_[IJK, np.ones(len(IJK))].T).T[:, :3]
    assert np.allclose(ours, _sitk_world(ref, IJK), atol=1e-4)
    assert np.array_equal(vol.data, sitk.GetArrayFromImage(ref).transpose(2, 1, 0))


@pytest.mark.parametrize("suffix", [".nii.gz", ".nii", ".nrrd"])
@pytest.mark.parametrize("name", ["ras", "oblique_mirrored"])
def test_written_volumes_read_the_same_in_simpleitk(tmp_path, suffix, name):
    """write_ct_volume: SimpleITK finds every voxel at the LPS point it was written for;
    NIfTI files carry RAS affines with sform and qform codes set."""
    T = np.diag([-1.0, -1.0, 1.0, 1.0]) @ RAS_AFFINES[name]  # an LPS voxel -> world map
    path = tmp_path / f"out{suffix}"
    data = _data()
    write_ct_volume(path, data, T)
    ref = sitk.ReadImage(str(path))
    ours = (T @ np.c_[IJK, np.ones(len(IJK))].T).T[:, :3]
    assert np.allclose(ours, _sitk_world(ref, IJK), atol=1e-4)
    assert np.array_equal(data, sitk.GetArrayFromImage(ref).transpose(2, 1, 0))
    if suffix != ".nrrd":
        img = nib.load(path)
        assert int(img.header["sform_code"]) == 1 and int(img.header["qform_code"]) == 1
        assert np.allclose(img.header.get_sform(), img.header.get_qform(), atol=1e-5)
        # nibabel (RAS world) names the directions the voxel axes point in the patient;
        # for an axis-aligned grid they are the LPS map's axes with x and y negated.
        assert nib.aff2axcodes(img.affine) == nib.aff2axcodes(RAS_AFFINES[name])


def test_axis_aligned_lps_grid_reads_as_lps_axes_in_nibabel(tmp_path):
    """A grid whose i, j, k run to the patient's left, posterior, superior (the phantoms'
    grids) must read as ('L', 'P', 'S') in nibabel, as in ITK; the old files read
    ('R', 'A', 'S') there: mirrored."""
    T = np.diag([0.5, 0.5, 0.5, 1.0])
    write_ct_volume(tmp_path / "a.nii.gz", _data(), T)
    assert nib.aff2axcodes(nib.load(tmp_path / "a.nii.gz").affine) == ("L", "P", "S")
    ref = sitk.ReadImage(str(tmp_path / "a.nii.gz"))
    assert np.allclose(np.asarray(ref.GetDirection()).reshape(3, 3), np.eye(3))


def test_rewritten_volume_keeps_its_header(tmp_path):
    """write_ct_volume(like=...) keeps the on-disk type, codes and description."""
    src = tmp_path / "in.nii.gz"
    ras = RAS_AFFINES["oblique"]
    img = nib.Nifti1Image(_data(), ras)
    img.set_sform(ras, code=2)
    img.set_qform(ras, code=2)
    img.header["descrip"] = b"scanner X"
    nib.save(img, src)
    vol = read_ct_volume(src)
    write_ct_volume(tmp_path / "out.nii.gz", vol.data, like=vol, T_world_from_voxel=None)
    out = nib.load(tmp_path / "out.nii.gz")
    assert out.get_data_dtype() == np.int16
    assert int(out.header["sform_code"]) == 2 and int(out.header["qform_code"]) == 2
    assert out.header["descrip"].item() == b"scanner X"
    assert np.allclose(out.affine, ras, atol=1e-5)
    assert np.array_equal(np.asanyarray(out.dataobj), vol.data)


def test_phantom_nifti_overlays_its_mesh(tmp_path):
    """Both CT volumes of a small phantom, read by SimpleITK (LPS world), contour to the
    phantom's mesh within half a voxel; mirrored they would be centimetres off. Every
    NIfTI it wrote reads its axes as L, P, S (the phantom's grid runs along +x, +y, +z of
    its LPS world) in nibabel."""
    from phantoms.cli import main

    out = tmp_path / "ph"
    args = ["generate", "--seed", "3", "--procedure", "bites", "--bites", "1", "--out", str(out)]
    coarse = ["--spacing-mm", "1.0", "--mesh-edge-mm", "1.0", "--mucosa-mm", "1.5"]
    assert main(args + coarse) == 0
    m = json.loads((out / "phantom.json").read_text())
    spacing = m["ct"]["spacing_mm"]
    for step in m["steps"]:
        mesh = trimesh.load(out / step["mesh"], process=False)
        for key, level in (("ct_hu", m["ct"]["iso_hu"]), ("ct_label", 0.5)):
            path = out / step[key]
            assert nib.aff2axcodes(nib.load(path).affine) == ("L", "P", "S")
            ref = sitk.ReadImage(str(path))
            field = sitk.GetArrayFromImage(ref).transpose(2, 1, 0).astype(np.float32)
            if key == "ct_label":
                field = (field > 0).astype(np.float32)
            verts, _, _, _ = marching_cubes(field, level=level)
            D = np.asarray(ref.GetDirection()).reshape(3, 3) * np.asarray(ref.GetSpacing())
            world = verts @ D.T + np.asarray(ref.GetOrigin())
            _, dist, _ = trimesh.proximity.closest_point(mesh, world)
            # HU: the two-voxel ramp puts the iso-surface on the mesh; labels: a voxel
            # centre's label says which side it lies on, so the 0.5 surface is within
            # half a voxel.
            assert np.percentile(dist, 99) <= 0.5 * spacing + 1e-3, (key, dist.max())
        # and through our reader: the surface is oriented outward (normals into air)
        surf = load_ct_surface(out / step["ct_hu"])
        centres = surf.triangles_center + 0.3 * spacing * surf.face_normals
        assert (~mesh.contains(centres[::50])).mean() > 0.95


def _refused(path: Path, match: str) -> None:
    with pytest.raises(InvalidInputError, match=match) as info:
        read_ct_volume(path)
    assert str(path) in str(info.value)


def test_volume_without_orientation_is_refused(tmp_path):
    """sform_code = qform_code = 0: nibabel falls back to a default affine; refused."""
    path = tmp_path / "noorient.nii.gz"
    _save_nifti(path, _data(), RAS_AFFINES["ras"], 0, 0)
    assert nib.load(path).affine is not None  # nibabel would have used a default
    _refused(path, "no orientation")
    with pytest.raises(InvalidInputError, match="no orientation"):
        load_ct_surface(path)
    raw = tmp_path / "nospace.nrrd"
    raw.write_bytes(
        b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\n" + bytes(8)
    )
    _refused(raw, "no patient orientation")


def test_4d_volume_is_refused_but_a_singleton_4th_axis_is_read(tmp_path):
    path = tmp_path / "series.nii.gz"
    _save_nifti(path, np.zeros((*SHAPE, 3), np.int16), RAS_AFFINES["ras"], 1, 1)
    _refused(path, "4-D")
    single = tmp_path / "single.nii.gz"
    _save_nifti(single, _data()[..., None], RAS_AFFINES["ras"], 1, 1)
    assert read_ct_volume(single).data.shape == SHAPE


def test_sheared_volume_is_refused(tmp_path):
    ras = RAS_AFFINES["ras"].copy()
    ras[0, 1] = 0.2  # j axis leans into x
    path = tmp_path / "sheared.nii.gz"
    _save_nifti(path, _data(), ras, 1, 0)
    _refused(path, "sheared")


def test_nan_affine_is_refused(tmp_path):
    """A NaN in the sform (patched into the header bytes: nibabel's save would rewrite it)."""
    path = tmp_path / "nan.nii"
    _save_nifti(path, _data(), RAS_AFFINES["ras"], 1, 0)
    raw = bytearray(path.read_bytes())
    raw[280:296] = np.array([np.nan, 0, 0, 0], "<f4").tobytes()  # srow_x, NIfTI-1 offset 280
    path.write_bytes(bytes(raw))
    assert np.isnan(nib.load(path).header["srow_x"][0])
    _refused(path, "NaN")


def test_other_bad_files_are_refused(tmp_path):
    _refused(tmp_path / "missing.nii.gz", "missing")
    junk = tmp_path / "junk.nii.gz"
    junk.write_bytes(b"junk")
    _refused(junk, "cannot read NIfTI")
    other = tmp_path / "ct.mha"
    other.write_bytes(b"x")
    _refused(other, "unknown CT volume type")
    with pytest.raises(InvalidInputError, match="unknown CT volume type"):
        write_ct_volume(tmp_path / "out.mha", _data(), np.eye(4))
    assert not (tmp_path / "out.mha").exists()
    with pytest.raises(InvalidInputError, match="sheared"):
        write_ct_volume(
            tmp_path / "out.nii.gz",
            _data(),
            np.array([[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
        )
    assert not (tmp_path / "out.nii.gz").exists()
