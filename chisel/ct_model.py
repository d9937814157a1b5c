"""The whole CT in the preoperative model: a TSDF initialised with the CT's signed distance.

The paper builds the preoperative model from the CT surface rendered at the preop poses,
so only what those frames see is in the model; a surface behind a lamella is unknown
until an update must reconstruct it from a noisy estimate. Here the model starts from
the CT itself (the paper's discussion names this): every voxel of the grid that the CT
covers takes the signed distance to the CT's tissue surface, normalised by the
truncation and clipped to [-1, 1] like the fused TSDF, with an initial weight.

Two inputs, both pure (no file I/O here; :func:`chisel.io.ct` reads files):

* a volume (intensity HU or integer labels) with its ``T_world_from_voxel``:
  the distance is the Euclidean distance to the marching-cubes iso-surface
  (Open3D ``RaycastingScene.compute_distance``), its sign from the volume itself
  (trilinear interpolation of the tissue field at the point: tissue = negative), so an
  iso-surface left open where tissue touches the CT's border does not flip signs;
* a closed (watertight) segmentation mesh enclosing tissue: Open3D's
  ``compute_signed_distance`` (negative inside).

Sign convention as in :mod:`chisel.model`: + = free space (air), - = tissue.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import transform_points
from chisel.core.raycast import SurfaceQueries
from chisel.io.ct import DEFAULT_HU_ISO, INTENSITY_MIN_HU, LABEL_ISO, surface_from_volume

CtKind = Literal["auto", "intensity", "label"]

TISSUE_LABELS: tuple[int, ...] = (1, 2)
"""Labels counted as tissue in a label volume by default (soft tissue, bone); 0 = air.
Any other value is refused (:func:`ct_from_volume`): a label map of another convention
must say which labels are tissue (``chisel build --tissue-labels``)."""


@dataclass(frozen=True, eq=False)
class CtInput:
    """A CT ready to give signed distances in world mm."""

    surface: trimesh.Trimesh
    """Tissue surface, world mm (normals towards the air)."""
    fingerprint: str
    """sha256 of the CT's content (volume values and affine, or mesh vertices and faces):
    recorded in the model so an update can refuse a model built on another CT."""
    bounds_mm: tuple[np.ndarray, np.ndarray]
    """World box the CT covers, ((3,), (3,)) float64 mm; outside it nothing is known."""
    source: str
    """Where the CT came from (file name), for error messages."""
    field: np.ndarray | None = None
    """(I, J, K) float32 tissue field of a volume (tissue where > ``level``), or None (mesh)."""
    T_world_from_voxel: np.ndarray | None = None
    """(4, 4) float64 the volume's voxel index -> world mm, or None (mesh)."""
    level: float = LABEL_ISO
    """Iso-level of ``field``."""


