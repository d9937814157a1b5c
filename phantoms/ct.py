"""CT-like volumes of the tissue mesh: a label map and a Hounsfield-like intensity volume.

Model (documented in ``docs/phantoms.md``, "CT volumes"):

* ``sd`` is the signed distance of each voxel centre to the tissue surface, mm, positive
  in air (Open3D ``RaycastingScene``: occupancy by majority of 3 rays, distance by
  closest point). Only voxels within ``mucosa_mm + spacing_mm`` of the surface need the
  exact distance; farther ones are clipped.
* label: 0 air (``sd > 0``), 1 soft tissue (depth ``-sd < mucosa_mm``), 2 bone (deeper).
  Every surface is covered by mucosa; lamellae thinner than ``2 * mucosa_mm`` are soft
  tissue in the CT (real CTs also show them far below bone values, by partial volume).
* HU = -1000 + 1040 f_tissue + 660 f_bone (+ seeded Gaussian noise), with the linear
  partial-volume ramps f_tissue = clip(0.5 - sd / (2 spacing), 0, 1) and
  f_bone = clip(0.5 + (depth - mucosa_mm) / spacing, 0, 1). The tissue ramp is two voxels
  wide, so along every grid edge that crosses the surface both end values lie on the
  ramp and marching cubes at -480 HU places the surface exactly where it is (planar
  surfaces are reproduced exactly; curved ones to a small fraction of a voxel). Bone
  starts ``mucosa_mm - spacing/2`` deep, beyond the reach of those edges.
* ``T_world_from_voxel`` maps voxel indices to voxel *centres* in the phantom's world
  frame (LPS, mm); it is a pure scaling plus translation. The NIfTI files hold its RAS
  form, ``diag(-1, -1, 1, 1) @ T_world_from_voxel`` (written by ``chisel.io.ct``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from chisel.core.geometry import ivec3, vec3
from chisel.core.raycast import SurfaceQueries

HU_AIR = -1000.0
HU_SOFT_TISSUE = 40.0
HU_BONE = 700.0
LABEL_AIR, LABEL_SOFT_TISSUE, LABEL_BONE = 0, 1, 2
ISO_HU = 0.5 * (HU_AIR + HU_SOFT_TISSUE)
"""-480 HU: the iso-level halfway between air and soft tissue that marks the surface."""


@dataclass(frozen=True)
class CTGrid:
    """A regular voxel grid in world mm.

    origin_mm : (3,) float, centre of voxel (0, 0, 0).  shape : (nx, ny, nz).
    spacing_mm : isotropic voxel size.
    """

    origin_mm: tuple[float, float, float]
    shape: tuple[int, int, int]
    spacing_mm: float

    @property
    def T_world_from_voxel(self) -> np.ndarray:
        """(4, 4) float64: voxel index (i, j, k, 1) -> voxel centre in world mm."""
        T = np.eye(4)
        T[:3, :3] *= self.spacing_mm
        T[:3, 3] = self.origin_mm
        return T

    def points(
        self, lo: tuple[int, int, int] = (0, 0, 0), hi: tuple[int, int, int] | None = None
    ) -> np.ndarray:
        """Voxel centres of the index box ``[lo, hi)``: (nx, ny, nz, 3) float32, mm."""
        hi = self.shape if hi is None else hi
        axes = [self.origin_mm[i] + self.spacing_mm * np.arange(lo[i], hi[i]) for i in range(3)]
        X, Y, Z = np.meshgrid(*axes, indexing="ij")
        return np.stack([X, Y, Z], axis=-1).astype(np.float32)

    def index_box(
        self, box_min_mm: np.ndarray, box_max_mm: np.ndarray
    ) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """Smallest index box ``[lo, hi)`` whose voxel centres cover the world box."""
        o = np.asarray(self.origin_mm)
        lo = np.floor((np.asarray(box_min_mm) - o) / self.spacing_mm).astype(int)
        hi = np.ceil((np.asarray(box_max_mm) - o) / self.spacing_mm).astype(int) + 1
        lo = np.clip(lo, 0, self.shape)
        hi = np.clip(hi, 0, self.shape)
        return ivec3(lo), ivec3(hi)


def grid_for_box(box_min_mm, box_max_mm, spacing_mm: float) -> CTGrid:
    """Grid covering the box plus two voxels of air on every side.

    The origin is offset by a quarter voxel so that voxel centres never fall on the
    block's faces (whose coordinates are multiples of 0.1 mm).
    """
    lo = np.asarray(box_min_mm, float) - 2.25 * spacing_mm
    n = (
        np.ceil((np.asarray(box_max_mm, float) + 2.0 * spacing_mm - lo) / spacing_mm).astype(int)
        + 1
    )
    return CTGrid(vec3(lo), ivec3(n), float(spacing_mm))


def grid_for_block(block_min_mm, block_max_mm, spacing_mm: float, inset_mm: float) -> CTGrid:
    """The CT field of view of a phantom: the tissue block, like a head in a scanner.

    The anterior side reaches two voxels into the air in front of the nostril (the face
    is imaged); the other five sides stay ``inset_mm`` inside the block, because the
    block's cut faces are not anatomy: tissue continues beyond the field of view, as in
    a real CT. Voxel centres are offset by a quarter voxel from the block's 0.1 mm
    lattice.
    """
    bmin = np.asarray(block_min_mm, float)
    bmax = np.asarray(block_max_mm, float)
    lo = bmin + inset_mm + 0.25 * spacing_mm
    lo[1] = bmin[1] - 2.25 * spacing_mm
    hi = bmax - inset_mm
    n = np.floor((hi - lo) / spacing_mm).astype(int) + 1
    return CTGrid(vec3(lo), ivec3(n), float(spacing_mm))


class SurfaceDistance(SurfaceQueries):
    """Signed distance to a closed triangle mesh (positive outside the solid), mm: the
    shared Open3D queries (:class:`chisel.core.raycast.SurfaceQueries`) plus the grid
    versions the CT volumes need.

    vertices_mm : (V, 3) float, mm.  faces : (F, 3) int.
    """

    def inside_grid(self, points_mm: np.ndarray) -> np.ndarray:
        """Occupancy of a (nx, ny, nz, 3) grid of points -> (nx, ny, nz) bool.

        One ray per voxel, then a majority of 3 rays for every voxel that differs from a
        face neighbour: a parity error of the single ray (a ray grazing an edge) always
        leaves such a disagreement, so this matches 3 rays everywhere at half the cost.
        """
        shape = points_mm.shape[:-1]
        p = np.ascontiguousarray(points_mm.reshape(-1, 3), dtype=np.float32)
        occ = self.inside(p, nsamples=1)
        occ = occ.reshape(shape).astype(bool)
        recheck = _boundary(occ)
        occ[recheck] = self.inside(points_mm[recheck])
        return occ

    def signed_distance_grid(
        self, points_mm: np.ndarray, clip_mm: tuple[float, float], spacing_mm: float
    ) -> np.ndarray:
        """Clipped signed distance on a (nx, ny, nz, 3) grid of points.

        ``clip_mm = (inside, outside)``: depths are clipped to ``inside`` and distances
        in air to ``outside``. Exact distances are computed only for voxels within the
        clip (plus a voxel) of the surface, found from the occupancy grid. Returns
        (nx, ny, nz) float32, mm, positive outside the solid.
        """
        clip_in, clip_out = clip_mm
        inside = self.inside_grid(points_mm)
        boundary = _boundary(inside)
        steps = (
            ndimage.distance_transform_edt(~boundary)
            if boundary.any()
            else np.full(inside.shape, np.inf)
        )
        reach = np.where(inside, clip_in, clip_out) + spacing_mm
        band = steps * spacing_mm <= reach
        sd = np.where(inside, -clip_in, clip_out).astype(np.float32)
        d = self.distance(points_mm[band])
        sd[band] = np.where(inside[band], -np.minimum(d, clip_in), np.minimum(d, clip_out))
        return sd


def _boundary(inside: np.ndarray) -> np.ndarray:
    """Voxels with a face neighbour on the other side (both sides of the surface)."""
    out = inside ^ ndimage.binary_erosion(inside, border_value=1)
    out |= ~inside ^ ndimage.binary_erosion(~inside, border_value=1)
    return out


def clip_distance_mm(spacing_mm: float, mucosa_mm: float) -> tuple[float, float]:
    """(depth, air distance) beyond which the label/HU model saturates, mm.

    In air the tissue ramp is 0 from one voxel out; inside, bone is complete at
    ``mucosa + spacing / 2`` deep.
    """
    return mucosa_mm + spacing_mm, spacing_mm


def labels_from_sd(sd_mm: np.ndarray, mucosa_mm: float) -> np.ndarray:
    """sd_mm : (...) float, mm, positive in air -> (...) uint8 labels 0 air / 1 soft / 2 bone."""
    label = np.full(sd_mm.shape, LABEL_SOFT_TISSUE, np.uint8)
    label[sd_mm > 0] = LABEL_AIR
    label[-sd_mm >= mucosa_mm] = LABEL_BONE
    return label


def hu_from_sd(
    sd_mm: np.ndarray, spacing_mm: float, mucosa_mm: float, noise: np.ndarray | None = None
) -> np.ndarray:
    """sd_mm : (...) float, mm, positive in air -> (...) int16 Hounsfield-like units.

    noise : (...) float, HU, added before rounding (None = none).
    """
    f_tissue = np.clip(0.5 - sd_mm / (2.0 * spacing_mm), 0.0, 1.0)
    f_bone = np.clip(0.5 + (-sd_mm - mucosa_mm) / spacing_mm, 0.0, 1.0)
    hu = HU_AIR + (HU_SOFT_TISSUE - HU_AIR) * f_tissue + (HU_BONE - HU_SOFT_TISSUE) * f_bone
    if noise is not None:
        hu = hu + noise
    return np.clip(np.rint(hu), -32768, 32767).astype(np.int16)


def ct_noise(shape: tuple[int, int, int], noise_hu: float, seed: int) -> np.ndarray | None:
    """The phantom's one seeded Gaussian noise field, (nx, ny, nz) float32 HU, or None."""
    if noise_hu <= 0:
        return None
    rng = np.random.default_rng([int(seed), 0xC7])
    return (noise_hu * rng.standard_normal(shape)).astype(np.float32)


