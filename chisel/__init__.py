"""Endoscopic Chisel: keep a preoperative sinus model true while surgery removes tissue.

The public API, in the order a user meets it: a :class:`Camera` and tracked poses
(``T_world_from_cam``, mm, OpenCV axes), a :class:`Sequence` folder on disk, a
:class:`TsdfModel` built from the CT with :func:`build_preop_model`, and an update per
surgical step, either a whole sequence at once (:func:`update_step`) or frame by frame in
a navigation system (:class:`ChiselUpdater`), tuned by frozen configs
(:class:`BuildConfig`, :class:`UpdateConfig`, :class:`ChangeConfig`,
:class:`RegistrationConfig`).

A spherical cavity of radius 10 mm seen from near its centre; then a pocket behind its
far wall is opened (tissue up to z = 12 mm removed) and a streaming update with exact
depth carves it:

>>> import numpy as np, trimesh
>>> from chisel import BuildConfig, Camera, ChiselUpdater, Frame, UpdateConfig
>>> from chisel import build_preop_model, extract_mesh, look_at
>>> from chisel.core.raycast import MeshRaycaster
>>> cam = Camera(64, 48, np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]]))
>>> poses = np.stack([look_at(np.array([x, y, 0.0]), np.array([0, 0, 10.0]), np.array([0, -1.0, 0]))
...                   for x in (-2, 0, 2) for y in (-2, 2)])
>>> cavity = trimesh.creation.icosphere(3, radius=10.0)
>>> model = build_preop_model(cavity, cam, poses, BuildConfig(voxel_size_mm=1.0, trunc_mm=3.0))
>>> pocket = trimesh.creation.box((8, 8, 4), trimesh.transformations.translation_matrix((0, 0, 10)))
>>> after = cavity.union(pocket)  # manifold3d
>>> exact = MeshRaycaster(after.vertices, after.faces)
>>> upd = ChiselUpdater(model, cam, lambda f: exact.render_depth(cam, f.T_world_from_cam),
...                     UpdateConfig(register=False, solve_scale="never"))
>>> upd.begin_step()
>>> reports = [upd.process(Frame(i, T)) for i, T in enumerate(poses)]
>>> _ = upd.end_step()
>>> upd.model.step, round(float(extract_mesh(model).bounds[1, 2])), round(float(extract_mesh(upd.model).bounds[1, 2]))
(1, 10, 12)

``chisel`` never imports the simulator (``sim``) or the phantom generator (``phantoms``):
it runs on real patient data. Names are resolved on first use, so ``import chisel`` stays
cheap for the command line (torch, Open3D and numba load only when needed).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS: dict[str, str] = {
    "Camera": "chisel.core.geometry",
    "look_at": "chisel.core.geometry",
    "ChiselError": "chisel.core.errors",
    "Sequence": "chisel.io.sequence",
    "Frame": "chisel.io.sequence",
    "write_sequence": "chisel.io.sequence",
    "load_ct_surface": "chisel.io.ct",
    "TsdfModel": "chisel.model",
    "ChangeConfig": "chisel.change",
    "RegistrationConfig": "chisel.registration",
    "BuildConfig": "chisel.build",
    "UpdateConfig": "chisel.update_config",
    "build_preop_model": "chisel.build",
    "update_step": "chisel.batch",
    "ChiselUpdater": "chisel.updater",
    "extract_mesh": "chisel.mesh",
}

__all__ = [
    "BuildConfig",
    "Camera",
    "ChangeConfig",
    "ChiselError",
    "ChiselUpdater",
    "Frame",
    "RegistrationConfig",
    "Sequence",
    "TsdfModel",
    "UpdateConfig",
    "build_preop_model",
    "extract_mesh",
    "load_ct_surface",
    "look_at",
    "update_step",
    "write_sequence",
]

if TYPE_CHECKING:
    from chisel.batch import update_step
    from chisel.build import BuildConfig, build_preop_model
    from chisel.change import ChangeConfig
    from chisel.core.errors import ChiselError
    from chisel.core.geometry import Camera, look_at
    from chisel.io.ct import load_ct_surface
    from chisel.io.sequence import Frame, Sequence, write_sequence
    from chisel.mesh import extract_mesh
    from chisel.model import TsdfModel
    from chisel.registration import RegistrationConfig
    from chisel.update_config import UpdateConfig
    from chisel.updater import ChiselUpdater


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'chisel' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
