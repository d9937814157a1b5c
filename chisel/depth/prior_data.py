"""Training pairs for the change-aware network: frame + prior render -> true depth.

For every frame of a surgical step k the *prior* is the previous step's surface (step
k-1's mesh; step 0's for the preoperative sweep, which has no change) rendered at the
frame's **tracked** pose, so the network learns to live with tracking error (the image
is taken from the true pose, the render from the tracked one). Two targets:

- ``target_pose="tracked"`` (default): step k's surface rendered at the **tracked** pose,
  i.e. what the model's render should become once the change is carved. The updater
  compares and fuses the estimate at the tracked pose, so this is the depth it needs:
  unchanged tissue is exactly the prior, removed tissue deeper. The label is
  ``target - prior > threshold_mm``, exact.
- ``target_pose="true"``: the frame's rendered true depth (true pose). With the
  simulator's default tracking error (0.5 mm / 0.5 deg hand-eye plus jitter) the prior
  differs from it by ~4 % (median) on unchanged tissue, which one frame cannot reveal;
  the label is then "true depth deeper than step k-1's surface seen from the true pose".

``PriorSet.true_mm`` always holds the frame's true depth (for reporting).

Inputs follow the dataset layout of ``python -m sim dataset`` (read as files only:
``chisel`` never imports ``sim`` or ``phantoms``)::

    DIR/dataset.json          {"sequences": [{"path", "phantom_seed", "kind", "step"}, ...]}
    DIR/phantoms/seed_S/phantom.json   {"steps": [{"step": k, "mesh": "meshes/step_kk.ply"}]}

Per-patient fine-tuning (:func:`preop_prior_set`) uses the preoperative sequence and the
CT surface mesh: prior = the CT surface at the tracked pose; target = the CT surface at
the true pose where the sequence has true poses (synthetic data), else the prior itself
(real data: the preop sweep shows no change, so the network learns "this patient's
tissue, unchanged, is the render"). A sweep without change alone teaches the network to
copy its prior; :func:`add_synthetic_removal` puts removals back in (a lamella in front
of the surface in the prior only, the frame and target unchanged).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import trimesh

from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.raycast import MeshRaycaster
from chisel.depth.change_train import PriorSet
from chisel.depth.data import DATASET_INDEX, SequenceRef, check_training_seeds, phantom_seed
from chisel.io.manifest import named_path, read_json_manifest
from chisel.io.meshfile import read_mesh_file
from chisel.io.sequence import Sequence

log = logging.getLogger(__name__)

CHANGE_THRESHOLD_MM = 1.0
"""Depth growth that labels a pixel as changed (the paper's change threshold)."""


@dataclass(frozen=True)
class StepSequenceRef:
    """A rendered sequence of one surgical step and the phantom it shows."""

    path: Path
    """Sequence folder (RGB, depth at the true pose, tracked and true poses)."""
    seed: int
    """Phantom seed."""
    step: int
    """Surgical step shown (0 = preoperative sweep)."""
    phantom_dir: Path
    """Phantom folder (``phantom.json`` and the meshes per step)."""


def read_step_dataset(
    inputs: list[str | Path], allow_outside: bool = False
) -> list[StepSequenceRef]:
    """Step sequences of dataset folders (or ``dataset.json`` files) from ``sim dataset``.

    The index is a manifest like the monocular one (:func:`chisel.depth.data.
    read_dataset_index`): read through :func:`read_json_manifest`, and every sequence
    folder it names must lie inside its folder unless ``allow_outside``; so must the
    phantom folder ``phantoms/seed_S`` that an entry's ``phantom_seed`` names (a link there
    would read another dataset's phantom.json and meshes).
    """
    if not inputs:
        raise InvalidInputError("--data", "no dataset given")
    refs = []
    for item in inputs:
        index = Path(item)
        if index.is_dir():
            index = index / DATASET_INDEX
        entries = read_json_manifest(index).get("sequences")
        if not isinstance(entries, list) or not entries:
            raise InvalidInputError(index, "expected a non-empty 'sequences' list")
        for i, e in enumerate(entries):
            where = f"{index} sequences[{i}]"
            if not isinstance(e, dict) or not all(k in e for k in ("path", "phantom_seed", "step")):
                raise InvalidInputError(
                    where, "change-aware training needs path, phantom_seed and step per entry "
                    "(a dataset from python -m sim dataset)",
                )  # fmt: skip
            seed = phantom_seed(e["phantom_seed"], "phantom_seed", where)
            step = _integer(e["step"], "step", where)
            path = named_path(
                index, e["path"], f"sequences[{i}]", allow_outside=allow_outside, kind="folder"
            )
            phantom_dir = named_path(
                index,
                f"phantoms/seed_{seed}",
                f"sequences[{i}].phantom_seed",
                allow_outside=allow_outside,
            )
            refs.append(StepSequenceRef(path, seed, step, phantom_dir))
    return refs


def _integer(value: Any, what: str, where: str | Path) -> int:
    """A JSON value as an int, as leniently as ``int()`` (as before), else the error."""
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError):  # 1e400 reads as infinity
        raise InvalidInputError(where, f"{what} must be an integer, got {value!r}") from None


