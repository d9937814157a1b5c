"""The preoperative model: the whole CT as signed distances, or the CT's surface fused
along the preoperative sweep (the paper)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

import numpy as np
import trimesh

from chisel.core.errors import EmptyResultError, InvalidInputError, PoseError
from chisel.core.geometry import Camera, check_rigid
from chisel.core.raycast import MeshRaycaster
from chisel.ct_model import CtInput, check_ct_covers_views, ct_from_mesh, ct_tsdf
from chisel.fusion import integrate
from chisel.mesh import extract_mesh
from chisel.model import TsdfModel

MIN_CT_WEIGHT = 1e-6
"""Smallest CT weight: a millionth of one frame's; below ~1e-45 float32 holds 0 and the
CT's voxels would read as never observed."""
MAX_CT_WEIGHT = 1e6
"""Largest CT weight. Weights are float32 and every frame that sees a voxel adds 1: above
2^24 (1.7e7) adding 1 no longer changes a float32, so the updates would be ignored
silently, and 1e300 became inf, a model ``chisel update`` refuses. 1e6 outweighs any sweep
and still leaves 10^7 frames of headroom."""


@dataclass(frozen=True)
class BuildConfig:
    """Parameters of the preoperative model."""

    voxel_size_mm: float = 0.5
    """Voxel edge, mm."""
    trunc_mm: float = 2.0
    """Truncation of the signed distance, mm (>= voxel size; ~4 voxels is usual)."""
    margin_mm: float = 3.0
    """Margin added around the data's bounds, mm."""
    max_view_mm: float = 60.0
    """The grid is cropped to the camera centres' box grown by this, mm (large CT scans)."""
    color: bool = False
    """Keep colour (from the frames' RGB) in the model."""
    ct_weight: float = 1.0
    """CT build: the initial weight of every voxel the CT covers (the sweep adds its own);
    1e-6 to 1e6."""
    max_miss_fraction: float = 0.05
    """CT build: a preop frame with more than this fraction of its rays leaving the CT
    without meeting tissue means the CT's grid does not cover the view (refused)."""

    def __post_init__(self) -> None:
        if not MIN_CT_WEIGHT <= self.ct_weight <= MAX_CT_WEIGHT:  # NaN fails too
            raise InvalidInputError(
                "ct_weight",
                f"must be in [{MIN_CT_WEIGHT:g}, {MAX_CT_WEIGHT:g}] (weights are float32; "
                f"a frame adds 1), got {self.ct_weight}",
            )
        if not 0.0 <= self.max_miss_fraction <= 1.0:
            raise InvalidInputError(
                "max_miss_fraction", f"must be in [0, 1], got {self.max_miss_fraction}"
            )
        if not self.voxel_size_mm > 0:
            raise InvalidInputError("voxel_size_mm", f"must be > 0, got {self.voxel_size_mm}")
        if not self.trunc_mm >= self.voxel_size_mm:
            raise InvalidInputError(
                "trunc_mm", f"must be >= voxel_size_mm ({self.voxel_size_mm}), got {self.trunc_mm}"
            )
        if self.margin_mm < 0 or self.max_view_mm <= 0:
            raise InvalidInputError("margin_mm", "margin must be >= 0 and max_view_mm > 0")


