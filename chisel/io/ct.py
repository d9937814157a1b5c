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
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import trimesh

from chisel.core.atomic import atomic_path, atomic_write_bytes
from chisel.core.errors import (
    EmptyResultError,
    InvalidInputError,
    OutsideManifestError,
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
from chisel.io.manifest import MAX_MANIFEST_BYTES, check_size, named_path
from chisel.io.meshfile import READABLE_MESH_SUFFIXES, read_mesh_file

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
MAX_NRRD_DATA_FILES = 65536
"""Most detached data files one NRRD header may name (a CT kept as one file per slice has
a few thousand)."""
_NRRD_DATA_FILE_FIELDS = ("data file", "datafile")
MAX_NRRD_FIELD_LINE = 960
"""Longest NRRD header line (and data file path, folder included) read, but for comments,
``key:=value`` lines and ``content``: SimpleITK 2.5's NRRD reader (ITK 5.4) crashes the
process (SIGSEGV) on a line of ~1000 bytes that it cannot parse (its error message quotes
the line) and on a data file path of ~990. Real ones are under 300 bytes."""
_NRRD_FIELDS = frozenset(
    (
        "type", "dimension", "space", "space dimension", "spacedimension", "sizes",
        "spacings", "thicknesses", "axis mins", "axismins", "axis maxs", "axismaxs",
        "space directions", "spacedirections", "centers", "centerings", "kinds", "min",
        "max", "old min", "oldmin", "old max", "oldmax", "endian", "encoding", "line skip",
        "lineskip", "byte skip", "byteskip", "block size", "blocksize", "number",
        "space origin", "spaceorigin", "measurement frame", "measurementframe", "content",
        "labels", "units", "space units", "spaceunits", "sample units", "sampleunits",
        *_NRRD_DATA_FILE_FIELDS,
    )
)  # fmt: skip
"""The NRRD field names (NrrdIO's, either spelling); other ``name: value`` lines are
``key:=value`` pairs or errors."""

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


_NRRD_EOL = re.compile(rb"\r\n|\r|\n")
"""NrrdIO's line ends: a lone ``\\r`` ends a line too."""


def _nrrd_header_lines(path: Path) -> list[str]:
    """The lines of an NRRD header after its magic line, split as NrrdIO splits them, up to
    the blank line that ends it (attached data follows) or the end of a detached header;
    [] for a file that does not start with the NRRD magic (SimpleITK refuses it). Bytes
    that are not UTF-8 are kept (surrogate escapes), so a file name is checked as the reader
    will open it."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_MANIFEST_BYTES + 1)
    except OSError as exc:
        raise InvalidInputError(path, f"cannot read: {exc.strerror or exc}") from None
    if not head.startswith(b"NRRD"):
        return []
    lines: list[str] = []
    pos = 0
    while (end := _NRRD_EOL.search(head, pos)) is not None or pos < len(head):
        stop = end.start() if end is not None else len(head)
        if stop == pos:
            return lines[1:]  # a blank line (or the end of the file) ends the header
        if end is None and len(head) > MAX_MANIFEST_BYTES:
            raise ResourceLimitError(
                path, f"NRRD header runs past {MAX_MANIFEST_BYTES} bytes without its end"
            )
        lines.append(head[pos:stop].decode("utf-8", "surrogateescape"))
        pos = end.end() if end is not None else len(head)
    return lines[1:]


def _nrrd_numbered(template: str, n: int) -> str:
    """``template``'s C conversion ``%d`` / ``%5d`` / ``%05d`` filled with ``n`` (``%%`` is a
    percent sign), as NrrdIO's ``sprintf`` makes a numbered data file's name. A width is
    capped at 255 (the most a file name holds: a wider one cannot be opened anyway)."""

    def fill(m: re.Match[str]) -> str:
        if m.group(0) == "%%":
            return "%"
        digits = m.group(1).lstrip("0")
        width = 255 if len(digits) > 3 else min(int(digits or 0), 255)
        return format(n, f"{'0' if m.group(1).startswith('0') else ''}{width}d")

    return re.sub(r"%%|%(\d*)d", fill, template)


def _nrrd_is_numbered(value: str) -> bool:
    """NrrdIO's test for the ``<template> <min> <max> <step>`` form: the first ``%`` that is
    not ``%%`` starts a ``%d`` conversion (digits allowed in between)."""
    m = re.match(r"(?:[^%]|%%)*%\d*(.)", value)
    return m is not None and m.group(1) == "d"


def _nrrd_data_files(path: Path, lines: list[str]) -> list[str]:
    """The file names an NRRD header's ``data file:`` field makes NrrdIO open (relative to
    the header's folder unless absolute): one name, the lines after ``LIST``, or every
    number of ``<template> <min> <max> <step>``; [] for attached data. Every such field is
    taken (NrrdIO refuses a repeated one; taking all cannot miss the one it reads)."""
    names: list[str] = []
    for k, line in enumerate(lines):
        key, sep, value = line.partition(": ")
        if line.startswith("#") or not sep or key.strip().lower() not in _NRRD_DATA_FILE_FIELDS:
            continue
        value = value.lstrip(" \t")
        if _nrrd_is_numbered(value):
            names += _nrrd_numbered_names(path, value)
        elif value.startswith("LIST"):
            return names + lines[k + 1 :]  # every line after it names a file
        else:
            names.append(value)
    return names


def _nrrd_numbered_names(path: Path, value: str) -> list[str]:
    """The names ``<template> <min> <max> <step>`` stands for (NrrdIO counts from min to
    max inclusive); just ``template`` at min where NrrdIO refuses the numbers."""
    template, rest = value, ""
    if (cut := re.search(r"[ \t]", value)) is not None:
        template, rest = value[: cut.start()], value[cut.start() :]
    nums = re.match(r"\s*([+-]?\d+)\s*([+-]?\d+)\s*([+-]?\d+)", rest)
    if nums is None:
        return [_nrrd_numbered(template, 0)]
    if any(len(x.lstrip("+-")) > 9 for x in nums.groups()):  # C int overflow: undefined
        raise InvalidInputError(path, f"data file numbers out of range: {rest.strip()[:80]!r}")
    lo, hi, step = (int(x) for x in nums.groups())
    if step == 0 or (hi - lo) * step < 0:
        return [_nrrd_numbered(template, lo)]
    check_size(path, "number of NRRD data files", (hi - lo) // step + 1, MAX_NRRD_DATA_FILES)
    return [_nrrd_numbered(template, n) for n in range(lo, hi + (1 if step > 0 else -1), step)]


def _nrrd_line_may_crash(line: str) -> bool:
    """Whether NrrdIO may quote a long ``line`` in an error message (all but a comment, a
    ``key:=value`` pair and ``content``, which it never refuses)."""
    if line.startswith("#"):
        return False
    key, sep, _ = line.partition(": ")
    if sep and key.strip().lower() in _NRRD_FIELDS:
        return key.lower() != "content"
    return ":=" not in line


def check_nrrd_data_files(path: str | Path) -> None:
    """Refuse an NRRD header (``.nhdr``, or a ``.nrrd`` with a ``data file:`` field) that
    names a data file outside its own folder (``../../other/ct.raw``, an absolute path, a
    link that points out): SimpleITK would read it. Raises :class:`OutsideManifestError`
    naming the header, the name and where it leads; :class:`InvalidInputError` for a field
    line or data file path past :data:`MAX_NRRD_FIELD_LINE` (SimpleITK would crash)."""
    path = Path(path)
    root = path.absolute().parent.resolve()
    lines = _nrrd_header_lines(path)
    for k, line in enumerate(lines, 2):
        size = len(line.encode("utf-8", "surrogateescape"))
        if size > MAX_NRRD_FIELD_LINE and _nrrd_line_may_crash(line):
            raise InvalidInputError(
                path,
                f"header line {k} is {size} bytes, over the {MAX_NRRD_FIELD_LINE} read "
                "(SimpleITK's NRRD reader crashes on a longer line it cannot parse)",
            )
    for name in _nrrd_data_files(path, lines):
        full = os.path.join(os.path.dirname(str(path)), name)  # as NrrdIO forms it
        if len(full.encode("utf-8", "surrogateescape")) > MAX_NRRD_FIELD_LINE:
            raise InvalidInputError(
                path,
                f"data file {name[:60]!r}... makes a path over {MAX_NRRD_FIELD_LINE} bytes "
                "(SimpleITK's NRRD reader crashes on a longer one)",
            )
        # NrrdIO does not expand "~"; named_path would.
        value = f"./{name}" if name.startswith("~") else name
        resolved = named_path(path, value, "data file", allow_outside=True)
        if resolved != root and root not in resolved.parents:
            raise OutsideManifestError(
                path,
                f"data file names {name!r}, which is {resolved}, outside the header's folder "
                f"{root}; an NRRD header may only name data files beside it (move the data "
                "file into the header's folder)",
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
