"""CT slices through the change box, before and after, as a surgeon reads a CT.

For one surgical step: axial and coronal slices of the preoperative CT, of the step's true
CT and of every method's updated CT (``chisel export-ct``), through the ROI box (the change
box) plus a margin, with the removed region outlined and each method's updated-CT Dice.

Conventions of the images (radiological, what a navigation system or 3D Slicer shows):

* world = LPS (+x patient left, +y posterior, +z superior; docs/conventions.md). Slices are
  sampled on a world-aligned pixel grid through the volume's own affine (any orientation),
  nearest voxel, so every pixel is one CT voxel value and the outlines sit on voxel edges;
* **axial** (plane z = const), seen from the feet: column = +x (patient's right on the
  image's left, patient's left on the image's right), row = +y (anterior up);
* **coronal** (plane y = const), seen from the front: column = +x (patient's left on the
  image's right), row = -z (superior up);
* grey window **W 2000 / L 0 HU** (-1000 HU black .. +1000 HU white): air black, soft
  tissue mid grey, the phantoms' bone (~700 HU) near white, for the thin sinus bone;
* outlines: *red*, inside the region a method removed (tissue in the preoperative CT, air
  in its updated CT); *green*, just outside the truly removed region (tissue before, air
  in the step's true label CT). Where they agree the green ring hugs the red one.

The slices of an experiment live in a small ``.npz`` (:func:`write_ct_slices`, no pickle)
written by the workflow beside the Dice (``workflow/scripts/ct_dice.py``) and drawn by the
report (:func:`ct_slices_html`).
"""

from __future__ import annotations

import html
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from scipy import ndimage

from chisel.core.atomic import atomic_savez
from chisel.core.errors import FormatVersionError, InvalidInputError
from chisel.eval.metrics import RoiBox
from chisel.eval.panels import png_data_uri
from chisel.io.ct import DEFAULT_HU_ISO, CtVolume
from chisel.io.limits import read_npz
from chisel.io.manifest import MAX_MANIFEST_BYTES, json_type, parse_json_text

CT_SLICES_FORMAT = "endoscopic-chisel/ct-slices"
CT_SLICES_VERSION = 1

WINDOW_WIDTH_HU = 2000.0
WINDOW_LEVEL_HU = 0.0
"""Grey window of the slices: W 2000 / L 0 HU (-1000 black .. +1000 white)."""
AIR_HU = -1000.0
MARGIN_MM = 6.0
"""Context around the ROI box on each side of a slice, mm."""
UPSCALE = 4
"""Display pixels per slice pixel (nearest), so that the outlines are one display pixel."""
RED = (255, 40, 40)
GREEN = (40, 220, 40)

Plane = Literal["axial", "coronal"]
PLANES: tuple[Plane, ...] = ("axial", "coronal")
BEFORE, TRUTH = "preoperative", "truth"
"""Reserved image names: the preoperative CT and the step's true CT."""


@dataclass(frozen=True)
class CtSlice:
    """One plane of one step: HU images and removed masks on one (H, W) pixel grid.

    images : name -> (H, W) float32 HU; ``preoperative``, ``truth`` (when known), then one
        per method, in display order.
    removed : name -> (H, W) bool; ``truth`` = truly removed, a method = what it removed.
    dice : method -> updated-CT Dice of the removed region (the whole volume's, not the
        slice's).
    T_world_from_pixel : (4, 4) float64, pixel (col, row, 0, 1) -> world LPS mm.
    """

    step: int
    plane: Plane
    position_mm: float
    """The plane's world coordinate (z for axial, y for coronal), LPS mm."""
    T_world_from_pixel: np.ndarray
    images: dict[str, np.ndarray]
    removed: dict[str, np.ndarray] = field(default_factory=dict)
    dice: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        src = f"CT slice (step {self.step}, {self.plane})"
        if self.plane not in PLANES:
            raise InvalidInputError(src, f"plane must be one of {PLANES}, got {self.plane!r}")
        if not self.images or BEFORE not in self.images:
            raise InvalidInputError(src, f"needs the {BEFORE!r} image")
        shape = np.shape(self.images[BEFORE])
        for kind, arrays in (("image", self.images), ("mask", self.removed)):
            for name, arr in arrays.items():
                if np.ndim(arr) != 2 or np.shape(arr) != shape:
                    raise InvalidInputError(
                        src, f"{kind} {name!r} is {np.shape(arr)}, expected {shape} (H, W)"
                    )
        for name in self.removed:
            if name not in self.images:
                raise InvalidInputError(src, f"mask {name!r} has no image")

    @property
    def methods(self) -> list[str]:
        return [n for n in self.images if n not in (BEFORE, TRUTH)]