def preop_bounds(
    surface: trimesh.Trimesh, poses: np.ndarray, cfg: BuildConfig
) -> tuple[np.ndarray, np.ndarray]:
    """World box of the preoperative grid: the surface's bounds plus a margin, cropped to
    the camera centres' box grown by ``max_view_mm``, and always holding every camera."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in surface.bounds)
    lo, hi = lo - cfg.margin_mm, hi + cfg.margin_mm
    cams = poses[:, :3, 3]
    lo = np.maximum(lo, cams.min(axis=0) - cfg.max_view_mm)
    hi = np.minimum(hi, cams.max(axis=0) + cfg.max_view_mm)
    lo = np.minimum(lo, cams.min(axis=0) - cfg.margin_mm)
    hi = np.maximum(hi, cams.max(axis=0) + cfg.margin_mm)
    return lo, hi


def snap_to_lattice(lo: np.ndarray, T_world_from_voxel: np.ndarray) -> np.ndarray:
    """``lo`` moved down onto the lattice of a volume's voxel centres, axis by axis, when the
    volume's voxels are axis-aligned (a diagonal affine, any sign); else ``lo`` unchanged.

    The CT's samples then are model voxels (when both share the voxel size): the model's
    sign at a voxel is the CT's own sample there, and a label CT of the same scan scores
    the model at the same points. Off the lattice, nearest-neighbour resampling between the
    grids moved the truth by up to half a voxel: on seed 5 the preoperative model's
    tissue and the label CT's disagreed at 3 059 voxels, and at 55 on the CT's lattice."""
    T = np.asarray(T_world_from_voxel, dtype=np.float64)
    R = T[:3, :3]
    # A rotation below 1e-6 rad (a float32 quaternion's rounding) drifts 1e-3 voxel over 1000.
    if not np.allclose(R, np.diag(np.diag(R)), rtol=0, atol=1e-6 * np.abs(R).max()):
        return lo
    spacing = np.abs(np.diag(R))
    origin = T[:3, 3]
    return origin + np.floor((lo - origin) / spacing + 1e-9) * spacing


def build_preop_model(
    surface: trimesh.Trimesh | None,
    camera: Camera,
    poses: np.ndarray,
    cfg: BuildConfig = BuildConfig(),  # noqa: B008 - frozen dataclass
    rgbs: Iterable[np.ndarray | None] | None = None,
    masks: Iterable[np.ndarray | None] | None = None,
    progress: Callable[[Iterable], Iterable] | None = None,
    ct: CtInput | None = None,
) -> TsdfModel:
    """The preoperative TSDF model: the whole CT (``ct`` given) or the preop sweep alone.

    surface : CT segmentation surface, world mm (see :func:`chisel.io.ct.load_ct_surface`);
        ignored (may be None) when ``ct`` is given, whose own surface is used.
    poses : (N, 4, 4) float64 ``T_world_from_cam`` of the preop sequence, mm.
    rgbs : N (H, W, 3) uint8 images (or None) for colour; masks : N (H, W) bool or None.
    ct : the CT as signed distances (:mod:`chisel.ct_model`). Given, every voxel the CT
        covers takes its normalised truncated signed distance and weight ``cfg.ct_weight``
        (``build = "ct"``), and the sweep adds observation weight and colour where it sees;
        the CT's grid must cover the preop views (else :class:`InvalidInputError`).
        Without it (the paper, ``build = "sweep"``): the surface rendered at every pose is
        fused with Curless-Levoy averaging, w = 1 per valid pixel, free space carved (+1).
    """
    P = check_rigid(poses, "poses")
    if P.ndim != 3 or len(P) == 0:
        raise PoseError("poses", f"expected (N, 4, 4) poses with N >= 1, got shape {P.shape}")
    rgb_list = [None] * len(P) if rgbs is None else list(rgbs)
    mask_list = [None] * len(P) if masks is None else list(masks)
    if len(rgb_list) != len(P) or len(mask_list) != len(P):
        raise PoseError(
            "poses",
            f"{len(P)} poses but {len(rgb_list)} images and {len(mask_list)} masks: counts differ",
        )
    if ct is not None:
        surface = ct.surface
        check_ct_covers_views(ct, P, np.zeros(len(P)), cfg.max_miss_fraction)  # the cameras
    if surface is None or len(surface.faces) == 0:
        raise InvalidInputError("surface", "CT surface has no triangle")
    lo, hi = preop_bounds(surface, P, cfg)
    if ct is not None and ct.T_world_from_voxel is not None:
        lo = snap_to_lattice(lo, ct.T_world_from_voxel)
    model = TsdfModel.empty(lo, hi, cfg.voxel_size_mm, cfg.trunc_mm, with_color=cfg.color)
    rc = MeshRaycaster(surface.vertices, surface.faces)
    items = list(zip(P, rgb_list, mask_list, strict=True))
    it = progress(items) if progress is not None else items
    seen = masked_out = 0
    misses: list[float] = []
    for T, rgb, mask in it:
        depth = rc.render_depth(camera, T)
        if mask is not None:
            masked_out += not mask.any()
            depth = np.where(mask, depth, np.nan).astype(np.float32)
        keep = np.ones(camera.shape, bool) if mask is None else np.asarray(mask, bool)
        misses.append(float((~np.isfinite(depth) & keep).sum() / max(int(keep.sum()), 1)))
        if np.isfinite(depth).any():
            seen += 1
            integrate(model, camera, T, depth, rgb=rgb)
    if ct is not None and masked_out < len(P):
        check_ct_covers_views(ct, P, misses, cfg.max_miss_fraction)
    if seen == 0:
        if masked_out == len(P):
            raise EmptyResultError("every preoperative frame's mask keeps no pixel")
        raise EmptyResultError("the CT surface is not visible from any preoperative pose")
    if ct is None:
        return model
    tsdf, covered = ct_tsdf(ct, model.T_world_from_voxel, model.shape, cfg.trunc_mm)
    weight = np.where(covered, np.float32(cfg.ct_weight), np.float32(0)) + model.weight
    return replace(
        model, tsdf=tsdf, weight=weight.astype(np.float32), build="ct", ct_sha256=ct.fingerprint
    )


def _face_keys(mesh: trimesh.Trimesh) -> set[bytes]:
    """One key per triangle, its corners' coordinates (float32, in sorted order)."""
    tri = np.sort(np.asarray(mesh.triangles, dtype=np.float32).reshape(-1, 3, 3), axis=1)
    return {t.tobytes() for t in tri}


