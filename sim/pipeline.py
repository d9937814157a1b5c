"""Render a phantom into sequence folders (the ``sim render`` command's library side).

Layout written (atomically: the whole ``OUT`` appears complete or not at all)::

    OUT/render.json          format, version, phantom, variant, num_steps, sequences, config
    OUT/preop/               preoperative sweep, rendered on step 0's mesh
    OUT/step_01 .. step_NN/  one intraoperative sequence per surgical step (its own mesh)
    OUT/eval/step_00 .. NN/  the fixed evaluation poses on each step's mesh

Each sequence folder follows :mod:`chisel.io.sequence` (``poses.txt`` = tracked poses,
``poses_true.txt`` = true poses, ``depth/``, ``rgb/``, ``mask/`` = valid depth,
``camera_mask.png`` = field stop). Evaluation sequences store exact poses in both files.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Sequence as Seq
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from tqdm import tqdm

from chisel.core.atomic import atomic_dir, check_output_outside
from chisel.core.mitsuba_variant import choose_variant
from chisel.io.sequence import Frame, SequenceWriter
from sim.appearance import TextureVolume, randomize, texture_volume
from sim.collision import TissueDistance
from sim.config import SimConfig, config_to_dict
from sim.paths import PathTarget, check_clearance, eval_poses, intraop_path, preop_sweep
from sim.phantom import Phantom, load_mesh, load_phantom
from sim.render import MeshRenderer
from sim.tracking import tracked_poses

log = logging.getLogger(__name__)

RENDER_FORMAT = "endoscopic-chisel/render"
RENDER_VERSION = 1
DEPTH_BATCH = 8
"""Frames per ray-intersection call in depth-only mode."""

_SEQ_SEED = {"preop": 0, "intraop": 1, "eval": 2}


def sequence_seed(seed: int, kind: str, step: int) -> int:
    """Seed of one sequence's random choices, derived from the master seed."""
    return int(np.random.default_rng([int(seed), _SEQ_SEED[kind], int(step)]).integers(2**31))


@dataclass(frozen=True)
class PlannedSequence:
    """A sequence to render: which step's mesh, which poses."""

    name: str
    """Folder name relative to OUT, e.g. ``step_01`` or ``eval/step_00``."""
    kind: str
    """``preop``, ``intraop`` or ``eval``."""
    step: int
    """Index of the mesh (surgical step) it is rendered on."""
    true_poses: np.ndarray
    """(N, 4, 4) float64 true ``T_world_from_cam``, mm."""
    tracked: np.ndarray
    """(N, 4, 4) float64 tracked ``T_world_from_cam`` written to ``poses.txt``, mm."""
    seed: int
    """Seed of the rendering noise of this sequence."""


def path_target(phantom: Phantom) -> PathTarget:
    """What the intraoperative and evaluation paths look at."""
    return PathTarget(
        center_mm=phantom.target_center_mm,
        normal=phantom.target_normal,
        roi_box_mm=phantom.roi_box_mm,
        approach_mm=phantom.airway_path_mm[-1],
        source=str(phantom.path / "phantom.json"),
    )


def plan_sequences(
    phantom: Phantom, meshes: Seq[trimesh.Trimesh], cfg: SimConfig, include_eval: bool = True
) -> list[PlannedSequence]:
    """All camera paths of a render, checked against every mesh they are rendered on.

    Raises :class:`~sim.errors.PathError` (or ``PathInTissueError``) before anything is
    rendered if a path cannot be built or collides.
    """
    pc = cfg.paths
    target = path_target(phantom)
    tissue0 = TissueDistance(meshes[0])
    planned: list[PlannedSequence] = []
    handeye_seed = int(cfg.seed)

    def add(name: str, kind: str, step: int, poses: np.ndarray, exact: bool) -> None:
        seed = sequence_seed(cfg.seed, kind, step)
        tracked = poses.copy() if exact else tracked_poses(poses, cfg.tracking, seed, handeye_seed)
        planned.append(PlannedSequence(name, kind, step, poses, tracked, seed))

    preop = preop_sweep(
        phantom.airway_path_mm,
        phantom.target_center_mm,
        tissue0,
        pc.preop_frames,
        pc,
        source=str(phantom.path / "phantom.json"),
    )
    add("preop", "preop", 0, preop, exact=False)
    evals = eval_poses(target, tissue0, pc.eval_poses, cfg.seed, pc) if include_eval else None
    for k in range(1, len(meshes)):
        tissue = tissue0 if k == 0 else TissueDistance(meshes[k])
        poses = intraop_path(
            target, tissue, pc.intraop_frames, sequence_seed(cfg.seed, "intraop", k), pc
        )
        add(f"step_{k:02d}", "intraop", k, poses, exact=False)
    if evals is not None:
        for k in range(len(meshes)):
            tissue = tissue0 if k == 0 else TissueDistance(meshes[k])
            check_clearance(
                evals[:, :3, 3], tissue, pc.clearance_mm, f"eval poses on step {k}'s mesh"
            )
            add(f"eval/step_{k:02d}", "eval", k, evals, exact=True)
    return planned