def check_change_training_seeds(refs: list[StepSequenceRef]) -> None:
    """Raise if a sequence shows a phantom reserved for evaluation (seeds 0-99)."""
    check_training_seeds([SequenceRef(r.path, r.seed) for r in refs])


def phantom_step_mesh(phantom_dir: str | Path, step: int) -> trimesh.Trimesh:
    """The surface mesh of surgical step ``step`` of a phantom folder (world mm)."""
    header = Path(phantom_dir) / "phantom.json"
    named_path(header, header.name, "phantom.json")  # not a link to another phantom's
    listed = read_json_manifest(header).get("steps", [])
    if not isinstance(listed, list):
        raise InvalidInputError(header, f"'steps' must be a list, got {type(listed).__name__}")
    steps = {
        _integer(s["step"], "step", header): s["mesh"]
        for s in listed
        if isinstance(s, dict) and "step" in s and "mesh" in s
    }
    if step not in steps:
        raise InvalidInputError(header, f"no mesh for step {step} (steps: {sorted(steps)})")
    mesh_path = named_path(header, steps[step], f"steps[step={step}].mesh", kind="file")
    return read_mesh_file(mesh_path, f"step {step} mesh")


def _frame_indices(n: int, frame_step: int) -> list[int]:
    if frame_step < 1:
        raise InvalidInputError("frame_step", f"must be >= 1, got {frame_step}")
    return list(range(0, n, frame_step))


def _valid_target(seq: Sequence, i: int) -> np.ndarray:
    depth = seq.depth_mm(i)
    mask = seq.mask(i)
    return depth if mask is None else np.where(mask, depth, np.float32(np.nan)).astype(np.float32)


