"""Depth rendering of a triangle mesh by ray casting (Open3D ``RaycastingScene``).

Used to render the CT-segmentation surface at tracked poses (preoperative model), the
current model's surface (M_t), and ground-truth meshes in the evaluation. The scene is
built once per mesh; each render casts one ray per pixel of the raw (distorted) image.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from chisel.errors import InvalidInputError
from chisel.geometry import Camera, check_rigid


class MeshRaycaster:
    """Ray caster over one triangle mesh in world mm.

    vertices_mm : (V, 3) float, world mm.  faces : (F, 3) int vertex indices.
    """

    def __init__(self, vertices_mm: np.ndarray, faces: np.ndarray) -> None:
        v = np.asarray(vertices_mm, dtype=np.float32)
        f = np.asarray(faces, dtype=np.uint32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise InvalidInputError(
                "mesh", f"expected (V, 3) vertices and (F>0, 3) faces, got {v.shape}, {f.shape}"
            )
        if not np.all(np.isfinite(v)):
            raise InvalidInputError("mesh", "vertices contain NaN/inf")
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(f))
        self._rays_key: Camera | None = None
        self._rays_cam = np.zeros((0, 3), dtype=np.float32)

    @classmethod
    def from_trimesh(cls, mesh) -> MeshRaycaster:  # noqa: ANN001 - trimesh.Trimesh
        return cls(mesh.vertices, mesh.faces)

    def render_depths(
        self, camera: Camera, T_world_from_cams: np.ndarray, batch: int = 8
    ) -> np.ndarray:
        """z-depth at many poses: (N, H, W) float32 mm, NaN on a miss.

        T_world_from_cams : (N, 4, 4) float64 poses. Rays of ``batch`` frames go to Open3D
        in one call, which costs less per frame than one call per frame.
        """
        P = check_rigid(T_world_from_cams, "T_world_from_cams")
        if P.ndim != 3:
            raise InvalidInputError("T_world_from_cams", f"expected (N, 4, 4), got {P.shape}")
        out = np.empty((len(P), camera.height, camera.width), dtype=np.float32)
        for a in range(0, len(P), batch):
            chunk = P[a : a + batch]
            out[a : a + len(chunk)] = self._cast_poses(camera, chunk)
        return out

    def _cast_poses(self, camera: Camera, poses: np.ndarray) -> np.ndarray:
        """One Open3D call for every pixel of ``poses`` (n, 4, 4): (n, H, W) z-depth, NaN miss."""
        dirs = self._camera_rays(camera)
        rays = np.empty((len(poses), len(dirs), 6), dtype=np.float32)
        for i, T in enumerate(poses):
            rays[i, :, :3] = T[:3, 3]
            rays[i, :, 3:] = dirs @ T[:3, :3].T.astype(np.float32)
        t = self.scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6)))["t_hit"].numpy()
        t[~np.isfinite(t)] = np.nan
        return t.reshape(len(poses), camera.height, camera.width)

    def _camera_rays(self, camera: Camera) -> np.ndarray:
        """(H*W, 3) float32 z = 1 rays of ``camera`` (so t_hit is the z-depth); cached."""
        if self._rays_key is not camera:
            self._rays_cam = np.ascontiguousarray(camera.rays_cam().reshape(-1, 3), np.float32)
            self._rays_key = camera
        return self._rays_cam

    def render_depth(self, camera: Camera, T_world_from_cam: np.ndarray) -> np.ndarray:
        """z-depth of the mesh seen from ``T_world_from_cam``.

        Returns (H, W) float32 z-depth in mm, NaN where the ray misses.
        """
        T = check_rigid(T_world_from_cam, "T_world_from_cam")
        if T.shape != (4, 4):
            raise InvalidInputError("T_world_from_cam", f"expected one (4, 4) pose, got {T.shape}")
        return self._cast_poses(camera, T[None])[0]
