"""CT volumes in and out, and the preoperative CT segmentation as a world-mm surface.

**The one place that reads volumes and the one place that writes them.** Inside the code
the world frame is DICOM **LPS** (x to the patient's left, y posterior, z superior), in
mm; ``T_world_from_voxel`` maps a voxel index ``(i, j, k)`` to its centre in that frame.
NIfTI's world is **RAS** (x right, y anterior), so a NIfTI affine is converted here and
nowhere else:

    T_world_from_voxel (LPS) = diag(-1, -1, 1, 1) @ nifti_affine (RAS)

* :func:`read_ct_volume` reads NIfTI (``.nii``, ``.nii.gz``, with nibabel) and NRRD
  (``.nrrd``, ``.nhdr``, with SimpleITK, whose world is LPS already) in any orientation:
  RAS or LPS, oblique, flipped axes, negative determinant. Refused, naming the file: a
  NIfTI with ``sform_code = qform_code = 0`` or an NRRD without an anatomical ``space``
  (no orientation: a default affine would put the anatomy inside out and shifted), a
  volume with more than three non-singleton axes, a sheared affine (one that SimpleITK,
  ITK and Slicer cannot represent), a NaN or singular affine.
* :func:`write_ct_volume` writes NIfTI with a RAS affine in both sform and qform (codes
  kept from the volume it copies, else 1 = scanner) or NRRD (SimpleITK, LPS), atomically.
  Given ``like=`` (a volume read by :func:`read_ct_volume`), the NIfTI header is that
  volume's (on-disk data type, scaling, descriptions, codes), so an updated CT keeps its
  header and orientation.

Surfaces (:func:`load_ct_surface`) accept a mesh (``.ply``, ``.stl``, ``.obj``, ``.off``,
``.glb``, vertices in world mm, read with trimesh) or a volume, contoured with
scikit-image marching cubes:

- an *intensity* CT (any value below ``INTENSITY_MIN_HU``, i.e. air at about -1000 HU)
  at ``iso_level`` (default -480 HU, half way between air and soft tissue);
- a *label* volume (all values >= -100) binarised as tissue = label > 0 at 0.5.

Triangles are wound so that normals point out of the tissue into air whatever the sign
of the affine's determinant.
"""

from __future__ import annotations

import gzip
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import trimesh

from chisel.core.atomic import atomic_path, atomic_write_bytes
from chisel.core.errors import (
    EmptyResultError,
    InvalidInputError,
    ResourceLimitError,
    out_of_memory_names,
)
from chisel.core.geometry import transform_points
from chisel.io.limits import (
    MAX_ARRAY_BYTES,
    MAX_PLACEMENT_MM,
    MAX_VOXEL_SIZE_MM,
    MIN_VOXEL_SIZE_MM,
)
from chisel.io.meshfile import READABLE_MESH_SUFFIXES, read_mesh_file
from chisel.io.nrrd_header import check_nrrd_data_files

NIFTI_SUFFIXES = (".nii", ".nii.gz")
NRRD_SUFFIXES = (".nrrd", ".nhdr")
VOLUME_SUFFIXES = NIFTI_SUFFIXES + NRRD_SUFFIXES
DEFAULT_HU_ISO = -480.0
"""Iso-level for intensity CT, HU: half way between air (-1000) and soft tissue (~40)."""
LABEL_ISO = 0.5
"""Iso-level between air (0) and tissue (1) of a binarised label volume."""
INTENSITY_MIN_HU = -100.0
"""A volume with any value below this is taken to be intensity CT, not labels."""
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
"""(4, 4) the RAS <-> LPS flip (its own inverse): negates x and y."""
SHEAR_TOLERANCE = 1e-4
"""Largest |cosine| between two voxel axes accepted as orthogonal (NIfTI stores float32)."""
_NRRD_SPACES = ("left-posterior-superior", "right-anterior-superior", "left-anterior-superior")
"""NRRD anatomical spaces that ITK converts to LPS (others carry no patient orientation)."""
_NIFTI_MM_PER_UNIT = {"mm": 1.0, "meter": 1000.0, "micron": 1e-3, "unknown": 1.0}
VolumeKind = Literal["intensity", "label"]