def build_prior_set(
    refs: list[StepSequenceRef],
    frame_step: int = 1,
    threshold_mm: float = CHANGE_THRESHOLD_MM,
    min_valid_fraction: float = 0.05,
    target_pose: Literal["tracked", "true"] = "tracked",
    surface_of: Callable[[Path, int], trimesh.Trimesh] = phantom_step_mesh,
) -> PriorSet:
    """Render every ``frame_step``-th frame's prior and change label; see the module doc.

    Frames whose prior and target overlap on fewer than ``min_valid_fraction`` of the
    pixels are skipped. Every sequence must share one image size. ``surface_of(phantom_dir,
    step)`` gives the surface rendered for a step: the phantom's mesh (default), or what a
    model holds of it (``chisel depth train --prior-surface model``), for prior and target
    alike, so that unchanged tissue stays exactly the prior.
    """
    if target_pose not in ("tracked", "true"):
        raise InvalidInputError("target_pose", f"expected 'tracked' or 'true', got {target_pose!r}")
    # Checked and sized before anything is rendered: the pairs are written into arrays
    # allocated once (a list of frames stacked at the end held every frame twice, ~17 GB
    # at peak for the 6 700 frames of the shipped checkpoint's data).
    checked: list[tuple[StepSequenceRef, Sequence, np.ndarray, list[int]]] = []
    shape: tuple[int, int] | None = None
    for ref in refs:
        seq = Sequence(ref.path)
        if not (seq.has_rgb and seq.has_depth) or seq.true_poses is None:
            raise InvalidInputError(
                ref.path,
                "change-aware training needs RGB, depth and true poses (a rendered sequence)",
            )
        if shape is None:
            shape = seq.camera.shape
        elif seq.camera.shape != shape:
            raise InvalidInputError(
                ref.path, f"image size {seq.camera.shape} != {shape} of earlier sequences"
            )
        checked.append((ref, seq, seq.true_poses, _frame_indices(len(seq), frame_step)))
    total = sum(len(idx) for *_, idx in checked)
    h, w = shape if shape is not None else (0, 0)
    rgb_all = np.empty((total, h, w, 3), np.uint8)
    prior_all, target_all, true_all = (np.empty((total, h, w), np.float32) for _ in range(3))
    changed_all = np.empty((total, h, w), bool)
    sources: list[str] = []
    n = 0
    for ref, seq, true_poses, idx in checked:
        mesh = surface_of(ref.phantom_dir, max(ref.step - 1, 0))
        rc = MeshRaycaster(mesh.vertices, mesh.faces)
        prior = rc.render_depths(seq.camera, seq.poses[idx])
        if target_pose == "true":
            reference = rc.render_depths(seq.camera, true_poses[idx])
        else:
            now = surface_of(ref.phantom_dir, ref.step)
            reference = prior
            tracked_now = MeshRaycaster(now.vertices, now.faces).render_depths(
                seq.camera, seq.poses[idx]
            )
        for j, i in enumerate(idx):
            true = _valid_target(seq, i)
            if target_pose == "true":
                target = true
            else:
                target = np.where(np.isfinite(true), tracked_now[j], np.float32(np.nan))
            both = np.isfinite(prior[j]) & np.isfinite(target)
            if both.mean() < min_valid_fraction:
                continue
            with np.errstate(invalid="ignore"):
                changed = np.isfinite(target) & (
                    ~np.isfinite(reference[j]) | (target - reference[j] > threshold_mm)
                )
            rgb_all[n] = seq.rgb(i)
            prior_all[n] = prior[j]
            target_all[n] = target
            changed_all[n] = changed & np.isfinite(prior[j])
            true_all[n] = true
            sources.append(f"{ref.path}#{i}")
            n += 1
    if n == 0:
        raise EmptyResultError(f"no usable frame in {len(refs)} sequence(s)")
    log.info("built %d prior/target pairs from %d sequences", n, len(refs))
    return PriorSet(
        rgb=torch.from_numpy(rgb_all[:n]),
        prior_mm=torch.from_numpy(prior_all[:n]),
        target_mm=torch.from_numpy(target_all[:n]),
        changed=torch.from_numpy(changed_all[:n]),
        sources=sources,
        true_mm=torch.from_numpy(true_all[:n]),
    )


