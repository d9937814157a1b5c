"""Loading a user's tissue surface so it can be cut like a generated phantom."""

from __future__ import annotations

from pathlib import Path

import manifold3d as m3d
import numpy as np

from chisel.io.meshfile import READABLE_MESH_SUFFIXES, read_mesh_file
from phantoms.anatomy import manifold_from_arrays
from phantoms.errors import NotManifoldError


def load_tissue(
    path: str | Path, repair: bool = False, repair_edge_mm: float | None = None
) -> m3d.Manifold:
    """Read a tissue surface (PLY/STL/OBJ, mm) as a closed manifold ready for bites.

    Parameters
    ----------
    path : str or Path
        A triangle mesh (:data:`chisel.io.meshfile.READABLE_MESH_SUFFIXES`).
    repair : bool
        Close a surface that is not a closed manifold with
        :func:`phantoms.tet.repair_surface` instead of raising.

    Raises
    ------
    NotManifoldError
        If the file is unreadable, or (without ``repair``) not a closed, oriented
        2-manifold.
    """
    path = Path(path)
    mesh = read_mesh_file(path, "surface", READABLE_MESH_SUFFIXES, error=NotManifoldError)
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    if repair:
        from phantoms.tet import repair_surface

        v, f = repair_surface(v, f, edge_mm=repair_edge_mm)
    return manifold_from_arrays(v, f, str(path))
