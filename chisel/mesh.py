"""Surface extraction from a TSDF model: marching cubes at D = 0 over observed voxels."""

from __future__ import annotations

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from chisel.core.errors import EmptyResultError
from chisel.core.geometry import transform_points
from chisel.model import TsdfModel


def extract_mesh(model: TsdfModel, with_color: bool = True) -> trimesh.Trimesh:
    """Triangle mesh of the model's zero level set, vertices in world mm.

    Only zero crossings between two observed voxels (weight > 0) are kept: faces with a
    vertex on an edge to an unobserved voxel are dropped. The search is cropped to the box
    of observed voxels near the surface. Vertices are mapped with
    ``T_world_from_voxel``; faces are oriented so normals point into free space (towards
    positive D). Raises :class:`EmptyResultError` when there is no surface.
    """
    band = (model.weight > 0) & (model.tsdf < 1.0)
    if not band.any():
        raise EmptyResultError("model has no observed voxel near a surface (nothing to mesh)")
    idx = [np.flatnonzero(band.any(axis=tuple(a for a in range(3) if a != ax))) for ax in range(3)]
    lo = np.array([max(int(i[0]) - 1, 0) for i in idx])
    hi = np.array([min(int(i[-1]) + 2, s) for i, s in zip(idx, model.shape, strict=True)])
    sl = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
    vol = model.tsdf[sl]
    w = model.weight[sl]
    obs = w > 0
    if min(vol.shape) < 2:
        raise EmptyResultError("model's observed region is too thin to mesh")
    vmin = float(vol[obs].min())
    vmax = float(vol[obs].max())
    if not (vmin < 0.0 < vmax):
        raise EmptyResultError(
            f"no zero crossing in the observed TSDF (range {vmin:.3f}..{vmax:.3f}): empty surface"
        )
    try:
        verts, faces, _normals, _ = marching_cubes(
            vol, level=0.0, gradient_direction="descent", allow_degenerate=False
        )
    except (ValueError, RuntimeError) as exc:
        raise EmptyResultError(f"marching cubes found no surface: {exc}") from None
    # Drop faces with a vertex on an edge that touches an unobserved voxel: such a zero
    # crossing interpolates against the placeholder value of a voxel that holds no data.
    lo_v = np.floor(verts).astype(np.int64)
    hi_v = np.minimum(np.ceil(verts).astype(np.int64), np.array(vol.shape) - 1)
    ok_v = (w[lo_v[:, 0], lo_v[:, 1], lo_v[:, 2]] > 0) & (w[hi_v[:, 0], hi_v[:, 1], hi_v[:, 2]] > 0)
    faces = faces[ok_v[faces].all(axis=1)]
    if len(faces) == 0:
        raise EmptyResultError("marching cubes found no surface in the observed voxels")
    verts_mm = transform_points(model.T_world_from_voxel, verts + lo)
    colors = None
    if with_color and model.color is not None:
        ijk = np.clip(np.rint(verts).astype(np.int64), 0, np.array(vol.shape) - 1)
        colors = model.color[sl][ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    mesh = trimesh.Trimesh(
        vertices=verts_mm, faces=faces, vertex_colors=colors, process=False, validate=False
    )
    mesh.remove_unreferenced_vertices()
    return mesh
