"""Depth renders of a model's surface: M_t, the reference every frame's change is measured
against, and the registration target (the surface's vertices with normals)."""

from __future__ import annotations

import numpy as np
import trimesh

from chisel.core.geometry import Camera
from chisel.core.raycast import MeshRaycaster
from chisel.icp import SurfaceIndex
from chisel.mesh import extract_mesh
from chisel.model import TsdfModel


class ModelRenderer:
    """Depth renders of a model's surface (marching cubes once, then ray casting with
    :class:`~chisel.core.raycast.MeshRaycaster`: Mitsuba where a JIT variant works, else Open3D)."""

    def __init__(self, model: TsdfModel) -> None:
        self.mesh: trimesh.Trimesh = extract_mesh(model, with_color=False)
        self._grid = (model.origin_mm, model.voxel_size_mm, model.shape)
        self.raycaster = MeshRaycaster(self.mesh.vertices, self.mesh.faces)
        self._normals = np.asarray(self.mesh.vertex_normals)
        self._index: SurfaceIndex | None = None

    @property
    def index(self) -> SurfaceIndex:
        """k-d tree of the surface's vertices with normals (registration target), lazily built."""
        if self._index is None:
            self._index = SurfaceIndex(self.mesh.vertices, self._normals, grid=self._grid)
        return self._index

    def render(self, camera: Camera, T_world_from_cam: np.ndarray) -> np.ndarray:
        """(H, W) float32 z-depth of the model surface, mm, NaN where nothing is hit."""
        return self.raycaster.render_depth(camera, T_world_from_cam)

    def surface_points(self, lo_mm: np.ndarray, hi_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mesh vertices and normals inside a world box: ((N, 3), (N, 3)) float64 mm."""
        v = self.mesh.vertices
        sel = np.all((v >= lo_mm) & (v <= hi_mm), axis=1)
        return v[sel], self._normals[sel]


def render_depth(model: TsdfModel, camera: Camera, T_world_from_cam: np.ndarray) -> np.ndarray:
    """Depth of the model's surface at a pose: (H, W) float32 mm, NaN = no surface.

    Convenience for one pose; for many poses keep a :class:`ModelRenderer`.
    """
    return ModelRenderer(model).render(camera, T_world_from_cam)