@dataclass(frozen=True, eq=False)
class CtVolume:
    """A CT volume in the LPS world.

    data : (X, Y, Z) numeric array, HU (intensity) or integer labels (0 = air), indexed
        like ``T_world_from_voxel``'s input (i along the file's first axis).
    T_world_from_voxel : (4, 4) float64, voxel index -> voxel centre in LPS world mm.
    kind : "intensity" (HU) or "label".
    source : the file it was read from ("" for a volume made in memory).
    file_format : "nifti" or "nrrd" (what it was read from; None when made in memory).
    header : the NIfTI header as read (nibabel ``Nifti1Header`` / ``Nifti2Header``), kept
        so that :func:`write_ct_volume` can write the same header back; None otherwise.
    """

    data: np.ndarray
    T_world_from_voxel: np.ndarray
    kind: VolumeKind
    source: str = ""
    file_format: Literal["nifti", "nrrd"] | None = None
    header: Any = None

    def __post_init__(self) -> None:
        src = self.source or "volume"
        if np.ndim(self.data) != 3:
            raise InvalidInputError(src, f"expected a 3-D volume, got shape {np.shape(self.data)}")
        object.__setattr__(
            self, "T_world_from_voxel", check_voxel_affine(self.T_world_from_voxel, src)
        )
        if self.kind not in ("intensity", "label"):
            raise InvalidInputError(src, f"kind must be 'intensity' or 'label', got {self.kind!r}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.data.shape)  # type: ignore[return-value]

    @property
    def spacing_mm(self) -> np.ndarray:
        """(3,) float64 voxel size along i, j, k, mm."""
        return np.linalg.norm(self.T_world_from_voxel[:3, :3], axis=0)


def check_voxel_affine(T: np.ndarray, source: str | Path) -> np.ndarray:
    """Return ``T`` as a (4, 4) float64 voxel -> world affine, or raise naming ``source``.

    Refused: not 4x4, NaN/inf, a bottom row other than [0, 0, 0, 1], singular, a voxel
    spacing or an origin beyond the grids' bounds (:mod:`chisel.io.limits`), sheared
    (voxel axes not orthogonal within :data:`SHEAR_TOLERANCE`). Rotations (oblique),
    flips and a negative determinant are fine.
    """
    A = np.asarray(T, dtype=np.float64)
    if A.shape != (4, 4):
        raise InvalidInputError(source, f"affine must be 4x4, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise InvalidInputError(source, f"affine contains NaN/inf: {A.tolist()}")
    if not np.allclose(A[3], [0, 0, 0, 1]):
        raise InvalidInputError(source, f"affine bottom row must be [0, 0, 0, 1], got {A[3]}")
    M = A[:3, :3]
    norms = np.linalg.norm(M, axis=0)
    if norms.min() < 1e-9 or abs(np.linalg.det(M)) < 1e-12 * norms.prod():
        raise InvalidInputError(source, f"affine is singular (voxel size 0): {M.tolist()}")
    if norms.min() < MIN_VOXEL_SIZE_MM or norms.max() > MAX_VOXEL_SIZE_MM:
        raise InvalidInputError(
            source,
            f"voxel spacing {norms.tolist()} mm is outside [{MIN_VOXEL_SIZE_MM:g}, "
            f"{MAX_VOXEL_SIZE_MM:g}] mm: not a CT's (metres or a unit error?)",
        )
    if np.abs(A[:3, 3]).max() > MAX_PLACEMENT_MM:
        raise InvalidInputError(
            source,
            f"affine places the volume's origin at {A[:3, 3].tolist()} mm, farther than "
            f"{MAX_PLACEMENT_MM:g} mm from the world origin: not a patient's CT frame",
        )
    cos = (M.T @ M) / np.outer(norms, norms)
    worst = float(np.abs(cos - np.eye(3)).max())
    if worst > SHEAR_TOLERANCE:
        raise InvalidInputError(
            source,
            f"affine is sheared (voxel axes not orthogonal, |cos| up to {worst:.3g}); "
            "resample the volume onto an orthogonal grid first",
        )
    return A


def _volume_kind(data: np.ndarray, kind: Literal["auto", "intensity", "label"], source: str):
    if kind == "auto":
        return "intensity" if float(np.min(data)) < INTENSITY_MIN_HU else "label"
    if kind not in ("intensity", "label"):
        raise InvalidInputError(source, f"kind must be auto, intensity or label, got {kind!r}")
    return kind


def _squeeze_to_3d(data: np.ndarray, source: str) -> np.ndarray:
    """Drop singleton axes beyond the third; refuse 4-D (or more) data and < 3 axes."""
    shape = data.shape
    if len(shape) < 3 or any(n != 1 for n in shape[3:]):
        raise InvalidInputError(
            source,
            f"expected a 3-D volume (a singleton 4th axis is fine), got shape {shape}"
            + ("; a 4-D series is not a CT" if len(shape) > 3 else ""),
        )
    return data.reshape(shape[:3])


def _suffix_kind(path: Path) -> Literal["nifti", "nrrd"] | None:
    name = path.name.lower()
    if name.endswith(NIFTI_SUFFIXES):
        return "nifti"
    if name.endswith(NRRD_SUFFIXES):
        return "nrrd"
    return None


def read_ct_volume(
    path: str | Path, kind: Literal["auto", "intensity", "label"] = "auto"
) -> CtVolume:
    """Read a NIfTI or NRRD CT into the LPS world (see the module docstring).

    kind : "auto" takes "intensity" when any value is below -100, else "label".
    Raises :class:`InvalidInputError` naming ``path`` on a missing or unreadable file,
    no orientation, 4-D data, a sheared, NaN or singular affine; its subclass
    :class:`OutsideManifestError` for an NRRD header whose ``data file`` lies outside the
    header's folder (:func:`check_nrrd_data_files`).
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "CT volume file is missing")
    fmt = _suffix_kind(path)
    if fmt is None:
        raise InvalidInputError(path, f"unknown CT volume type; expected one of {VOLUME_SUFFIXES}")
    with out_of_memory_names(path, "reading this CT volume"):
        if fmt == "nifti":
            data, T, header = _read_nifti(path)
        else:
            data, T = _read_nrrd(path)
            header = None
    if data.dtype.kind not in "biuf":  # RGB (structured) or complex voxels
        raise InvalidInputError(
            path, f"voxels must be real numbers (CT values or labels), got data type {data.dtype}"
        )
    if data.size == 0:
        raise InvalidInputError(path, f"volume is empty, shape {data.shape}")
    if np.issubdtype(data.dtype, np.floating) and not np.all(np.isfinite(data)):
        raise InvalidInputError(path, "volume contains NaN/inf values")
    return CtVolume(
        data=data,
        T_world_from_voxel=T,
        kind=_volume_kind(data, kind, str(path)),
        source=str(path),
        file_format=fmt,
        header=header,
    )


def _read_nifti(path: Path) -> tuple[np.ndarray, np.ndarray, Any]:
    import nibabel as nib

    try:
        # nib.load is annotated FileBasedImage; a .nii / .nii.gz loads as a Nifti1Image
        # (Nifti2Image is a subclass)
        img = cast("nib.Nifti1Image", nib.load(str(path)))
        header = img.header
        sform_code = int(header["sform_code"])
        qform_code = int(header["qform_code"])
    except MemoryError:  # named as such by read_ct_volume
        raise
    except Exception as exc:  # nibabel raises many types on corrupt files
        raise InvalidInputError(path, f"cannot read NIfTI: {exc}") from None
    if sform_code == 0 and qform_code == 0:
        raise InvalidInputError(
            path,
            "NIfTI has no orientation (sform_code = qform_code = 0): the voxel-to-world "
            "affine is unknown; set the sform or qform (e.g. in 3D Slicer or with nibabel)",
        )
    # nibabel's rule (the NIfTI standard's): the sform when its code is set, else the qform.
    ras = header.get_sform() if sform_code > 0 else header.get_qform()
    ras = check_voxel_affine(ras, path)  # NaN / sheared / singular before any use
    try:
        unit = header.get_xyzt_units()[0]
    except KeyError:  # codes 4-7 of the spatial bits are not units
        code = int(header["xyzt_units"]) & 0x07
        raise InvalidInputError(
            path, f"NIfTI xyzt_units has spatial unit code {code}, which is no unit (0-3)"
        ) from None
    ras = ras.copy()
    ras[:3, :] *= _NIFTI_MM_PER_UNIT.get(unit, 1.0)
    _check_nifti_data_size(path, header, int(getattr(img.dataobj, "offset", 0)))
    try:
        data = np.asanyarray(img.dataobj)
    except MemoryError:  # named as such by read_ct_volume
        raise
    except Exception as exc:
        # nibabel's messages span lines and repeat the path; the CLI prints one line.
        why = " ".join(str(exc).replace(str(path), "").split())
        raise InvalidInputError(path, f"cannot read NIfTI data: {why}") from None
    data = _squeeze_to_3d(np.asarray(data), str(path))
    return data, LPS_FROM_RAS @ ras, header.copy()


def _check_nifti_data_size(path: Path, header: Any, offset: int) -> None:
    """Refuse data that the header declares past :data:`MAX_ARRAY_BYTES` (scaled to
    float64 when a slope or intercept is set) or beyond the end of the file, before
    nibabel allocates it (for a .nii.gz it allocates the declared size up front)."""
    try:
        shape = tuple(int(n) for n in header.get_data_shape())
        itemsize = int(header.get_data_dtype().itemsize)
        slope, inter = header.get_slope_inter()
    except Exception as exc:  # noqa: BLE001 - nibabel raises many types on bad headers
        raise InvalidInputError(path, f"cannot read NIfTI header: {exc}") from None
    count = 1
    for n in shape:
        count *= n
    stored = count * itemsize
    scaled = count * 8 if (slope, inter) != (None, None) else stored
    if max(stored, scaled) > MAX_ARRAY_BYTES:
        raise ResourceLimitError(
            path,
            f"NIfTI declares {shape} voxels of {itemsize} bytes ({max(stored, scaled)} bytes "
            f"in memory), over the limit of {MAX_ARRAY_BYTES} bytes",
        )
    if path.name.lower().endswith(".gz"):
        with open(path, "rb") as fh:  # gzip's trailer: the unpacked size modulo 2**32
            fh.seek(-4, os.SEEK_END)
            available = int.from_bytes(fh.read(4), "little")
        if offset + stored >= 2**32:
            return  # cannot tell from the trailer; the limit above bounds it
    else:
        available = path.stat().st_size
    if offset + stored > available:
        raise InvalidInputError(
            path,
            f"NIfTI declares {stored} bytes of data at offset {offset} but the file holds "
            f"{available} bytes (truncated, or a wrong dim/datatype in the header?)",
        )


def _read_nrrd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import SimpleITK as sitk

    check_nrrd_data_files(path)
    try:
        reader = sitk.ImageFileReader()
        reader.SetFileName(str(path))
        reader.ReadImageInformation()
        keys = set(reader.GetMetaDataKeys())
        space = reader.GetMetaData("NRRD_space") if "NRRD_space" in keys else None
        size = reader.GetSize()
        ncomp = reader.GetNumberOfComponents()
    except MemoryError:  # named as such by read_ct_volume
        raise
    except Exception as exc:  # SimpleITK raises RuntimeError with ITK's message
        raise InvalidInputError(path, f"cannot read NRRD: {str(exc).strip()}") from None
    if space not in _NRRD_SPACES:
        raise InvalidInputError(
            path,
            f"NRRD has no patient orientation (space: {space or 'missing'}); expected one of "
            f"{_NRRD_SPACES} with space directions and origin",
        )
    if ncomp != 1:
        raise InvalidInputError(path, f"expected one value per voxel, got {ncomp} components")
    if len(size) < 3 or any(n != 1 for n in size[3:]):
        raise InvalidInputError(path, f"expected a 3-D volume, got size {tuple(size)}")
    try:
        img = reader.Execute()
        if img.GetDimension() > 3:
            img = img[:, :, :, 0]
    except MemoryError:  # named as such by read_ct_volume
        raise
    except Exception as exc:
        raise InvalidInputError(path, f"cannot read NRRD data: {str(exc).strip()}") from None
    D = np.asarray(img.GetDirection(), dtype=np.float64).reshape(3, 3)
    T = np.eye(4)
    T[:3, :3] = D @ np.diag(img.GetSpacing())
    T[:3, 3] = img.GetOrigin()
    data = np.ascontiguousarray(sitk.GetArrayFromImage(img).transpose(2, 1, 0))
    return data, check_voxel_affine(T, path)


def nifti_bytes(
    volume: CtVolume | np.ndarray,
    T_world_from_voxel: np.ndarray | None = None,
    like: CtVolume | None = None,
    description: str = "",
    compress: bool = True,
) -> bytes:
    """A NIfTI file's bytes with a RAS affine (sform and qform both set).

    NIfTI-1, or NIfTI-2 when the header copied from ``like`` is one.
    volume : a :class:`CtVolume`, or an (X, Y, Z) array with ``T_world_from_voxel``
        ((4, 4) voxel -> LPS world mm; default: ``like``'s).
    like : a volume read from NIfTI whose header (on-disk data type, codes, description)
        is kept.
    compress : gzip with a zero mtime (equal volumes give equal bytes).
    """
    import nibabel as nib

    data, T = _data_and_affine(volume, T_world_from_voxel, like)
    ras = LPS_FROM_RAS @ T
    base = like if like is not None else (volume if isinstance(volume, CtVolume) else None)
    header = base.header.copy() if base is not None and base.header is not None else None
    if header is not None:
        image_class = nib.Nifti2Image if isinstance(header, nib.Nifti2Header) else nib.Nifti1Image
        img = image_class(data, ras, header=header)
        sform_code = int(header["sform_code"]) or 1
        qform_code = int(header["qform_code"]) or sform_code
    else:
        img = nib.Nifti1Image(data, ras)
        img.header.set_data_dtype(data.dtype)
        sform_code = qform_code = 1
    img.header.set_xyzt_units(xyz="mm")
    img.set_sform(ras, code=sform_code)
    img.set_qform(ras, code=qform_code)
    if description:
        img.header["descrip"] = description.encode("ascii", "replace")[:79]
    raw = img.to_bytes()
    return gzip.compress(raw, compresslevel=6, mtime=0) if compress else raw


def _data_and_affine(
    volume: CtVolume | np.ndarray,
    T_world_from_voxel: np.ndarray | None,
    like: CtVolume | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    if T_world_from_voxel is None and like is not None and not isinstance(volume, CtVolume):
        T_world_from_voxel = like.T_world_from_voxel
    if isinstance(volume, CtVolume):
        data = volume.data
        T = volume.T_world_from_voxel if T_world_from_voxel is None else T_world_from_voxel
    else:
        if T_world_from_voxel is None:
            raise InvalidInputError("T_world_from_voxel", "required with a bare array (or like=)")
        data, T = volume, T_world_from_voxel
    data = np.asarray(data)
    if data.ndim != 3:
        raise InvalidInputError("volume", f"expected a 3-D volume, got shape {data.shape}")
    return data, check_voxel_affine(T, "T_world_from_voxel")


def write_ct_volume(
    path: str | Path,
    volume: CtVolume | np.ndarray,
    T_world_from_voxel: np.ndarray | None = None,
    like: CtVolume | None = None,
    description: str = "",
) -> None:
    """Write a volume atomically: NIfTI (RAS affine) or NRRD (LPS), by ``path``'s suffix.

    volume, T_world_from_voxel, like, description : as in :func:`nifti_bytes`. Nothing is
    written when the input is refused.
    """
    path = Path(path)
    name = path.name.lower()
    if name.endswith(NIFTI_SUFFIXES):
        data = nifti_bytes(
            volume, T_world_from_voxel, like, description, compress=name.endswith(".gz")
        )
        atomic_write_bytes(path, data)
    elif name.endswith(".nrrd"):
        _write_nrrd(path, *_data_and_affine(volume, T_world_from_voxel, like))
    else:
        raise InvalidInputError(
            path, "unknown CT volume type to write; expected .nii, .nii.gz or .nrrd"
        )


def _write_nrrd(path: Path, data: np.ndarray, T: np.ndarray) -> None:
    import SimpleITK as sitk

    spacing = np.linalg.norm(T[:3, :3], axis=0)
    img = sitk.GetImageFromArray(np.ascontiguousarray(data.transpose(2, 1, 0)))
    img.SetSpacing([float(s) for s in spacing])
    img.SetDirection([float(v) for v in (T[:3, :3] / spacing).ravel()])
    img.SetOrigin([float(v) for v in T[:3, 3]])
    with atomic_path(path, suffix=".nrrd") as tmp:
        sitk.WriteImage(img, str(tmp), useCompression=True)


def surface_from_volume(
    volume: np.ndarray,
    T_world_from_voxel: np.ndarray,
    kind: Literal["auto", "intensity", "label"] = "auto",
    iso_level: float | None = None,
    source: str = "volume",
) -> trimesh.Trimesh:
    """Marching-cubes surface of a CT volume, vertices in world mm, normals into air.

    volume : (X, Y, Z) numeric, HU (intensity) or integer labels (0 = air).
    T_world_from_voxel : (4, 4) float64 voxel index -> world mm (LPS).
    kind : "intensity" contours ``iso_level`` (default -480 HU); "label" contours tissue =
        label > 0 at 0.5; "auto" picks "intensity" when any value is below -100.
    """
    from skimage.measure import marching_cubes

    vol = np.asarray(volume)
    if vol.ndim != 3 or min(vol.shape) < 2:
        raise InvalidInputError(source, f"expected a 3-D volume, got shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise InvalidInputError(source, "volume contains NaN/inf")
    T = check_voxel_affine(T_world_from_voxel, source)
    kind = _volume_kind(vol, kind, source)
    if kind == "label":
        field = (vol > 0).astype(np.float32)
        level = LABEL_ISO if iso_level is None else float(iso_level)
    else:
        field = vol.astype(np.float32)
        level = DEFAULT_HU_ISO if iso_level is None else float(iso_level)
    if not (float(field.min()) < level < float(field.max())):
        raise EmptyResultError(
            f"{source}: iso-level {level} is outside the volume's range "
            f"{float(field.min())}..{float(field.max())}: no surface"
        )
    # The field is high in tissue; with gradient_direction="ascent" scikit-image winds
    # the triangles so that (right-hand rule, index space) normals point to lower values,
    # i.e. out of the tissue into air.
    verts, faces, _, _ = marching_cubes(
        field, level=level, allow_degenerate=False, gradient_direction="ascent"
    )
    if len(faces) == 0:
        raise EmptyResultError(f"{source}: marching cubes found no surface at {level}")
    if np.linalg.det(T[:3, :3]) < 0:  # a mirroring affine flips the winding: undo it
        faces = faces[:, ::-1]
    return trimesh.Trimesh(transform_points(T, verts), np.ascontiguousarray(faces), process=False)


def load_ct_surface(
    path: str | Path,
    kind: Literal["auto", "intensity", "label"] = "auto",
    iso_level: float | None = None,
) -> trimesh.Trimesh:
    """Read a CT segmentation (mesh, NIfTI or NRRD; see the module docstring) as a
    world-mm (LPS) mesh."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "CT segmentation file is missing")
    name = path.name.lower()
    if name.endswith(VOLUME_SUFFIXES):
        vol = read_ct_volume(path, kind)
        with out_of_memory_names(path, "meshing this CT volume"):
            return surface_from_volume(
                vol.data, vol.T_world_from_voxel, vol.kind, iso_level, source=str(path)
            )
    if name.endswith(READABLE_MESH_SUFFIXES):
        return read_mesh_file(path, "CT segmentation mesh", READABLE_MESH_SUFFIXES)
    raise InvalidInputError(
        path,
        f"unknown CT segmentation type; expected one of {READABLE_MESH_SUFFIXES + VOLUME_SUFFIXES}",
    )
