"""The simulator's materials as Mitsuba dicts: wet mucosa and raw cut tissue (principled
BSDFs over baked colour volumes, blended per face where a cut made the face), a film of
blood over them (blended per face with its coverage) and the instruments' brushed steel.
Pure functions of the configuration: the renderer loads them; :class:`SharedMaterials`
keeps what the renderers of one phantom's steps share."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from chisel.core.geometry import make_transform
from sim.appearance import TextureVolume
from sim.config import AppearanceConfig, BloodConfig, ToolsConfig
from sim.spot_direct import PackedTexture


def principled_dict(mi: Any, texture: TextureVolume, appearance: AppearanceConfig) -> dict:
    """The tissue's principled BSDF over a baked colour volume (Mitsuba dict)."""
    box = texture.box_mm
    to_world = make_transform(np.diag(box[1] - box[0]), box[0])
    return {
        "type": "principled",
        "base_color": {
            "type": "volume",
            "volume": {
                "type": "gridvolume",
                "grid": mi.VolumeGrid(np.ascontiguousarray(texture.rgb, dtype=np.float32)),
                "to_world": mi.ScalarTransform4f(to_world),
            },
        },
        "roughness": float(appearance.roughness),
        "specular": float(appearance.specular),
    }


def blood_dict(blood: BloodConfig) -> dict:
    """The blood film's principled BSDF: uniform colour, smoother than mucosa (wet)."""
    return {
        "type": "principled",
        "base_color": {"type": "rgb", "value": [float(x) for x in blood.rgb]},
        "roughness": float(blood.roughness),
        "specular": float(blood.specular),
    }


def tissue_properties(
    mi: Any,
    appearance: AppearanceConfig,
    texture: TextureVolume | None,
    cut: np.ndarray | None,
    cut_texture: TextureVolume | None,
    depth_only: bool,
    blood: BloodConfig | None = None,
) -> Any:
    """The tissue mesh's Mitsuba properties: the mucosa's principled BSDF, blended per face
    with the cut tissue's where faces are labelled cut (mesh attribute ``face_cut``), and
    that blended with the blood film's (``blood``: mesh attribute ``face_blood``, the
    film's coverage) when given; none for a depth-only renderer."""
    props = mi.Properties()
    if depth_only:
        return props
    assert texture is not None
    tissue = principled_dict(mi, texture, appearance)
    if cut is not None:
        assert cut_texture is not None
        tissue = {
            "type": "blendbsdf",
            "weight": {"type": "mesh_attribute", "name": "face_cut"},
            "bsdf_0": tissue,
            "bsdf_1": principled_dict(mi, cut_texture, appearance),
        }
    if blood is not None:
        tissue = {
            "type": "blendbsdf",
            "weight": {"type": "mesh_attribute", "name": "face_blood"},
            "bsdf_0": tissue,
            "bsdf_1": blood_dict(blood),
        }
    props["bsdf"] = mi.load_dict(tissue)
    return props


def steel_dict(tools: ToolsConfig) -> dict:
    """Brushed steel: a rough conductor plus a little diffuse scattering (Mitsuba's
    blendbsdf), so the metal is not black away from highlights."""
    return {
        "type": "blendbsdf",
        "weight": float(tools.diffuse),
        "bsdf_0": {
            "type": "roughconductor",
            "material": tools.material,
            "distribution": "ggx",
            "alpha": float(tools.roughness),
        },
        "bsdf_1": {"type": "diffuse", "reflectance": 0.55},
    }


class SharedMaterials:
    """What the renderers of one phantom's steps can share: the tissue's loaded Mitsuba
    BSDF (its colour volumes are ~70 MB of float32 each) and the fast integrator's packed
    textures, built once per texture volume instead of once per step (~0.4 s of each
    renderer's ~0.9 s set-up). Keyed by the volumes' identity, which it keeps alive, so
    one instance must serve one set of volumes, appearance and blood config (a phantom's
    render: :func:`sim.pipeline.render_phantom`)."""

    def __init__(self) -> None:
        self._items: dict[tuple, tuple[tuple, Any]] = {}

    def _get(self, key: tuple, keep: tuple, make: Callable[[], Any]) -> Any:
        """The object stored under ``key``, made by ``make()`` the first time; ``keep``
        holds the objects whose ``id`` is in ``key`` alive as long as the entry."""
        if key not in self._items:
            self._items[key] = (keep, make())
        return self._items[key][1]

    def tissue_properties(
        self,
        mi: Any,
        appearance: AppearanceConfig,
        texture: TextureVolume | None,
        cut: np.ndarray | None,
        cut_texture: TextureVolume | None,
        depth_only: bool,
        blood: BloodConfig | None = None,
    ) -> Any:
        """:func:`tissue_properties` for one mesh, the BSDF loaded once per volumes."""
        key = ("bsdf", id(texture), id(cut_texture) if cut is not None else None, blood)
        loaded = self._get(
            key,
            (texture, cut_texture),
            lambda: tissue_properties(mi, appearance, texture, cut, cut_texture, depth_only, blood),
        )
        # a Properties object is consumed by the shape that loads it: each mesh gets its
        # own, holding the shared BSDF object
        props = mi.Properties()
        if "bsdf" in loaded:
            props["bsdf"] = loaded["bsdf"]
        return props

    def packed(self, mi: Any, texture: TextureVolume | None) -> PackedTexture:
        """The fast integrator's packed copy of ``texture``, once per volume."""
        if texture is None:
            raise ValueError("MeshRenderer: a texture volume is required to render RGB")
        return self._get(("packed", id(texture)), (texture,), lambda: PackedTexture(mi, texture))