def ct_tissue(ct: CtVolume) -> np.ndarray:
    """(X, Y, Z) bool: tissue in a CT (label > 0, or HU above -480), as the Dice counts it."""
    return ct.data > 0 if ct.kind == "label" else ct.data > DEFAULT_HU_ISO


def removed_mask(before: CtVolume, after: CtVolume) -> np.ndarray:
    """(X, Y, Z) bool: tissue in ``before`` and not in ``after`` (one grid)."""
    if before.shape != after.shape:
        raise InvalidInputError(after.source or "CT", "not on the preoperative CT's grid")
    return ct_tissue(before) & ~ct_tissue(after)


# --------------------------------------------------------------------------------------
# Sampling


def _plane_axes(plane: Plane) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(column direction, row direction, normal) unit vectors in LPS, and the normal axis."""
    ex, ey, ez = np.eye(3)
    if plane == "axial":
        return ex, ey, ez, 2  # patient's left right, anterior up
    return ex, -ez, ey, 1  # coronal: patient's left right, superior up


def slice_frame(
    plane: Plane, box: RoiBox, position_mm: float, pixel_mm: float, margin_mm: float = MARGIN_MM
) -> tuple[np.ndarray, tuple[int, int]]:
    """The pixel grid of a slice: (T_world_from_pixel (4, 4), (H, W)).

    Pixel (col c, row r) is centred at ``T_world_from_pixel @ [c, r, 0, 1]``, world LPS mm,
    covering the box plus ``margin_mm`` in the plane's two directions.
    """
    if not pixel_mm > 0:
        raise InvalidInputError("pixel_mm", f"must be positive, got {pixel_mm}")
    u, v, n, axis = _plane_axes(plane)
    lo = np.asarray(box.min_mm, float) - margin_mm
    hi = np.asarray(box.max_mm, float) + margin_mm
    corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    cu, cv = corners @ u, corners @ v
    width = int(np.floor((cu.max() - cu.min()) / pixel_mm)) + 1
    height = int(np.floor((cv.max() - cv.min()) / pixel_mm)) + 1
    origin = u * cu.min() + v * cv.min()
    origin[axis] = position_mm
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = u * pixel_mm, v * pixel_mm, n, origin
    return T, (height, width)


def sample_slice(
    volume: np.ndarray,
    T_world_from_voxel: np.ndarray,
    T_world_from_pixel: np.ndarray,
    shape_hw: tuple[int, int],
    outside: float | bool,
) -> np.ndarray:
    """Nearest-voxel values of ``volume`` (X, Y, Z) at the pixel centres of a slice.

    Returns (H, W) of the volume's dtype; pixels outside the volume get ``outside``.
    """
    h, w = shape_hw
    rows, cols = np.mgrid[0:h, 0:w]
    pix = np.stack([cols.ravel(), rows.ravel(), np.zeros(h * w), np.ones(h * w)])
    ijk = (np.linalg.inv(T_world_from_voxel) @ T_world_from_pixel @ pix)[:3]
    idx = np.rint(ijk).astype(np.int64)
    inside = np.all((idx >= 0) & (idx < np.array(volume.shape)[:, None]), axis=0)
    out = np.full(h * w, outside, dtype=volume.dtype)
    out[inside] = volume[idx[0, inside], idx[1, inside], idx[2, inside]]
    return out.reshape(h, w)


def slice_position_mm(
    plane: Plane, mask: np.ndarray, T_world_from_voxel: np.ndarray, box: RoiBox, pixel_mm: float
) -> float:
    """Where to cut: the plane (on the pixel grid) holding most voxels of ``mask`` inside
    the box; the box centre when the mask has none there."""
    axis = _plane_axes(plane)[3]
    ijk = np.argwhere(mask)
    if len(ijk):
        world = ijk @ T_world_from_voxel[:3, :3].T + T_world_from_voxel[:3, 3]
        world = world[box.contains(world)]
        if len(world):
            keys, counts = np.unique(np.rint(world[:, axis] / pixel_mm), return_counts=True)
            return float(keys[np.argmax(counts)] * pixel_mm)
    return float((box.min_mm[axis] + box.max_mm[axis]) / 2)


def make_ct_slices(
    step: int,
    before: CtVolume,
    updated: Mapping[str, CtVolume],
    box: RoiBox,
    truth_label: CtVolume | None = None,
    truth_image: CtVolume | None = None,
    dice: Mapping[str, float] | None = None,
) -> list[CtSlice]:
    """Axial and coronal slices of one step through the change box.

    before : the preoperative HU CT; updated : method -> its updated CT (same grid);
    truth_label : the step's true CT (label or HU) for the truly removed region;
    truth_image : the step's true HU CT to show (default: ``truth_label`` when it is HU).
    Both planes cut through the most truly removed voxels (else the most voxels any
    method removed, else the box centre). Returns [axial, coronal].
    """
    masks = {m: removed_mask(before, ct) for m, ct in updated.items()}
    if truth_label is not None:
        masks[TRUTH] = removed_mask(before, truth_label)
    if truth_image is None and truth_label is not None and truth_label.kind == "intensity":
        truth_image = truth_label
    vols: dict[str, CtVolume] = {BEFORE: before}
    if truth_image is not None:
        vols[TRUTH] = truth_image
    vols.update(updated)
    for name, vol in vols.items():
        if vol.shape != before.shape or not np.allclose(
            vol.T_world_from_voxel, before.T_world_from_voxel, atol=1e-4
        ):
            raise InvalidInputError(vol.source or name, "not on the preoperative CT's grid")
    pixel_mm = float(before.spacing_mm.min())
    guide = masks.get(TRUTH)
    if guide is None or not guide.any():
        guide = np.logical_or.reduce(list(masks.values())) if masks else np.zeros(before.shape)
    out = []
    for plane in PLANES:
        pos = slice_position_mm(plane, guide, before.T_world_from_voxel, box, pixel_mm)
        T, hw = slice_frame(plane, box, pos, pixel_mm)
        Tv = before.T_world_from_voxel
        images = {
            n: sample_slice(v.data, Tv, T, hw, AIR_HU).astype(np.float32) for n, v in vols.items()
        }
        removed = {n: sample_slice(m, Tv, T, hw, False) for n, m in masks.items()}
        if TRUTH in removed and TRUTH not in images:
            images[TRUTH] = images[BEFORE].copy()  # no true image: show the mask on the preop
        out.append(CtSlice(step, plane, pos, T, images, removed, dict(dice or {})))
    return out


# --------------------------------------------------------------------------------------
# Images


def window_grey(
    hu: np.ndarray, width_hu: float = WINDOW_WIDTH_HU, level_hu: float = WINDOW_LEVEL_HU
):
    """(H, W) HU -> (H, W) uint8 grey: level - width/2 black, level + width/2 white."""
    t = (np.asarray(hu, np.float64) - (level_hu - width_hu / 2)) / width_hu
    return np.round(np.clip(t, 0.0, 1.0) * 255).astype(np.uint8)


def _inner_edge(mask: np.ndarray) -> np.ndarray:
    return mask & ~ndimage.binary_erosion(mask, border_value=0)


def slice_rgb(
    hu: np.ndarray,
    removed: np.ndarray | None = None,
    true_removed: np.ndarray | None = None,
    upscale: int = UPSCALE,
) -> np.ndarray:
    """A windowed slice, ``upscale`` x nearest, with the outlines drawn.

    hu : (H, W) HU. removed : (H, W) bool, outlined in red on the inside of its edge.
    true_removed : (H, W) bool, outlined in green just outside its edge.
    Returns (H * upscale, W * upscale, 3) uint8 RGB.
    """
    k = int(upscale)
    grey = np.kron(window_grey(hu), np.ones((k, k), np.uint8))
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    if true_removed is not None and np.any(true_removed):
        up = np.kron(np.asarray(true_removed, bool), np.ones((k, k), bool))
        rgb[ndimage.binary_dilation(up) & ~up] = GREEN
    if removed is not None and np.any(removed):
        up = np.kron(np.asarray(removed, bool), np.ones((k, k), bool))
        rgb[_inner_edge(up)] = RED
    return rgb


_ORIENTATION = {
    "axial": ("z", "seen from the feet: patient's right on the left, anterior up"),
    "coronal": ("y", "seen from the front: patient's right on the left, superior up"),
}


def _caption(name: str, s: CtSlice) -> str:
    if name == BEFORE:
        return "preoperative CT" + (
            " <small>(green: truly removed)</small>" if TRUTH in s.removed else ""
        )
    if name == TRUTH:
        return "true CT after the step"
    d = s.dice.get(name)
    dice = "" if d is None else f"<br>updated-CT Dice <b>{d:.3f}</b>"
    return f"{html.escape(name)}: updated CT{dice}"


def ct_slice_html(s: CtSlice) -> str:
    """One plane of one step as a row of images with R/L markers and Dice captions."""
    truth = s.removed.get(TRUTH)
    figs = []
    for name, hu in s.images.items():
        own = None if name in (BEFORE, TRUTH) else s.removed.get(name)
        rgb = slice_rgb(hu, own, truth)
        figs.append(
            f"<figure><div class='ctimg'><span class='ori l'>R</span>"
            f"<img class='ct' alt='{s.plane} {html.escape(name)} step {s.step}' "
            f"data-plane='{s.plane}' data-name='{html.escape(name)}' src='{png_data_uri(rgb)}'>"
            f"<span class='ori r'>L</span></div><figcaption>{_caption(name, s)}</figcaption></figure>"
        )
    coord, how = _ORIENTATION[s.plane]
    return (
        f"<h4>{s.plane}, {coord} = {s.position_mm:.1f} mm (LPS), {how}</h4>"
        f"<div class='panel'>{''.join(figs)}</div>"
    )


CT_SLICES_CSS = """
.ctimg { display: flex; align-items: center; gap: 0.2em; }
.ori { font-size: 0.8em; color: #555; } img.ct { image-rendering: pixelated; width: 200px; }
"""


def ct_slices_html(slices: Sequence[CtSlice]) -> str:
    """The report section: per step, the axial and the coronal row (see the module doc)."""
    parts = [
        "<p class='note'>Slices of the CT through the change box (ROI box + "
        f"{MARGIN_MM:g} mm), one CT voxel per pixel (nearest). Grey window W "
        f"{WINDOW_WIDTH_HU:g} / L {WINDOW_LEVEL_HU:g} HU. Radiological orientation: the "
        "patient's left is on the image's right (R / L marked). <span style='color:#d22'>"
        "Red</span>: inside the region the method removed (tissue in the preoperative CT, "
        "air in its updated CT); <span style='color:#2a2'>green</span>: just outside the "
        "truly removed region (tissue before, air in the step's true label CT). Dice: "
        "updated-CT Dice of the removed region over the whole volume.</p>"
    ]
    for step in sorted({s.step for s in slices}):
        parts.append(f"<h3>bite {step}</h3>" if step else "<h3>preop</h3>")
        parts += [ct_slice_html(s) for s in slices if s.step == step]
    return "\n".join(parts)


# --------------------------------------------------------------------------------------
# The slices file (npz, no pickle)


def write_ct_slices(path: str | Path, slices: Sequence[CtSlice]) -> Path:
    """Write slices to an ``.npz`` (atomically, no pickle).

    Layout: ``meta`` (0-d string, JSON: format, version, and per slice its step, plane,
    position_mm, T_world_from_pixel, image and mask names, dice), then ``s<i>_hu_<k>``
    (H, W) float32 HU and ``s<i>_removed_<k>`` (H, W) bool, k = the name's index.
    """
    if not slices:
        raise InvalidInputError(path, "no CT slice to write")
    arrays: dict[str, np.ndarray] = {}
    entries = []
    for i, s in enumerate(slices):
        names = list(s.images)
        for k, name in enumerate(names):
            arrays[f"s{i}_hu_{k}"] = np.asarray(s.images[name], np.float32)
            if name in s.removed:
                arrays[f"s{i}_removed_{k}"] = np.asarray(s.removed[name], bool)
        entries.append(
            {
                "step": int(s.step),
                "plane": s.plane,
                "position_mm": float(s.position_mm),
                "T_world_from_pixel": np.asarray(s.T_world_from_pixel, float).tolist(),
                "names": names,
                "removed": [n for n in names if n in s.removed],
                "dice": {k: float(v) for k, v in s.dice.items()},
            }
        )
    meta = {"format": CT_SLICES_FORMAT, "version": CT_SLICES_VERSION, "slices": entries}
    arrays["meta"] = np.array(json.dumps(meta))
    return atomic_savez(path, arrays)


def _read_meta(path: Path, raw: np.ndarray) -> dict:
    """The ``meta`` member: one JSON object, read with the limits a manifest is read with
    (:func:`chisel.io.manifest.read_json_manifest`: size, nesting depth, an object)."""
    if raw.dtype.kind != "U" or raw.ndim != 0:
        raise InvalidInputError(path, f"meta must be one JSON string, got {raw.dtype} {raw.shape}")
    text = str(raw)
    if len(text) > MAX_MANIFEST_BYTES:
        raise InvalidInputError(
            path, f"meta is {len(text)} characters; at most {MAX_MANIFEST_BYTES} are read"
        )
    meta = parse_json_text(path, text, what="meta")
    if not isinstance(meta, dict):
        raise InvalidInputError(path, f"meta: expected a JSON object, got {json_type(meta)}")
    return meta


def read_ct_slices(path: str | Path) -> list[CtSlice]:
    """Read a slices file written by :func:`write_ct_slices`.

    Read as a model file is (:meth:`chisel.model.TsdfModel.load`): declared sizes and
    object arrays refused from the headers, no pickle; every problem is one error naming
    the file."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "CT slices file is missing")
    data = read_npz(path, "CT slices")
    meta = _read_meta(path, data["meta"]) if "meta" in data else {}
    if meta.get("format") != CT_SLICES_FORMAT:
        raise FormatVersionError(path, f"not a CT slices file (format {CT_SLICES_FORMAT!r})")
    if meta.get("version") != CT_SLICES_VERSION:
        raise FormatVersionError(
            path,
            f"CT slices version {meta.get('version')!r}; this reader reads {CT_SLICES_VERSION}"[
                :300
            ],
        )
    out = []
    try:
        for i, e in enumerate(meta["slices"]):
            names = e["names"]
            images = {n: data[f"s{i}_hu_{k}"] for k, n in enumerate(names)}
            removed = {n: data[f"s{i}_removed_{names.index(n)}"] for n in e["removed"]}
            out.append(
                CtSlice(
                    int(e["step"]),
                    e["plane"],
                    float(e["position_mm"]),
                    np.asarray(e["T_world_from_pixel"], float),
                    images,
                    removed,
                    {k: float(v) for k, v in e["dice"].items()},
                )
            )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InvalidInputError(path, f"malformed CT slices file: {exc!r}"[:300]) from None
    return out
