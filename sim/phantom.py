"""Reading a phantom folder (``phantom.json`` + meshes) written by ``python -m phantoms``.

The simulator never imports ``phantoms``; this module reads its on-disk contract::

    DIR/phantom.json  {"format": "endoscopic-chisel/phantom", "version": 1, "seed": S,
                       "steps": [{"step": 0, "name": "preop", "mesh": "meshes/step_00.ply"}, ...],
                       "roi_box_mm": [[xmin, ymin, zmin], [xmax, ymax, zmax]],
                       "target": {"name": ..., "center_mm": [x, y, z], "normal": [nx, ny, nz]},
                       "airway_path_mm": [[x, y, z], ...]}

Each mesh is the closed tissue solid (world = CT frame, mm); the camera lives in the air.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from chisel.io.manifest import named_path, read_json_manifest
from chisel.io.meshfile import MESH_SUFFIXES, READABLE_MESH_SUFFIXES, read_mesh_file
from sim.errors import MeshError, PhantomError

PHANTOM_FORMAT = "endoscopic-chisel/phantom"
PHANTOM_VERSION = 1


@dataclass(frozen=True)
class PhantomStep:
    """One surgical step of a phantom."""

    step: int
    """Step index (0 = preoperative)."""
    name: str
    """Step name, e.g. ``preop`` or ``bite_1``."""
    mesh_path: Path
    """Absolute path of the tissue mesh after this step."""


@dataclass(frozen=True)
class Phantom:
    """A phantom manifest in memory (meshes are loaded on demand with :func:`load_mesh`)."""

    path: Path
    """Absolute phantom folder."""
    seed: int
    """Seed the phantom was generated with."""
    steps: tuple[PhantomStep, ...]
    """Steps in order, step 0 first."""
    roi_box_mm: np.ndarray
    """(2, 3) float64 [[xmin, ymin, zmin], [xmax, ymax, zmax]], the change region, mm."""
    target_center_mm: np.ndarray
    """(3,) float64 centre of the surgical target on the tissue surface, mm."""
    target_normal: np.ndarray
    """(3,) float64 unit normal pointing from the target surface into the airway."""
    airway_path_mm: np.ndarray
    """(N, 3) float64 polyline from the nostril to a point in front of the target, mm."""
    target_name: str = "target"
    """Name of the target structure."""

    @property
    def num_steps(self) -> int:
        """Number of surgical steps after the preoperative one."""
        return len(self.steps) - 1


def _vec(value: Any, shape: tuple[int, ...], where: str, source: Path) -> np.ndarray:
    if value is None:
        raise PhantomError(source, f"{where}: missing")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise PhantomError(source, f"{where}: expected numbers, got {value!r}"[:200]) from None
    if shape[0] == -1:
        ok = arr.ndim == 2 and arr.shape[1] == shape[1]
        want = f"(N, {shape[1]})"
    else:
        ok = arr.shape == shape
        want = str(shape)
    if not ok:
        raise PhantomError(source, f"{where}: expected an array of shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PhantomError(source, f"{where}: values are not finite (NaN or inf)")
    return arr


def _int(value: Any, where: str, source: Path) -> int:
    # JSON numbers only: int("1") or int(1.7) would hide a broken manifest.
    if not isinstance(value, int) or isinstance(value, bool):
        raise PhantomError(source, f"{where}: expected an integer, got {value!r}"[:200])
    return value


def load_phantom(path: str | Path, allow_outside: bool = False) -> Phantom:
    """Read and validate ``path/phantom.json``; raises :class:`PhantomError` naming the problem.

    Each step's mesh must resolve (links followed) inside the phantom folder unless
    ``allow_outside`` (``sim render --allow-outside-phantom``):
    :class:`~chisel.core.errors.OutsideManifestError` otherwise, so one phantom cannot
    render another's (or any) file.
    """
    root = Path(path).absolute()
    manifest = root / "phantom.json"
    if not root.is_dir():
        raise PhantomError(root, "phantom folder does not exist")
    if not manifest.is_file():
        raise PhantomError(manifest, "phantom.json is missing (run `python -m phantoms generate`)")
    data = read_json_manifest(manifest, PhantomError)
    if data.get("format") != PHANTOM_FORMAT:
        raise PhantomError(
            manifest, f"format is {data.get('format')!r}, expected {PHANTOM_FORMAT!r}"
        )
    if data.get("version") != PHANTOM_VERSION:
        raise PhantomError(
            manifest, f"version {data.get('version')!r}, this reader reads {PHANTOM_VERSION}"
        )
    for key in ("steps", "roi_box_mm", "target", "airway_path_mm"):
        if key not in data:
            raise PhantomError(manifest, f"missing key {key!r}")
    raw_steps = data["steps"]
    if not isinstance(raw_steps, list) or not raw_steps:
        raise PhantomError(manifest, "steps: expected a non-empty list")
    steps = []
    for i, s in enumerate(raw_steps):
        if not isinstance(s, dict) or "mesh" not in s:
            raise PhantomError(manifest, f"steps[{i}]: expected an object with a 'mesh' path")
        if _int(s.get("step", i), f"steps[{i}].step", manifest) != i:
            raise PhantomError(manifest, f"steps[{i}]: step index is {s.get('step')}, expected {i}")
        mesh = s["mesh"]
        if not isinstance(mesh, str) or not mesh:
            raise PhantomError(manifest, f"steps[{i}].mesh: expected a file path, got {mesh!r}")
        mesh_path = named_path(
            manifest,
            mesh,
            f"steps[{i}].mesh",
            allow_outside=allow_outside,
            option="--allow-outside-phantom",
        )
        if mesh_path.suffix.lower() not in MESH_SUFFIXES:
            raise PhantomError(
                manifest, f"steps[{i}].mesh: expected a PLY/STL/OBJ mesh, got {mesh!r}"[:300]
            )
        steps.append(PhantomStep(i, str(s.get("name", f"step_{i}")), mesh_path))
    roi = _vec(data["roi_box_mm"], (2, 3), "roi_box_mm", manifest)
    if np.any(roi[1] <= roi[0]):
        raise PhantomError(
            manifest, f"roi_box_mm: max must exceed min on every axis, got {roi.tolist()}"
        )
    target = data["target"]
    if not isinstance(target, dict):
        raise PhantomError(manifest, "target: expected an object")
    center = _vec(target.get("center_mm"), (3,), "target.center_mm", manifest)
    normal = _vec(target.get("normal"), (3,), "target.normal", manifest)
    n = float(np.linalg.norm(normal))
    if n < 1e-9:
        raise PhantomError(manifest, "target.normal is zero")
    airway = _vec(data["airway_path_mm"], (-1, 3), "airway_path_mm", manifest)
    if len(airway) < 2:
        raise PhantomError(manifest, f"airway_path_mm: need at least 2 points, got {len(airway)}")
    return Phantom(
        path=root,
        seed=_int(data.get("seed", 0), "seed", manifest),
        steps=tuple(steps),
        roi_box_mm=roi,
        target_center_mm=center,
        target_normal=normal / n,
        airway_path_mm=airway,
        target_name=str(target.get("name", "target")),
    )


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Load a closed tissue mesh (PLY/STL/OBJ, mm); raises :class:`MeshError`.

    Refused: a missing or unreadable file, an empty mesh, non-finite vertices, and a mesh
    that is not watertight (the simulator's inside/outside tests need a closed solid).
    """
    p = Path(path)
    if not p.is_file():
        raise MeshError(p, "mesh file does not exist")
    # Processed (duplicate vertices merged): smooth vertex normals for rendering.
    mesh = read_mesh_file(p, "mesh file", READABLE_MESH_SUFFIXES, process=True, error=MeshError)
    mesh = check_mesh(mesh, str(p))
    # Lets path errors name the mesh file (sim.collision.TissueDistance.source).
    mesh.metadata["file_path"] = str(p.absolute())
    return mesh


def check_mesh(mesh: trimesh.Trimesh, source: str = "mesh") -> trimesh.Trimesh:
    """Validate an in-memory tissue mesh (see :func:`load_mesh`); returns it."""
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(source, "mesh is empty (no triangles)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(source, "mesh vertices contain NaN/inf")
    if not mesh.is_watertight:
        raise MeshError(
            source,
            f"mesh is not watertight ({len(mesh.faces)} faces, "
            f"{int(np.sum(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1).shape[0]))} "
            f"boundary edges): the tissue solid must be closed",
        )
    return mesh