def fingerprint_arrays(*arrays: np.ndarray) -> str:
    """sha256 hex digest of arrays' shapes, dtypes and bytes (C order)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _tissue_field(
    volume: np.ndarray,
    kind: CtKind,
    iso_level: float | None,
    tissue_labels: Sequence[int],
    source: str,
) -> tuple[np.ndarray, float, str]:
    """(field float32 with tissue > level, level, the kind used)."""
    vol = np.asarray(volume)
    if kind == "auto":
        kind = "intensity" if float(vol.min()) < INTENSITY_MIN_HU else "label"
    if kind == "intensity":
        return (
            vol.astype(np.float32),
            DEFAULT_HU_ISO if iso_level is None else float(iso_level),
            kind,
        )
    if kind != "label":
        raise InvalidInputError("--kind", f"expected 'auto', 'intensity' or 'label', got {kind!r}")
    if vol.dtype.kind == "f" and not np.all(vol == np.round(vol)):
        raise InvalidInputError(
            source, "label volume holds non-integer values (use --kind intensity)"
        )
    values = np.unique(vol.astype(np.int64))
    known = {0, *(int(t) for t in tissue_labels)}
    unknown = sorted(set(values.tolist()) - known)
    if unknown:
        raise InvalidInputError(
            source,
            f"label volume holds unknown label(s) {unknown[:10]}; known: 0 = air and tissue "
            f"{sorted(known - {0})} (--tissue-labels)",
        )
    field = np.isin(vol.astype(np.int64), list(tissue_labels)).astype(np.float32)
    return field, LABEL_ISO, kind


def ct_from_volume(
    volume: np.ndarray,
    T_world_from_voxel: np.ndarray,
    kind: CtKind = "auto",
    iso_level: float | None = None,
    tissue_labels: Sequence[int] = TISSUE_LABELS,
    source: str = "CT volume",
) -> CtInput:
    """A CT volume as a :class:`CtInput`.

    volume : (I, J, K) HU (intensity) or integer labels (0 = air, ``tissue_labels`` tissue).
    T_world_from_voxel : (4, 4) float64 voxel index -> world mm (LPS, as the reader gives).
    Raises :class:`InvalidInputError` on unknown labels (naming ``source``).
    """
    vol = np.asarray(volume)
    if vol.ndim != 3 or min(vol.shape) < 2:
        raise InvalidInputError(source, f"expected a 3-D volume, got shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise InvalidInputError(source, "volume contains NaN/inf")
    T = np.asarray(T_world_from_voxel, dtype=np.float64)
    field, level, _ = _tissue_field(vol, kind, iso_level, tissue_labels, source)
    surface = surface_from_volume(field, T, "intensity", level, source=source)
    corners = np.array(
        [
            [i, j, k]
            for i in (0, vol.shape[0] - 1)
            for j in (0, vol.shape[1] - 1)
            for k in (0, vol.shape[2] - 1)
        ],
        dtype=np.float64,
    )
    cw = transform_points(T, corners)
    return CtInput(
        surface=surface,
        fingerprint=fingerprint_arrays(vol, T),
        bounds_mm=(cw.min(axis=0), cw.max(axis=0)),
        source=source,
        field=field,
        T_world_from_voxel=T,
        level=level,
    )


def ct_from_mesh(mesh: trimesh.Trimesh, source: str = "CT mesh") -> CtInput:
    """A closed segmentation mesh (enclosing tissue, world mm) as a :class:`CtInput`."""
    if len(mesh.faces) == 0:
        raise InvalidInputError(source, "mesh has no triangle")
    if not mesh.is_watertight:
        raise InvalidInputError(
            source,
            "a CT-initialised model needs a closed (watertight) mesh to tell inside from "
            "outside; give the NIfTI volume, or build with --build sweep",
        )
    v = np.asarray(mesh.vertices, dtype=np.float64)
    return CtInput(
        surface=mesh,
        fingerprint=fingerprint_arrays(v, np.asarray(mesh.faces, dtype=np.int64)),
        bounds_mm=(v.min(axis=0), v.max(axis=0)),
        source=source,
    )


def signed_distance_mm(ct: CtInput, points_mm: np.ndarray) -> np.ndarray:
    """Signed distance of world points to the CT's tissue surface, mm: (N,) float64.

    + = air, - = tissue; NaN outside the CT's box (``ct.bounds_mm``).
    """
    from scipy.ndimage import map_coordinates

    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    queries = SurfaceQueries(ct.surface.vertices, ct.surface.faces, ct.source)
    if ct.field is None:
        sd = queries.signed_distance(p, nsamples=1).astype(np.float64)
    else:
        dist = queries.distance(p).astype(np.float64)
        assert ct.T_world_from_voxel is not None  # a volume (field) has its affine
        ijk = transform_points(np.linalg.inv(ct.T_world_from_voxel), p)
        val = map_coordinates(ct.field, ijk.T, order=1, mode="nearest")
        sd = np.where(val > ct.level, -dist, dist)
    lo, hi = ct.bounds_mm
    inside = np.all((p >= lo - 1e-6) & (p <= hi + 1e-6), axis=1)
    return np.where(inside, sd, np.nan)


def ct_tsdf(
    ct: CtInput,
    T_world_from_voxel: np.ndarray,
    shape: tuple[int, int, int],
    trunc_mm: float,
    chunk: int = 2_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """The CT's normalised truncated signed distance on a model grid.

    Returns (tsdf (X, Y, Z) float32 = clip(sd / trunc_mm, -1, 1), covered (X, Y, Z) bool =
    voxel inside the CT's box). Voxels outside the CT hold +1 (and are not covered).
    """
    n = int(np.prod(shape))
    tsdf = np.ones(n, dtype=np.float32)
    covered = np.zeros(n, dtype=bool)
    ii = np.arange(n)
    for a in range(0, n, chunk):
        idx = np.stack(np.unravel_index(ii[a : a + chunk], shape), axis=1).astype(np.float64)
        sd = signed_distance_mm(ct, transform_points(T_world_from_voxel, idx))
        ok = np.isfinite(sd)
        covered[a : a + chunk] = ok
        tsdf[a : a + chunk] = np.where(ok, np.clip(sd / trunc_mm, -1.0, 1.0), 1.0)
    return tsdf.reshape(shape), covered.reshape(shape)


def check_ct_covers_views(
    ct: CtInput,
    poses: np.ndarray,
    miss_fractions: ArrayLike,
    max_miss_fraction: float,
    option: str = "--ct",
) -> None:
    """Refuse a CT whose grid does not cover the preop poses' view.

    poses : (N, 4, 4) preop ``T_world_from_cam``; each camera centre must lie in the CT's box.
    miss_fractions : per preop frame, the fraction of its (unmasked) pixels whose ray leaves
    the CT without meeting tissue. Raises :class:`InvalidInputError` naming ``ct.source``.
    """
    lo, hi = ct.bounds_mm
    c = np.asarray(poses)[:, :3, 3]
    out = np.flatnonzero(~np.all((c >= lo) & (c <= hi), axis=1))
    if len(out):
        raise InvalidInputError(
            ct.source,
            f"{len(out)} preop camera(s) lie outside the CT's grid "
            f"[{np.round(lo, 1).tolist()}, {np.round(hi, 1).tolist()}] mm (first: frame "
            f"{int(out[0])} at {np.round(c[out[0]], 1).tolist()}): the CT does not cover "
            f"the preop poses' view ({option})",
        )
    miss = np.asarray(miss_fractions, dtype=np.float64)
    bad = np.flatnonzero(miss > max_miss_fraction)
    if len(bad):
        raise InvalidInputError(
            ct.source,
            f"in {len(bad)} preop frame(s) more than {max_miss_fraction:.0%} of the rays leave "
            f"the CT without meeting tissue (worst: frame {int(bad[np.argmax(miss[bad])])}, "
            f"{miss[bad].max():.0%}): the CT's grid does not cover the preop poses' view ({option}; "
            "--max-miss-fraction)",
        )