def render_sequence(
    renderer: MeshRenderer,
    seq: PlannedSequence,
    out_dir: Path,
    meta: dict[str, Any],
    progress: bool = True,
) -> Path:
    """Render one planned sequence with ``renderer`` into ``out_dir`` (atomically)."""
    cam = renderer.camera
    n = len(seq.true_poses)
    bar = tqdm(total=n, desc=f"render {seq.name}", unit="frame", disable=not progress, leave=False)
    with SequenceWriter(out_dir, cam, meta=meta, camera_mask=renderer.field_stop) as w:
        if renderer.depth_only:
            for start in range(0, n, DEPTH_BATCH):
                depths = renderer.render_depth(seq.true_poses[start : start + DEPTH_BATCH])
                for j, depth in enumerate(depths):
                    i = start + j
                    w.add(
                        Frame(i, seq.tracked[i], None, depth, np.isfinite(depth), seq.true_poses[i])
                    )
                bar.update(len(depths))
        else:
            for i in range(n):
                f = renderer.render(seq.true_poses[i], index=i, seed=seq.seed)
                w.add(Frame(i, seq.tracked[i], f.rgb, f.depth_mm, f.valid, seq.true_poses[i]))
                bar.update(1)
    bar.close()
    return out_dir


def _texture_box(mesh: trimesh.Trimesh) -> np.ndarray:
    b = np.asarray(mesh.bounds, dtype=np.float64)
    return np.stack([b[0] - 1.0, b[1] + 1.0])


def drawn_config(cfg: SimConfig) -> SimConfig:
    """The configuration a render uses and records: with ``randomization.enabled``,
    appearance, light and sensor drawn once with ``cfg.seed`` and randomisation switched
    off (so the recorded config renders the same images again); else ``cfg`` itself."""
    if not cfg.randomization.enabled:
        return cfg
    drawn = randomize(cfg, cfg.seed)
    return dataclasses.replace(
        drawn, randomization=dataclasses.replace(drawn.randomization, enabled=False)
    )


def render_phantom(
    phantom_dir: str | Path,
    out_dir: str | Path,
    cfg: SimConfig,
    include_eval: bool = True,
    progress: bool = True,
    texture: TextureVolume | None = None,
    allow_outside_phantom: bool = False,
) -> dict[str, Any]:
    """Render every sequence of a phantom into ``out_dir``; returns the render.json dict.

    Validates the phantom, every mesh and every path before rendering anything; the
    output folder appears only when everything succeeded. With
    ``cfg.randomization.enabled``, appearance, light and sensor are drawn once from the
    ranges with ``cfg.seed``; render.json records the drawn values (randomisation off, so
    that rendering with its config reproduces the same images).
    """
    randomized = cfg.randomization.enabled
    cfg = drawn_config(cfg)
    phantom = load_phantom(phantom_dir, allow_outside=allow_outside_phantom)
    check_output_outside(out_dir, phantom.path, *{Path(s.mesh_path).parent for s in phantom.steps})
    meshes = [load_mesh(s.mesh_path) for s in phantom.steps]
    planned = plan_sequences(phantom, meshes, cfg, include_eval=include_eval)
    variant = choose_variant(cfg.variant)
    if texture is None and not cfg.depth_only:
        texture = texture_volume(_texture_box(meshes[0]), cfg.appearance, cfg.seed)
    sequences: dict[str, Any] = {"preop": "preop", "steps": {}, "eval": {}}
    for p in planned:
        if p.kind == "intraop":
            sequences["steps"][str(p.step)] = p.name
        elif p.kind == "eval":
            sequences["eval"][str(p.step)] = p.name
    header = {
        "format": RENDER_FORMAT,
        "version": RENDER_VERSION,
        "phantom": str(phantom.path),
        "phantom_seed": phantom.seed,
        "variant": variant,
        "num_steps": phantom.num_steps,
        "depth_only": bool(cfg.depth_only),
        "randomized": bool(randomized),
        "sequences": sequences
        if include_eval
        else {k: v for k, v in sequences.items() if k != "eval"},
        "config": config_to_dict(cfg),
    }
    out = Path(out_dir)
    with atomic_dir(out, "render.json") as tmp:
        (tmp / "eval").mkdir()
        for k, mesh in enumerate(meshes):
            todo = [p for p in planned if p.step == k]
            if not todo:
                continue
            renderer = MeshRenderer(mesh, cfg, texture, depth_only=cfg.depth_only)
            for p in todo:
                meta = {
                    "source": "sim",
                    "kind": p.kind,
                    "step": p.step,
                    "step_name": phantom.steps[k].name,
                    "phantom": str(phantom.path),
                    "phantom_seed": phantom.seed,
                    "mesh": str(phantom.steps[k].mesh_path),
                    "variant": renderer.variant,
                    "seed": p.seed,
                    "poses_txt": "true poses (evaluation viewpoints)"
                    if p.kind == "eval"
                    else "tracked poses",
                    "tracking": config_to_dict(cfg)["tracking"] if p.kind != "eval" else None,
                }
                render_sequence(renderer, p, tmp / p.name, meta, progress=progress)
            del renderer
        if not include_eval:
            (tmp / "eval").rmdir()
        (tmp / "render.json").write_text(json.dumps(header, indent=2) + "\n")
    return header
