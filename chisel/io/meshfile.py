"""Reading a triangle mesh file (PLY/STL/OBJ) that came from elsewhere, checked for its kind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from chisel.core.errors import InvalidInputError, ResourceLimitError, out_of_memory_names

MESH_SUFFIXES = (".ply", ".stl", ".obj")
"""Mesh formats a manifest may name (read by trimesh)."""

MAX_MESH_FILE_BYTES = 2 * 2**30
"""Largest mesh file read; a CT segmentation surface is tens of MB."""


def read_mesh_file(path: str | Path, what: str = "mesh") -> trimesh.Trimesh:
    """Load ``path`` as a triangle mesh; every failure is one error naming the file.

    Refused (:class:`InvalidInputError`): another suffix than :data:`MESH_SUFFIXES`, a file
    trimesh cannot parse, no triangle, face indices outside the vertex list (trimesh keeps
    them with ``process=False`` and a later step would fail on them without a name),
    non-finite vertices. :class:`ResourceLimitError` for a file over
    :data:`MAX_MESH_FILE_BYTES`.
    """
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InvalidInputError(
            path, f"{what} must be one of {', '.join(MESH_SUFFIXES)}, got {path.suffix!r}"
        )
    if not path.is_file():
        raise InvalidInputError(path, f"{what} file not found")
    size = path.stat().st_size
    if size > MAX_MESH_FILE_BYTES:
        raise ResourceLimitError(path, f"{what} file is {size} bytes, over {MAX_MESH_FILE_BYTES}")
    try:
        with out_of_memory_names(path, f"reading this {what}"):
            mesh = trimesh.load(str(path), force="mesh", process=False)
    except InvalidInputError:  # the out-of-memory error, named
        raise
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types on bad files
        raise InvalidInputError(
            path, f"not a readable {what} (PLY/STL/OBJ expected): {type(exc).__name__}: {exc}"
        ) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InvalidInputError(path, f"{what} has no triangle (not a mesh?)")
    faces = np.asarray(mesh.faces)
    if faces.min() < 0 or faces.max() >= len(mesh.vertices):
        raise InvalidInputError(
            path,
            f"{what} face indices run from {int(faces.min())} to {int(faces.max())} but there "
            f"are {len(mesh.vertices)} vertices",
        )
    if not np.all(np.isfinite(mesh.vertices)):
        raise InvalidInputError(path, f"{what} vertices contain NaN/inf")
    return mesh
