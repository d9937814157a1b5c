"""Volumetric meshes (pytetwild / fTetWild) and surface repair.

* :func:`tetrahedralize` turns a closed tissue surface into tetrahedra (exported per step
  as ``tet/step_NN.vtu`` with ``--tet``) for users who simulate soft tissue.
* :func:`repair_surface` closes a user-supplied surface that is not a closed manifold
  (holes, duplicated or flipped faces): fTetWild tetrahedralises the space it encloses
  (by generalised winding number) and the boundary of those tetrahedra is the repaired,
  watertight surface.

pytetwild writes ``__tracked_surface.stl`` into the working directory, so every call runs
inside a temporary directory (``os.chdir`` is process-wide: do not call these from
several threads at once). One thread keeps the output deterministic.
"""

from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path

import manifold3d as m3d
import numpy as np

from phantoms.anatomy import arrays_from_manifold, manifold_from_arrays
from phantoms.errors import NotManifoldError, ParameterRangeError


def _check_surface(
    vertices_mm: np.ndarray, faces: np.ndarray, source: str
) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices_mm, dtype=np.float64)
    f = np.asarray(faces)
    if (
        v.ndim != 2
        or v.shape[1] != 3
        or f.ndim != 2
        or f.shape[1] != 3
        or len(f) == 0
        or len(v) < 4
    ):
        raise NotManifoldError(
            source, f"expected (V>=4, 3) vertices and (F>0, 3) faces, got {v.shape} and {f.shape}"
        )
    if not np.all(np.isfinite(v)):
        raise NotManifoldError(source, "vertices contain NaN or inf")
    if f.min() < 0 or f.max() >= len(v):
        raise NotManifoldError(
            source, f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]"
        )
    return v, f.astype(np.int32)


def tetrahedralize(
    vertices_mm: np.ndarray,
    faces: np.ndarray,
    edge_mm: float = 3.0,
    envelope_mm: float = 0.2,
    source: str = "surface",
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral mesh of the solid a surface encloses.

    Parameters
    ----------
    vertices_mm : (V, 3) float, mm.  faces : (F, 3) int.
    edge_mm : float
        Target tetrahedron edge length, mm.
    envelope_mm : float
        Largest distance of the tet mesh's boundary from the input surface, mm.

    Returns
    -------
    points_mm : (P, 3) float64, mm.
    tets : (T, 4) int32, VTK ordering (every tetrahedron has positive volume).
    """
    import pytetwild

    if not 0.05 <= edge_mm <= 20.0:
        raise ParameterRangeError("edge_mm", f"expected a length in [0.05, 20] mm, got {edge_mm!r}")
    v, f = _check_surface(vertices_mm, faces, source)
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    if diag <= 0:
        raise NotManifoldError(source, "all vertices coincide")
    with tempfile.TemporaryDirectory(prefix="phantoms-tetwild-") as tmp, contextlib.chdir(tmp):
        pts, tets = pytetwild.tetrahedralize(
            v,
            f,
            edge_length_abs=float(edge_mm),
            epsilon=float(envelope_mm) / diag,
            optimize=False,
            num_threads=1,
            vtk_ordering=True,
            quiet=True,
        )
    pts = np.asarray(pts, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int32)
    if len(tets) == 0:
        raise NotManifoldError(source, "encloses no volume: tetrahedralisation gave no tetrahedra")
    return pts, tets


def tet_volumes(points_mm: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron, (T,) float64 mm^3 (positive for VTK ordering)."""
    a, b, c, d = (points_mm[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def boundary_surface(points_mm: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward-oriented boundary triangles of a tet mesh (faces used by one tetrahedron).

    Returns compacted (V, 3) float64 vertices and (F, 3) int64 faces.
    """
    t = np.asarray(tets, dtype=np.int64)
    # outward faces of a positively oriented tetrahedron (a, b, c, d)
    tri = np.concatenate([t[:, [0, 2, 1]], t[:, [0, 1, 3]], t[:, [0, 3, 2]], t[:, [1, 2, 3]]])
    key = np.sort(tri, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    tri = tri[counts[inverse.ravel()] == 1]
    used, faces = np.unique(tri, return_inverse=True)
    return np.asarray(points_mm, np.float64)[used], faces.reshape(-1, 3)


def repair_surface(
    vertices_mm: np.ndarray,
    faces: np.ndarray,
    edge_mm: float | None = None,
    envelope_mm: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Close a surface that is not a closed manifold (holes, flipped or duplicated faces).

    Parameters
    ----------
    vertices_mm : (V, 3) float, mm.  faces : (F, 3) int.
    edge_mm : float, optional
        Target edge length of the intermediate tet mesh (default: 1/40 of the bounding
        box diagonal).
    envelope_mm : float, optional
        Largest deviation from the input surface (default: 1/1000 of the diagonal).

    Returns
    -------
    (V', 3) float64 vertices and (F', 3) int64 faces of a closed, oriented 2-manifold
    (checked with manifold3d; where two parts of the solid touch along an edge, the
    vertices there are duplicated so each part stays manifold).

    Raises
    ------
    NotManifoldError
        If even the repaired surface is not a closed manifold (e.g. the input encloses
        nothing).
    """
    v, f = _check_surface(vertices_mm, faces, "surface")
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    edge = edge_mm if edge_mm is not None else diag / 40.0
    env = envelope_mm if envelope_mm is not None else diag / 1000.0
    pts, tets = tetrahedralize(v, f, edge_mm=edge, envelope_mm=env, source="surface")
    bv, bf = boundary_surface(pts, tets)
    try:
        return arrays_from_manifold(manifold_from_arrays(bv, bf, "repaired surface"))
    except NotManifoldError:
        pass
    # Two parts of the solid touching along an edge make that edge non-manifold; give
    # every triangle its own corners and let manifold3d merge only what stays manifold.
    corners = np.ascontiguousarray(bv[bf].reshape(-1, 3))
    mesh = m3d.Mesh64(
        vert_properties=corners, tri_verts=np.arange(len(corners), dtype=np.uint64).reshape(-1, 3)
    )
    mesh.merge()
    man = m3d.Manifold(mesh)
    if man.status() != m3d.Error.NoError or man.is_empty():
        raise NotManifoldError(
            "repaired surface",
            f"still not a closed manifold (manifold3d status {man.status().name})",
        )
    return arrays_from_manifold(man)


def vtu_bytes(points_mm: np.ndarray, tets: np.ndarray) -> bytes:
    """VTK XML unstructured grid (``.vtu``, binary, zlib) of tetrahedra, through pyvista.

    points_mm : (P, 3) float, mm.  tets : (T, 4) int, VTK ordering.
    """
    import pyvista as pv

    grid = pv.UnstructuredGrid(
        {pv.CellType.TETRA: np.asarray(tets, dtype=np.int64)}, np.asarray(points_mm, np.float64)
    )
    with tempfile.TemporaryDirectory(prefix="phantoms-vtu-") as tmp:
        path = Path(tmp) / "mesh.vtu"
        grid.save(path, binary=True)
        return path.read_bytes()


def read_vtu(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) float64 points in mm and (T, 4) int64 tetrahedra of a ``.vtu`` file."""
    import pyvista as pv

    grid = pv.read(str(path))
    cells = grid.cells_dict
    if pv.CellType.TETRA not in cells:
        raise NotManifoldError(path, "contains no tetrahedra")
    return np.asarray(grid.points, np.float64), np.asarray(cells[pv.CellType.TETRA], np.int64)
