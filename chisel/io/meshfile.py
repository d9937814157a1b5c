"""Reading a triangle mesh file (PLY/STL/OBJ) that came from elsewhere, checked for its kind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from chisel.core.errors import InvalidInputError, ResourceLimitError, out_of_memory_names

MESH_SUFFIXES = (".ply", ".stl", ".obj")
"""Mesh formats a manifest may name (read by trimesh)."""
READABLE_MESH_SUFFIXES = (*MESH_SUFFIXES, ".off", ".glb")
"""Every mesh format the readers take from a user's own file (a CT segmentation, a
phantom's or a tool's mesh): what trimesh reads as one triangle mesh."""

MAX_MESH_FILE_BYTES = 2 * 2**30
"""Largest mesh file read; a CT segmentation surface is tens of MB."""


def read_mesh_file(
    path: str | Path,
    what: str = "mesh",
    suffixes: tuple[str, ...] = MESH_SUFFIXES,
    *,
    process: bool = False,
    error: type[InvalidInputError] = InvalidInputError,
) -> trimesh.Trimesh:
    """Load ``path`` as a triangle mesh; every failure is one error naming the file.

    process : let trimesh merge duplicate vertices (smooth vertex normals for rendering);
    False keeps the file's vertices as they are (indices that other files refer to).

    Refused (``error``, an :class:`InvalidInputError`): another suffix than ``suffixes``, a file
    trimesh cannot parse, no triangle, face indices outside the vertex list (trimesh keeps
    them with ``process=False`` and a later step would fail on them without a name),
    non-finite vertices. :class:`ResourceLimitError` for a file over
    :data:`MAX_MESH_FILE_BYTES`.
    """
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise error(path, f"{what} must be one of {', '.join(suffixes)}, got {path.suffix!r}")
    if not path.is_file():
        raise error(path, f"{what} file not found")
    size = path.stat().st_size
    if size > MAX_MESH_FILE_BYTES:
        raise ResourceLimitError(path, f"{what} file is {size} bytes, over {MAX_MESH_FILE_BYTES}")
    try:
        with out_of_memory_names(path, f"reading this {what}"):
            mesh = trimesh.load(str(path), force="mesh", process=process)
    except ResourceLimitError:  # the out-of-memory error, named
        raise
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types on bad files
        raise error(
            path,
            f"not a readable {what} ({', '.join(suffixes)} expected): {type(exc).__name__}: {exc}",
        ) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise error(path, f"{what} has no triangle (not a mesh?)")
    faces = np.asarray(mesh.faces)
    if faces.min() < 0 or faces.max() >= len(mesh.vertices):
        raise error(
            path,
            f"{what} face indices run from {int(faces.min())} to {int(faces.max())} but there "
            f"are {len(mesh.vertices)} vertices",
        )
    if not np.all(np.isfinite(mesh.vertices)):
        raise error(path, f"{what} vertices contain NaN/inf")
    return mesh
