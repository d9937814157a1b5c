"""Distance-to-tissue queries for camera paths (Open3D ``RaycastingScene``).

The mesh is the closed tissue solid: the signed distance is positive in the air (outside
the solid, where the camera lives) and negative inside tissue.
"""

from __future__ import annotations

import numpy as np
import trimesh

from chisel.core.raycast import SurfaceQueries


class TissueDistance:
    """Signed distance, closest points and line-of-sight tests against one tissue mesh.

    mesh : closed trimesh in world mm.
    """

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        self.bounds = np.asarray(mesh.bounds, dtype=np.float64)
        """(2, 3) axis-aligned bounding box of the mesh, mm."""
        # sim.phantom.load_mesh records the file, so that path errors can name it.
        self.source = str(mesh.metadata.get("file_path", "the tissue mesh"))
        """The mesh file (or a description), for error messages."""
        self.queries = SurfaceQueries(mesh.vertices, mesh.faces, self.source)

    def signed_distance(self, points_mm: np.ndarray) -> np.ndarray:
        """points_mm : (..., 3) world mm. Returns (...,) float64 mm, > 0 in air, < 0 in tissue."""
        return self.queries.signed_distance(points_mm).astype(np.float64)

    def closest_points(self, points_mm: np.ndarray) -> np.ndarray:
        """points_mm : (..., 3) world mm. Returns (..., 3) float64, nearest surface points."""
        return self.queries.closest_points(points_mm).astype(np.float64)

    def first_hit_mm(self, origins_mm: np.ndarray, targets_mm: np.ndarray) -> np.ndarray:
        """Distance from each origin towards its target to the first tissue hit, mm (inf = none).

        origins_mm, targets_mm : (N, 3) world mm.
        """
        o = np.asarray(origins_mm, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(targets_mm, dtype=np.float64).reshape(-1, 3) - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return self.queries.first_hit(o, d).astype(np.float64)

    def push_to_clearance(
        self, points_mm: np.ndarray, clearance_mm: float, iterations: int = 8
    ) -> np.ndarray:
        """Move air points closer than ``clearance_mm`` to tissue away from it.

        points_mm : (N, 3) world mm, all in the air. Each offending point moves along
        (point - closest surface point) until it is ``clearance_mm`` (+ 5 %) away.
        Returns (N, 3) float64; points already clear are unchanged.
        """
        p = np.array(points_mm, dtype=np.float64).reshape(-1, 3)
        target = clearance_mm * 1.05
        for _ in range(iterations):
            d = self.signed_distance(p)
            bad = d < clearance_mm
            if not bad.any():
                break
            c = self.closest_points(p[bad])
            away = p[bad] - c
            n = np.linalg.norm(away, axis=1, keepdims=True)
            away = away / np.maximum(n, 1e-9)
            p[bad] = c + away * target
        return p
