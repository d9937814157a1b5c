"""Render a phantom into sequence folders (the ``sim render`` command's library side).

Layout written (atomically: the whole ``OUT`` appears complete or not at all)::

    OUT/render.json          format, version, phantom, variant, num_steps, sequences, config
    OUT/preop/               preoperative sweep, rendered on step 0's mesh
    OUT/step_01 .. step_NN/  one intraoperative sequence per surgical step (its own mesh)
    OUT/eval/step_00 .. NN/  the fixed evaluation poses on each step's mesh

Each sequence folder follows :mod:`chisel.io.sequence` (``poses.txt`` = tracked poses,
``poses_true.txt`` = true poses, ``depth/``, ``rgb/``, ``mask/`` = valid depth,
``camera_mask.png`` = field stop). Evaluation sequences store exact poses in both files.
With instruments (``tools.enabled``) an intraoperative sequence also holds
``depth_visible/NNNNNN.npy`` (z-depth of the visible scene, tool included, 0 = none),
``tool_mask/NNNNNN.png`` (255 = the pixel's first hit is an instrument) and
``tools.json`` (per frame: instrument and ``T_world_from_tool``); ``depth/`` stays the
tissue's depth (the tool is not in it) and ``mask/`` excludes the tool pixels.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import logging
from collections.abc import Iterator
from collections.abc import Sequence as Seq
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from tqdm import tqdm

from chisel.core.atomic import atomic_dir, check_output_outside
from chisel.core.errors import InvalidInputError, ResourceLimitError, out_of_memory_names
from chisel.core.mitsuba_variant import choose_variant
from chisel.io.limits import check_npy_header
from chisel.io.manifest import named_path, read_json_manifest
from chisel.io.sequence import Frame, SequenceWriter, depth_to_disk, imwrite
from sim.appearance import TextureVolume, cut_texture_volume, randomize, texture_volume
from sim.blood import blood_film_weight, fresh_cut_faces
from sim.collision import TissueDistance
from sim.config import SimConfig, config_to_dict
from sim.effects import FrameEffects, smear_mask, smear_schedule
from sim.errors import PhantomError
from sim.materials import SharedMaterials
from sim.paths import PathTarget, check_clearance, eval_poses, intraop_path, preop_sweep
from sim.phantom import Phantom, load_mesh, load_phantom
from sim.render import MeshRenderer, RenderedFrame
from sim.tools import ToolSet, ToolTrack, plan_tool_track, tool_set
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
    tools: ToolTrack | None = None
    """Instruments per frame (intraoperative sequences with ``tools.enabled``), else None."""


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
    phantom: Phantom,
    meshes: Seq[trimesh.Trimesh],
    cfg: SimConfig,
    include_eval: bool = True,
    tools: ToolSet | None = None,
) -> list[PlannedSequence]:
    """All camera paths of a render, checked against every mesh they are rendered on.

    With ``tools``, each intraoperative sequence also gets its instrument track
    (:func:`sim.tools.plan_tool_track`, clear of that step's tissue).
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
        if tools is not None:
            track = plan_tool_track(
                tools,
                cfg.camera.camera(),
                poses,
                tissue,
                cfg.tools,
                sequence_seed(cfg.seed, "intraop", k),
            )
            planned[-1] = dataclasses.replace(planned[-1], tools=track)
    if evals is not None:
        for k in range(len(meshes)):
            tissue = tissue0 if k == 0 else TissueDistance(meshes[k])
            check_clearance(
                evals[:, :3, 3], tissue, pc.clearance_mm, f"eval poses on step {k}'s mesh"
            )
            add(f"eval/step_{k:02d}", "eval", k, evals, exact=True)
    return planned


def frame_effects(
    cfg: SimConfig, seq: PlannedSequence, index: int, smear_seed: int
) -> FrameEffects:
    """The smoke, blur and smear of frame ``index`` of ``seq`` (see :mod:`sim.effects`)."""
    shape = (cfg.camera.height, cfg.camera.width)
    smear = None
    if smear_seed >= 0:
        smear = smear_mask(shape, cfg.lens.smear_strength, smear_seed)
    return FrameEffects(
        smoke=cfg.smoke,
        smoke_seed=int(np.random.default_rng([seq.seed, index, 59]).integers(2**31)),
        blur=cfg.blur,
        T_prev=seq.true_poses[index - 1] if index > 0 else None,
        smear=smear,
        smear_blur_px=cfg.lens.smear_blur_px * cfg.camera.width / 320.0,
    )


def sequence_frames(renderer: MeshRenderer, seq: PlannedSequence) -> Iterator[RenderedFrame]:
    """The colour frames of ``seq`` as :func:`render_sequence` renders them (instruments,
    and for intraoperative sequences the effects), one at a time, nothing written."""
    n = len(seq.true_poses)
    cfg = renderer.cfg
    effects_on = seq.kind == "intraop" and not renderer.depth_only
    smears = smear_schedule(n, cfg.lens, seq.seed) if effects_on else np.full(n, -1)
    track = seq.tools
    for i in range(n):
        fx = frame_effects(cfg, seq, i, int(smears[i])) if effects_on else None
        tool = None if track is None else (int(track.kind[i]), track.T_world_from_tool[i])
        yield renderer.render(seq.true_poses[i], index=i, seed=seq.seed, tool=tool, effects=fx)


def render_sequence(
    renderer: MeshRenderer,
    seq: PlannedSequence,
    out_dir: Path,
    meta: dict[str, Any],
    progress: bool = True,
) -> Path:
    """Render one planned sequence with ``renderer`` into ``out_dir`` (atomically).

    Instruments and effects apply to intraoperative sequences only (the preoperative
    sweep and the evaluation poses stay clean ground truth for the model and the score).
    """
    cam = renderer.camera
    n = len(seq.true_poses)
    track = seq.tools
    extras = out_dir.parent / f".{out_dir.name}.tools.tmp" if track is not None else None
    if extras is not None:
        for sub in ("depth_visible", "tool_mask"):
            (extras / sub).mkdir(parents=True, exist_ok=True)
    bar = tqdm(total=n, desc=f"render {seq.name}", unit="frame", disable=not progress, leave=False)
    if track is not None:
        assert extras is not None  # made above whenever there is a tool track
        with SequenceWriter(out_dir, cam, meta=meta, camera_mask=renderer.field_stop) as w:
            for i, f in enumerate(sequence_frames(renderer, seq)):
                assert f.tool_mask is not None and f.depth_visible_mm is not None
                name = f"{i:06d}"
                np.save(extras / "depth_visible" / f"{name}.npy", depth_to_disk(f.depth_visible_mm))
                imwrite(
                    str(extras / "tool_mask" / f"{name}.png"),
                    np.where(f.tool_mask, 255, 0).astype(np.uint8),
                )
                mask = f.valid & ~f.tool_mask
                w.add(Frame(i, seq.tracked[i], f.rgb, f.depth_mm, mask, seq.true_poses[i]))
                bar.update(1)
        for sub in ("depth_visible", "tool_mask"):
            (extras / sub).rename(out_dir / sub)
        extras.rmdir()
        (out_dir / "tools.json").write_text(
            json.dumps(
                {
                    "kinds": list(renderer.tools.kinds) if renderer.tools else [],
                    "sizes_mm": list(renderer.tools.sizes_mm) if renderer.tools else [],
                    "frames": [
                        {
                            "index": i,
                            "tool": renderer.tools.kinds[int(track.kind[i])]
                            if track.kind[i] >= 0 and renderer.tools
                            else None,
                            "T_world_from_tool": track.T_world_from_tool[i].tolist()
                            if track.kind[i] >= 0
                            else None,
                        }
                        for i in range(n)
                    ],
                },
                indent=1,
            )
            + "\n"
        )
        bar.close()
        return out_dir
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
            for i, f in enumerate(sequence_frames(renderer, seq)):
                w.add(Frame(i, seq.tracked[i], f.rgb, f.depth_mm, f.valid, seq.true_poses[i]))
                bar.update(1)
    bar.close()
    return out_dir


def _texture_box(mesh: trimesh.Trimesh) -> np.ndarray:
    b = np.asarray(mesh.bounds, dtype=np.float64)
    return np.stack([b[0] - 1.0, b[1] + 1.0])


def load_cut_faces(
    phantom: Phantom, step: int, n_faces: int, allow_outside: bool = False
) -> np.ndarray | None:
    """(F,) bool cut-face labels of a step's mesh, from ``phantom.json``'s optional
    ``steps[k].cut_faces`` (a uint8 ``.npy`` per face; ``docs/phantoms.md``), or None
    when the phantom has none. A file that does not match the mesh, is not a ``.npy``
    (an ``.npz`` archive, a corrupt file, Python objects) or lies outside the phantom's
    folder (unless ``allow_outside``, as for its meshes) raises
    :class:`~sim.errors.PhantomError` (or :class:`OutsideManifestError`) naming it and
    the key."""
    manifest = phantom.path / "phantom.json"
    data = read_json_manifest(manifest, PhantomError)
    steps = data.get("steps")
    if not isinstance(steps, list) or step >= len(steps) or not isinstance(steps[step], dict):
        return None
    rel = steps[step].get("cut_faces")
    if rel is None:
        return None
    key = f"steps[{step}].cut_faces"
    path = named_path(
        manifest,
        rel,
        key,
        allow_outside=allow_outside,
        kind="file",
        option="--allow-outside-phantom",
    )
    # Read as the sequence reader reads depth: the .npy header first (declared size,
    # object dtype), then without pickle; an .npz archive has no .npy header.
    with out_of_memory_names(path, "reading these cut-face labels"):
        try:
            with open(path, "rb") as fh:
                check_npy_header(fh, path, path.stat().st_size)
            labels = np.load(path, allow_pickle=False)
        except InvalidInputError as exc:  # names the file; add the key
            kind = ResourceLimitError if isinstance(exc, ResourceLimitError) else PhantomError
            raise kind(path, f"{key}: {exc.problem}") from None
        except (OSError, ValueError, EOFError) as exc:
            raise PhantomError(path, f"{key}: not a .npy array: {exc}") from None
    if labels.ndim != 1 or len(labels) != n_faces or labels.dtype.kind not in "biu":
        raise PhantomError(
            path,
            f"{key}: expected ({n_faces},) integer labels (one per face of "
            f"{phantom.steps[step].mesh_path.name}), got {labels.shape} {labels.dtype}",
        )
    if np.any((labels != 0) & (labels != 1)):
        raise PhantomError(path, f"{key}: labels must be 0 or 1")
    return labels.astype(bool)


def blood_films(
    cfg: SimConfig, meshes: Seq[trimesh.Trimesh], labels: Seq[np.ndarray | None]
) -> list[np.ndarray | None]:
    """Per step, the blood film's per-face coverage below the faces that step cut
    (:mod:`sim.blood`), or None (``blood.enabled`` off, depth only, no labels, step 0)."""
    films: list[np.ndarray | None] = [None] * len(meshes)
    if not cfg.blood.enabled or cfg.depth_only:
        return films
    for k in range(1, len(meshes)):
        cut = labels[k]
        if cut is None or not cut.any():
            continue
        fresh = fresh_cut_faces(meshes[k], cut, meshes[k - 1], labels[k - 1])
        seed = int(np.random.default_rng([int(cfg.seed), 31, k]).integers(2**31))
        films[k] = blood_film_weight(meshes[k], fresh, cfg.blood, seed)
    return films


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


@dataclass
class PhantomScene:
    """What every step's renderer of one phantom shares, and the sequences to render:
    :func:`render_phantom` renders them, ``benchmarks/bench_dataset.py`` times the same
    renderers alone."""

    cfg: SimConfig
    """The drawn configuration (:func:`drawn_config`)."""
    meshes: list[trimesh.Trimesh]
    cuts: list[np.ndarray | None]
    """Per step, the cut-face labels in use (None: none, ``cut`` off or depth only)."""
    films: list[np.ndarray | None]
    """Per step, the blood film's per-face coverage (:func:`blood_films`)."""
    texture: TextureVolume | None
    cut_texture: TextureVolume | None
    tools: ToolSet | None
    planned: list[PlannedSequence]
    shared: SharedMaterials
    """One tissue BSDF and packed texture for every step."""

    @classmethod
    def build(
        cls,
        phantom: Phantom,
        cfg: SimConfig,
        include_eval: bool = True,
        texture: TextureVolume | None = None,
        allow_outside: bool = False,
    ) -> PhantomScene:
        """Meshes, labels, textures and planned paths of ``phantom`` under the drawn
        ``cfg``; raises before anything is rendered if a path or a label file cannot be
        used (``allow_outside``: files outside the phantom's folder, as for its meshes)."""
        meshes = [load_mesh(s.mesh_path) for s in phantom.steps]
        labels = [
            load_cut_faces(phantom, k, len(m.faces), allow_outside=allow_outside)
            for k, m in enumerate(meshes)
        ]
        films = blood_films(cfg, meshes, labels)
        cuts: list[np.ndarray | None] = (
            labels if cfg.cut.enabled and not cfg.depth_only else [None] * len(meshes)
        )
        tools = tool_set(cfg.tools, cfg.seed) if cfg.tools.enabled else None
        planned = plan_sequences(phantom, meshes, cfg, include_eval=include_eval, tools=tools)
        if texture is None and not cfg.depth_only:
            texture = texture_volume(_texture_box(meshes[0]), cfg.appearance, cfg.seed)
        cut_texture = None
        if any(c is not None and c.any() for c in cuts):
            cut_texture = cut_texture_volume(_texture_box(meshes[0]), cfg, cfg.seed)
        return cls(
            cfg, meshes, cuts, films, texture, cut_texture, tools, planned, SharedMaterials()
        )

    def step_renderer(self, k: int) -> MeshRenderer:
        """The renderer of step ``k``'s mesh (instruments only if a sequence on it has a
        track)."""
        cfg = self.cfg
        step_tools = (
            self.tools if any(p.tools is not None for p in self.planned if p.step == k) else None
        )
        return MeshRenderer(
            self.meshes[k],
            cfg,
            self.texture,
            depth_only=cfg.depth_only,
            cut_faces=self.cuts[k],
            cut_texture=self.cut_texture,
            tools=step_tools,
            blood_weight=self.films[k],
            shared=self.shared,
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
    scene = PhantomScene.build(
        phantom,
        cfg,
        include_eval=include_eval,
        texture=texture,
        allow_outside=allow_outside_phantom,
    )
    planned, meshes = scene.planned, scene.meshes
    variant = choose_variant(cfg.variant)
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
        for k in range(len(meshes)):
            todo = [p for p in planned if p.step == k]
            if not todo:
                continue
            renderer = scene.step_renderer(k)
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
                    "cut_faces": 0 if (cut := scene.cuts[k]) is None else int(cut.sum()),
                    "tools": p.tools is not None,
                }
                if (film := scene.films[k]) is not None:
                    meta["blood_faces"] = int((film > 0).sum())
                render_sequence(renderer, p, tmp / p.name, meta, progress=progress)
            del renderer
            # A renderer's Mitsuba scene sits in reference cycles, and Python's cycle
            # collector runs by object counts, not bytes: without this a dataset's process
            # kept every earlier step's scene (~40 MB per phantom, 911 -> 1410 MB over 12).
            gc.collect()
        if not include_eval:
            (tmp / "eval").rmdir()
        (tmp / "render.json").write_text(json.dumps(header, indent=2) + "\n")
    return header