def update_sd(
    sd_mm: np.ndarray,
    grid: CTGrid,
    surface: SurfaceDistance,
    changed_min_mm: np.ndarray,
    changed_max_mm: np.ndarray,
    clip_mm: tuple[float, float],
) -> np.ndarray:
    """Recompute the clipped signed distance where the solid may have changed.

    When the solid changes only inside the box ``[changed_min_mm, changed_max_mm]``
    (a cutter's bounds), a voxel farther than the clip from that box keeps its
    clipped distance: every surface within the clip of it is unchanged. So only the
    box grown by the larger clip plus a voxel is recomputed. ``clip_mm = (inside,
    outside)`` as in :meth:`SurfaceDistance.signed_distance_grid`. Returns a new
    (nx, ny, nz) float32 array.
    """
    clip_in, clip_out = clip_mm
    grow = max(clip_in, clip_out) + grid.spacing_mm
    lo, hi = grid.index_box(np.asarray(changed_min_mm) - grow, np.asarray(changed_max_mm) + grow)
    out = sd_mm.copy()
    if any(h <= l for l, h in zip(lo, hi, strict=True)):
        return out
    pts = grid.points(lo, hi)
    inside = surface.inside(pts)
    d = surface.distance(pts)
    out[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = np.where(
        inside, -np.minimum(d, clip_in), np.minimum(d, clip_out)
    )
    return out


def nifti_gz_bytes(
    volume: np.ndarray, T_world_from_voxel: np.ndarray, description: str = ""
) -> bytes:
    """A NIfTI-1 image, gzip-compressed with a zero mtime so equal volumes give equal bytes.

    volume : (nx, ny, nz) uint8 or int16.  T_world_from_voxel : (4, 4) float, voxel ->
    the phantom's (LPS) world mm. Written by the project's one volume writer
    (:func:`chisel.io.ct.nifti_bytes`): a RAS affine in sform and qform (code 1), as
    NIfTI requires.
    """
    from chisel.io.ct import nifti_bytes

    return nifti_bytes(np.asarray(volume), T_world_from_voxel, description=description)


def bbox_voxels(grid: CTGrid, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """World box (min, max) of the centres of the True voxels of ``mask``, or None."""
    idx = np.argwhere(mask)
    if len(idx) == 0:
        return None
    o = np.asarray(grid.origin_mm)
    return o + grid.spacing_mm * idx.min(axis=0), o + grid.spacing_mm * idx.max(axis=0)