def voxel_copies(
    surfaces: list[trimesh.Trimesh],
    bounds_min_mm: np.ndarray,
    bounds_max_mm: np.ndarray,
    voxel_size_mm: float = BuildConfig.voxel_size_mm,
    trunc_mm: float = BuildConfig.trunc_mm,
) -> list[trimesh.Trimesh]:
    """The surfaces a CT-built model holds of closed meshes, as the updater renders them.

    Each mesh's truncated signed distance on one grid over the world box (as
    :func:`build_preop_model` with ``ct`` sets it; voxels outside a mesh's bounds are air),
    meshed at zero by :func:`chisel.mesh.extract_mesh`: the surface behind the model's
    render M_t, whose lamellae thinner than a voxel come out thicker, holed or gone and
    whose edges are rounded. The change-aware network's training priors use it, so that
    what it learns to trust is what it is given.

    Successive surgical steps share most of their faces (manifold3d keeps the faces a cut
    does not touch): a step's distances are computed afresh only in the box of the faces
    that differ from the previous mesh, grown by the truncation, which is ~5x quicker
    over five steps than each mesh on the whole grid (the signed distance is the cost).
    """
    grid = TsdfModel.empty(bounds_min_mm, bounds_max_mm, voxel_size_mm, trunc_mm)
    shape = np.array(grid.shape)
    out: list[trimesh.Trimesh] = []
    tsdf: np.ndarray | None = None
    keys: set[bytes] = set()
    for k, surface in enumerate(surfaces):
        ct = ct_from_mesh(surface, f"voxel_copies surface {k}")
        new_keys = _face_keys(surface)
        if tsdf is None:
            lo_i, hi_i = np.zeros(3, np.int64), shape.copy()
        else:
            changed = np.frombuffer(b"".join(keys ^ new_keys), np.float32).reshape(-1, 3)
            if len(changed) == 0:
                out.append(out[-1])
                continue
            pad = trunc_mm + voxel_size_mm
            lo_w, hi_w = changed.min(axis=0) - pad, changed.max(axis=0) + pad
            lo_i = np.clip(np.floor((lo_w - grid.origin_mm) / voxel_size_mm), 0, shape)
            hi_i = np.clip(np.ceil((hi_w - grid.origin_mm) / voxel_size_mm) + 1, 0, shape)
            lo_i, hi_i = lo_i.astype(np.int64), hi_i.astype(np.int64)
        keys = new_keys
        if np.all(hi_i > lo_i):
            T = grid.T_world_from_voxel.copy()
            T[:3, 3] += lo_i * voxel_size_mm
            nx, ny, nz = (int(n) for n in hi_i - lo_i)
            part, _covered = ct_tsdf(ct, T, (nx, ny, nz), trunc_mm)
            if tsdf is None:
                tsdf = part
            else:  # in place: each step's mesh is extracted before the next step writes
                tsdf[lo_i[0] : hi_i[0], lo_i[1] : hi_i[1], lo_i[2] : hi_i[2]] = part
        assert tsdf is not None
        model = replace(grid, tsdf=tsdf, weight=np.ones(grid.shape, np.float32), build="ct")
        out.append(extract_mesh(model, with_color=False))
    return out
