"""Loading a user's tissue surface so it can be cut like a generated phantom."""

from __future__ import annotations

from pathlib import Path
from typing import cast

import manifold3d as m3d
import numpy as np

from phantoms.anatomy import manifold_from_arrays
from phantoms.errors import NotManifoldError


def load_tissue(
    path: str | Path, repair: bool = False, repair_edge_mm: float | None = None
) -> m3d.Manifold:
    """Read a tissue surface (PLY/STL/OBJ, mm) as a closed manifold ready for bites.

    Parameters
    ----------
    path : str or Path
        Any triangle-mesh format trimesh reads.
    repair : bool
        Close a surface that is not a closed manifold with
        :func:`phantoms.tet.repair_surface` instead of raising.

    Raises
    ------
    NotManifoldError
        If the file is unreadable, or (without ``repair``) not a closed, oriented
        2-manifold.
    """
    import trimesh

    path = Path(path)
    try:
        # load() is annotated Geometry; force="mesh" returns a Trimesh (Scene.to_mesh)
        mesh = cast("trimesh.Trimesh", trimesh.load(path, force="mesh", process=False))
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types for unreadable files
        raise NotManifoldError(path, f"cannot read a triangle mesh: {exc}") from None
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    if repair:
        from phantoms.tet import repair_surface

        v, f = repair_surface(v, f, edge_mm=repair_edge_mm)
    return manifold_from_arrays(v, f, str(path))