def preop_prior_set(
    sequence: Sequence,
    mesh: trimesh.Trimesh,
    frame_step: int = 1,
    target_pose: Literal["tracked", "true"] = "tracked",
    surface: Literal["ct", "model"] = "ct",
) -> tuple[PriorSet, str]:
    """Fine-tuning pairs from the preoperative sequence and the CT surface mesh (or the
    preoperative model's surface: ``surface`` names which ``mesh`` is, for the label).

    target_pose : "tracked" (default, as :func:`build_prior_set`; also all real data has):
    target = the CT render at the tracked pose = the prior (the sweep shows no change);
    "true": the CT render at the true pose, where the sequence has true poses.
    Returns the pairs and what the target is: ``"ct-render-true-pose"`` or
    ``"ct-render-tracked-pose"`` (``"model-render-..."`` for the model's surface).
    """
    if not sequence.has_rgb:
        raise InvalidInputError(sequence.path, "fine-tuning needs the preop sequence's RGB")
    rc = MeshRaycaster(mesh.vertices, mesh.faces)
    idx = _frame_indices(len(sequence), frame_step)
    prior = rc.render_depths(sequence.camera, sequence.poses[idx])
    if target_pose == "true" and sequence.true_poses is not None:
        target, what = (
            rc.render_depths(sequence.camera, sequence.true_poses[idx]),
            f"{surface}-render-true-pose",
        )
    else:
        target, what = prior.copy(), f"{surface}-render-tracked-pose"
    keep = [j for j in range(len(idx)) if np.isfinite(prior[j]).mean() >= 0.05]
    if not keep:
        what_surface = "CT surface" if surface == "ct" else "model's surface"
        raise EmptyResultError(f"{sequence.path}: the {what_surface} is seen in no frame")
    rgb = []
    for j in keep:
        mask = sequence.mask(idx[j])
        if mask is not None:
            target[j][~mask] = np.nan
        rgb.append(sequence.rgb(idx[j]))
    pairs = PriorSet(
        rgb=torch.from_numpy(np.stack(rgb)),
        prior_mm=torch.from_numpy(prior[keep].astype(np.float32)),
        target_mm=torch.from_numpy(target[keep].astype(np.float32)),
        changed=torch.zeros(prior[keep].shape, dtype=torch.bool),
        sources=[f"{sequence.path}#{idx[j]}" for j in keep],
    )
    return pairs, what


SYNTHETIC_REMOVAL_MM = (1.5, 5.0)
"""Range of the thickness between a synthetic lamella and the surface behind it, mm."""
SYNTHETIC_RADIUS = (0.08, 0.3)
"""Range of a synthetic removal's semi-axes, as fractions of the image width."""


def add_synthetic_removal(pairs: PriorSet, fraction: float, seed: int) -> PriorSet:
    """Fine-tuning pairs with removals put in: in a seeded ``fraction`` of the frames the
    prior shows tissue in front of the true surface (an elliptical lamella, 1.5-5 mm in
    front, sharp-edged like a cut) that the frame and the target do not, as the model's
    render M_t does after a bite. The change label marks it; unchanged pairs are kept.

    Why: the preop sweep has no change, and 60 steps of "prior = target" taught the shipped
    network to copy its prior (default experiment, seed 2: mask recall 0.00 at every
    step). Returns a new set (the input is not modified)."""
    if not 0.0 <= fraction <= 1.0:
        raise InvalidInputError("--synthetic-removal", f"must be in [0, 1], got {fraction}")
    prior = pairs.prior_mm.numpy().copy()
    changed = pairs.changed.numpy().copy()
    rng = np.random.default_rng(seed)
    n, H, W = prior.shape
    vv, uu = np.mgrid[0:H, 0:W]
    for i in np.flatnonzero(rng.random(n) < fraction):
        valid = np.isfinite(prior[i])
        if not valid.any():
            continue
        k = rng.integers(valid.sum())
        cv, cu = np.argwhere(valid)[k]
        ra, rb = rng.uniform(*SYNTHETIC_RADIUS, size=2) * W
        angle = rng.uniform(0.0, np.pi)
        du, dv = uu - cu, vv - cv
        x = du * np.cos(angle) + dv * np.sin(angle)
        y = -du * np.sin(angle) + dv * np.cos(angle)
        inside = valid & ((x / ra) ** 2 + (y / rb) ** 2 <= 1.0)
        lamella = prior[i] - rng.uniform(*SYNTHETIC_REMOVAL_MM)
        inside &= lamella > 1.0  # not through the lens
        prior[i][inside] = lamella[inside]
        changed[i] |= inside
    return PriorSet(
        rgb=pairs.rgb,
        prior_mm=torch.from_numpy(prior),
        target_mm=pairs.target_mm,
        changed=torch.from_numpy(changed),
        sources=pairs.sources,
        true_mm=pairs.true_mm,
    )
