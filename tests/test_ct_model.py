"""The whole-CT preoperative model (chisel.ct_model) against analytic signed distances.

Scenes: a spherical air cavity in tissue and a two-chamber box (two air boxes separated by
a wall). The camera sits in one place and sees only part of the walls; the model must
hold every wall inside the truncation band, including those no camera sees.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from chisel.build import BuildConfig, build_preop_model
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, look_at, transform_points
from chisel.ct_model import ct_from_mesh, ct_from_volume
from chisel.model import TsdfModel

VOXEL_MM = 0.5
TRUNC_MM = 2.0
CAM = Camera.from_fov(64, 48, 70.0)


def _grid(lo: float, hi: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """CT grid points (I, J, K, 3) mm and its T_world_from_voxel (a cube lo..hi)."""
    n = int(round((hi - lo) / spacing)) + 1
    T = np.diag([spacing, spacing, spacing, 1.0])
    T[:3, 3] = lo
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).astype(float)
    return transform_points(T, ijk.reshape(-1, 3)).reshape(n, n, n, 3), T


def _sphere_sd(p: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance of the air sphere: + inside (air), - in the tissue around it."""
    return radius - np.linalg.norm(p, axis=-1)


def _box_sd(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Signed distance of an air box: + inside, - outside (exact Euclidean)."""
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(p - c) - h
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(np.max(q, axis=-1), 0.0)
    return -(outside + inside)


CH_A = (np.array([-8.0, -6.0, -6.0]), np.array([-1.0, 6.0, 6.0]))
CH_B = (np.array([1.0, -6.0, -6.0]), np.array([8.0, 6.0, 6.0]))
"""Two air chambers separated by a 2 mm wall at x in [-1, 1]."""


def _chambers_sd(p: np.ndarray) -> np.ndarray:
    return np.maximum(_box_sd(p, *CH_A), _box_sd(p, *CH_B))


def _model_points(model: TsdfModel) -> np.ndarray:
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in model.shape], indexing="ij"), axis=-1)
    return transform_points(model.T_world_from_voxel, ijk.reshape(-1, 3).astype(float)).reshape(
        *model.shape, 3
    )


def _check_band(model: TsdfModel, truth_sd: np.ndarray, sel: np.ndarray, tol_mm: float) -> None:
    """Model distance vs truth inside the band (|sd| < trunc - tol) over ``sel``."""
    band = sel & (np.abs(truth_sd) < TRUNC_MM - tol_mm)
    assert band.sum() > 200
    err = np.abs(model.distance_mm()[band] - truth_sd[band])
    assert err.max() <= tol_mm, f"max error {err.max():.3f} mm"
    assert np.all(model.weight[band] > 0)
    # Beyond the band the TSDF is clipped to the sign of the truth.
    far = sel & (np.abs(truth_sd) > TRUNC_MM + tol_mm)
    np.testing.assert_array_equal(model.tsdf[far], np.sign(truth_sd[far]).astype(np.float32))


def _sphere_pose() -> np.ndarray:
    # Looks along +z from near the centre: the hemisphere z < 0 is never seen.
    return look_at([0.0, 0.0, -2.0], [0.0, 0.0, 10.0], [0.0, -1.0, 0.0])[None]


@pytest.mark.parametrize("kind", ["intensity", "label"])
def test_sphere_cavity_matches_the_analytic_signed_distance(kind: str) -> None:
    radius = 8.0
    pts, T = _grid(-12.0, 12.0, VOXEL_MM if kind == "label" else 1.0)
    sd = _sphere_sd(pts, radius)
    # Intensity: HU linear in the distance, -480 on the sphere; labels: 0 air, 1 tissue.
    vol = (
        (-480.0 - 100.0 * sd).astype(np.float32)
        if kind == "intensity"
        else (sd < 0).astype(np.uint8)
    )
    ct = ct_from_volume(vol, T, kind)
    model = build_preop_model(None, CAM, _sphere_pose(), BuildConfig(VOXEL_MM, TRUNC_MM), ct=ct)
    assert model.build == "ct" and model.ct_sha256 == ct.fingerprint
    P = _model_points(model)
    truth = _sphere_sd(P, radius)
    inner = np.all(np.abs(P) < 11.0, axis=-1)  # away from the CT's border
    # Marching cubes of a linear field is exact to float precision; of a binary label
    # map, the surface lies between the voxel centres: within half a CT voxel.
    tol = 0.05 if kind == "intensity" else 0.5 * VOXEL_MM + 0.05
    _check_band(model, truth, inner, tol)
    unseen = inner & (P[..., 2] < -3.0)  # behind the camera: no preop frame sees it
    _check_band(model, truth, unseen, tol)


def test_two_chamber_box_holds_the_chamber_no_camera_sees() -> None:
    pts, T = _grid(-11.0, 11.0, 0.5)
    sd = _chambers_sd(pts)
    vol = (-480.0 - 100.0 * np.clip(sd, -5, 5)).astype(np.float32)
    ct = ct_from_volume(vol, T, "intensity")
    pose = look_at([-4.5, 0.0, 0.0], [-8.0, 0.0, 0.0], [0.0, -1.0, 0.0])[None]  # away from B
    model = build_preop_model(None, CAM, pose, BuildConfig(VOXEL_MM, TRUNC_MM), ct=ct)
    P = _model_points(model)
    truth = _chambers_sd(P)
    inner = np.all(np.abs(P) < 10.0, axis=-1)
    # Box edges and corners: marching cubes cuts a corner by up to a fraction of a voxel.
    not_edge = np.sum(np.abs(np.abs(P) - np.array([8.0, 6.0, 6.0])) < 1.0, axis=-1) < 2
    _check_band(model, truth, inner & not_edge, 0.15)
    chamber_b = inner & not_edge & (P[..., 0] > 1.0)
    _check_band(model, truth, chamber_b, 0.15)
    # The paper's sweep-only build never saw chamber B: unobserved (weight 0) there.
    sweep = build_preop_model(ct.surface, CAM, pose, BuildConfig(VOXEL_MM, TRUNC_MM))
    assert sweep.build == "sweep"
    band_b = chamber_b & (np.abs(truth) < 1.0)
    assert np.all(sweep.weight[band_b] == 0)


def test_closed_mesh_gives_the_same_model_as_the_volume() -> None:
    # Open3D's signed distance of a closed mesh is an independent route to the same field.
    radius = 8.0
    mesh = trimesh.creation.box(extents=[24, 24, 24]).difference(
        trimesh.creation.icosphere(subdivisions=5, radius=radius), engine="manifold"
    )
    ct = ct_from_mesh(mesh, "sphere.ply")
    model = build_preop_model(None, CAM, _sphere_pose(), BuildConfig(VOXEL_MM, TRUNC_MM), ct=ct)
    P = _model_points(model)
    inner = np.all(np.abs(P) < 9.5, axis=-1)  # >= 2.5 mm from the block's outer faces
    # An icosphere of 5 subdivisions is within ~0.01 mm of the sphere at this radius.
    _check_band(model, _sphere_sd(P, radius), inner, 0.05)


def test_model_file_records_the_build_and_loads_old_files(tmp_path) -> None:
    pts, T = _grid(-12.0, 12.0, 1.0)
    vol = (-480.0 - 100.0 * _sphere_sd(pts, 8.0)).astype(np.float32)
    ct = ct_from_volume(vol, T, "intensity")
    model = build_preop_model(None, CAM, _sphere_pose(), BuildConfig(1.0, 3.0), ct=ct)
    back = TsdfModel.load(model.save(tmp_path / "m.npz"))
    assert back.build == "ct" and back.ct_sha256 == ct.fingerprint
    # A file written before the field existed loads as the paper's build.
    with np.load(tmp_path / "m.npz") as z:
        data = {k: z[k] for k in z.files if k not in ("build", "ct_sha256")}
    with open(tmp_path / "old.npz", "wb") as fh:
        np.savez(fh, **data)
    old = TsdfModel.load(tmp_path / "old.npz")
    assert old.build == "sweep" and old.ct_sha256 == ""


def test_unknown_labels_are_refused() -> None:
    pts, T = _grid(-12.0, 12.0, 1.0)
    vol = (_sphere_sd(pts, 8.0) < 0).astype(np.uint8)
    vol[0, 0, 0] = 7
    with pytest.raises(InvalidInputError, match=r"unknown label.*7.*--tissue-labels") as exc:
        ct_from_volume(vol, T, "label", source="labels.nii.gz")
    assert "labels.nii.gz" in str(exc.value)
    # Declared as tissue, it is accepted.
    ct_from_volume(vol, T, "label", tissue_labels=(1, 7))


def test_ct_not_covering_the_preop_view_is_refused() -> None:
    pts, T = _grid(-12.0, 12.0, 1.0)
    vol = (-480.0 - 100.0 * _sphere_sd(pts, 8.0)).astype(np.float32)
    cut = vol[:, :, :16]  # the CT ends at z = 3: the camera looks out of it
    ct = ct_from_volume(cut, T, "intensity", source="cropped.nii.gz")
    with pytest.raises(InvalidInputError, match=r"cropped.nii.gz.*does not cover the preop"):
        build_preop_model(None, CAM, _sphere_pose(), BuildConfig(1.0, 3.0), ct=ct)
    outside = look_at([0.0, 0.0, 20.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0])[None]
    ct_full = ct_from_volume(vol, T, "intensity", source="full.nii.gz")
    with pytest.raises(InvalidInputError, match=r"outside the CT's grid"):
        build_preop_model(None, CAM, outside, BuildConfig(1.0, 3.0), ct=ct_full)


def test_open_mesh_is_refused() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    sphere.update_faces(np.arange(len(sphere.faces) - 4))
    with pytest.raises(InvalidInputError, match=r"closed \(watertight\)"):
        ct_from_mesh(sphere, "open.ply")


@pytest.mark.parametrize("flip", [1.0, -1.0])
def test_model_grid_lies_on_the_ct_lattice_and_keeps_its_labels(flip: float) -> None:
    # A CT whose lattice sits at a fraction of a voxel from any round number (and, flipped,
    # runs along -x and -y as a reader's LPS affine can): the model's voxels are the CT's
    # samples, so its tissue is the label CT's at every voxel, with nothing resampled.
    spacing, n = VOXEL_MM, 49
    T = np.diag([flip * spacing, flip * spacing, spacing, 1.0])
    T[:3, 3] = [-flip * 12.0 + 0.13, -flip * 12.0 - 0.07, -12.0 + 0.21]
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).astype(float)
    pts = transform_points(T, ijk.reshape(-1, 3)).reshape(n, n, n, 3)
    labels = (_sphere_sd(pts, 8.0) < 0).astype(np.uint8)
    ct = ct_from_volume(labels, T, "label")
    model = build_preop_model(None, CAM, _sphere_pose(), BuildConfig(VOXEL_MM, TRUNC_MM), ct=ct)
    in_ct = np.linalg.inv(T) @ model.T_world_from_voxel
    np.testing.assert_allclose(in_ct[:3, 3], np.round(in_ct[:3, 3]), atol=1e-6)
    c = np.rint(transform_points(np.linalg.inv(T), _model_points(model).reshape(-1, 3))).astype(int)
    inside = np.all((c >= 0) & (c < n), axis=1)
    tissue_ct = labels[c[inside, 0], c[inside, 1], c[inside, 2]] == 1
    tissue_model = (model.tsdf.reshape(-1) < 0)[inside]
    assert inside.sum() > 50_000
    np.testing.assert_array_equal(tissue_model, tissue_ct)


def test_a_rotated_ct_leaves_the_grid_where_the_bounds_put_it() -> None:
    from chisel.build import snap_to_lattice

    lo = np.array([1.23, -4.56, 7.89])
    R = trimesh.transformations.rotation_matrix(0.3, [0, 0, 1])
    R[:3, :3] *= 0.5
    np.testing.assert_array_equal(snap_to_lattice(lo, R), lo)
    T = np.diag([0.5, -0.5, 0.625, 1.0])
    T[:3, 3] = [0.1, 0.2, 0.3]
    np.testing.assert_allclose(snap_to_lattice(lo, T), [1.1, -4.8, 7.8], atol=1e-12)
    # A float32 quaternion's rounding (1e-8 rad) is not a rotation.
    T[:3, :3] = trimesh.transformations.rotation_matrix(1e-8, [0, 0, 1])[:3, :3] @ T[:3, :3]
    np.testing.assert_allclose(snap_to_lattice(lo, T), [1.1, -4.8, 7.8], atol=1e-6)
