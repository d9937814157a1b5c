"""The preoperative CT segmentation as a surface mesh in world (CT) millimetres.

Two inputs are accepted:

* a surface mesh (``.ply``, ``.stl``, ``.obj``, ``.off``, ``.glb``) read with trimesh,
  vertices already in world mm;
* a NIfTI volume (``.nii`` / ``.nii.gz``) read with nibabel, turned into a surface with
  scikit-image marching cubes and mapped to world mm with the NIfTI affine (voxel index
  -> world, the same convention as ``T_world_from_voxel``):

  - an *intensity* CT (any value below ``INTENSITY_MIN_HU`` present, i.e. air at about
    -1000 HU) is contoured at ``iso_level`` (default -480 HU, half way between air and
    soft tissue);
  - a *label* volume (all values >= 0) is binarised as tissue = label > 0 and contoured
    at 0.5, the boundary between air (0) and tissue (1).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.geometry import transform_points

MESH_SUFFIXES = (".ply", ".stl", ".obj", ".off", ".glb")
NIFTI_SUFFIXES = (".nii", ".nii.gz")
DEFAULT_HU_ISO = -480.0
"""Iso-level for intensity CT, HU: half way between air (-1000) and soft tissue (~40)."""
LABEL_ISO = 0.5
"""Iso-level between air (0) and tissue (1) of a binarised label volume."""
INTENSITY_MIN_HU = -100.0
"""A volume with any value below this is taken to be intensity CT, not labels."""


def surface_from_volume(
    volume: np.ndarray,
    T_world_from_voxel: np.ndarray,
    kind: Literal["auto", "intensity", "label"] = "auto",
    iso_level: float | None = None,
    source: str = "volume",
) -> trimesh.Trimesh:
    """Marching-cubes surface of a CT volume, vertices in world mm.

    volume : (X, Y, Z) numeric, HU (intensity) or integer labels (0 = air).
    T_world_from_voxel : (4, 4) float64 voxel index -> world mm (the NIfTI affine).
    kind : "intensity" contours ``iso_level`` (default -480 HU); "label" contours tissue =
        label > 0 at 0.5; "auto" picks "intensity" when any value is below -100.
    """
    from skimage.measure import marching_cubes

    vol = np.asarray(volume)
    if vol.ndim != 3 or min(vol.shape) < 2:
        raise InvalidInputError(source, f"expected a 3-D volume, got shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise InvalidInputError(source, "volume contains NaN/inf")
    T = np.asarray(T_world_from_voxel, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or abs(np.linalg.det(T[:3, :3])) < 1e-12:
        raise InvalidInputError(source, f"affine must be a finite invertible 4x4, got {T.tolist()}")
    if kind == "auto":
        kind = "intensity" if float(vol.min()) < INTENSITY_MIN_HU else "label"
    if kind == "label":
        field = (vol > 0).astype(np.float32)
        level = LABEL_ISO if iso_level is None else float(iso_level)
    elif kind == "intensity":
        field = vol.astype(np.float32)
        level = DEFAULT_HU_ISO if iso_level is None else float(iso_level)
    else:
        raise InvalidInputError("kind", f"expected 'auto', 'intensity' or 'label', got {kind!r}")
    if not (float(field.min()) < level < float(field.max())):
        raise EmptyResultError(
            f"{source}: iso-level {level} is outside the volume's range "
            f"{float(field.min())}..{float(field.max())}: no surface"
        )
    verts, faces, _, _ = marching_cubes(field, level=level, allow_degenerate=False)
    if len(faces) == 0:
        raise EmptyResultError(f"{source}: marching cubes found no surface at {level}")
    return trimesh.Trimesh(transform_points(T, verts), faces, process=False)


def load_ct_surface(
    path: str | Path,
    kind: Literal["auto", "intensity", "label"] = "auto",
    iso_level: float | None = None,
) -> trimesh.Trimesh:
    """Read a CT segmentation (mesh or NIfTI, see the module docstring) as a world-mm mesh."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "CT segmentation file is missing")
    name = path.name.lower()
    if name.endswith(NIFTI_SUFFIXES):
        import nibabel as nib

        try:
            img = nib.load(str(path))
            vol = np.asanyarray(img.dataobj)
        except Exception as exc:  # nibabel raises many types on corrupt files
            raise InvalidInputError(path, f"cannot read NIfTI: {exc}") from None
        if vol.ndim == 4 and vol.shape[3] == 1:
            vol = vol[..., 0]
        return surface_from_volume(vol, img.affine, kind, iso_level, source=str(path))
    if name.endswith(MESH_SUFFIXES):
        try:
            mesh = trimesh.load(str(path), force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types on corrupt files
            raise InvalidInputError(path, f"cannot read mesh: {exc}") from None
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise InvalidInputError(path, "mesh has no triangle")
        if not np.all(np.isfinite(mesh.vertices)):
            raise InvalidInputError(path, "mesh vertices contain NaN/inf")
        return mesh
    raise InvalidInputError(
        path, f"unknown CT segmentation type; expected one of {MESH_SUFFIXES + NIFTI_SUFFIXES}"
    )
