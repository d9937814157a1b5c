"""``chisel depth train|finetune|export --kind change-aware``: the change-aware network.

Thin wrappers: read the dataset / sequence / mesh, call :mod:`chisel.depth.change_train`,
write the checkpoint (``kind: change-aware``) with the exact command that reproduces it
(:mod:`chisel.cli.provenance`, as the monocular commands). Called by
``chisel.cli.cmd_depth``, which owns the parser; this module does not import it back.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from chisel.cli.args import trainer_options
from chisel.cli.provenance import canonical_command, environment, finetune_info, write_summary
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import transform_points
from chisel.depth.change_aware import (
    ChangeAwarePredictor,
    ChangeNetConfig,
    load_change_checkpoint,
    num_parameters,
    save_change_checkpoint,
)
from chisel.depth.change_source import export_change_aware
from chisel.depth.change_train import ChangeTrainConfig, train_change_aware
from chisel.depth.data import held_out_groups
from chisel.depth.prior_data import (
    StepSequenceRef,
    add_synthetic_removal,
    build_prior_set,
    check_change_training_seeds,
    phantom_step_mesh,
    preop_prior_set,
    read_step_dataset,
)
from chisel.io.meshfile import READABLE_MESH_SUFFIXES, read_mesh_file
from chisel.io.sequence import Sequence

log = logging.getLogger(__name__)

TRAIN_OPTS = [
    "kind",
    "data",
    "out",
    "steps",
    "batch_size",
    "lr",
    "seed",
    "val_fraction",
    "frame_step",
    "widths",
    "eval_every",
    "max_minutes",
    "threads",
    "device",
    "note",
    "prior_surface",
    "init",
]
FINETUNE_OPTS = [
    "kind",
    "checkpoint",
    "sequence",
    "mesh",
    "model",
    "out",
    "steps",
    "batch_size",
    "lr",
    "seed",
    "frame_step",
    "synthetic_removal",
    "threads",
    "device",
]


def train(args: argparse.Namespace) -> int:
    """``chisel depth train --kind change-aware``."""
    # Options are checked before hours of data are read.
    cfg = ChangeTrainConfig(
        steps=args.steps,
        max_minutes=args.max_minutes,
        eval_every=args.eval_every,
        **trainer_options(args),
    )
    refs = read_step_dataset(args.data, args.allow_outside_manifest)
    check_change_training_seeds(refs)
    seeds = sorted({r.seed for r in refs})
    val_seeds = held_out_groups(seeds, args.val_fraction, args.seed)
    train_refs = [r for r in refs if r.seed not in val_seeds]
    val_refs = [r for r in refs if r.seed in val_seeds]
    log.info("train seeds %s, validation seeds %s", sorted(set(seeds) - val_seeds), val_seeds)
    init = None
    if args.init is not None:
        if args.widths is not None:
            raise InvalidInputError("--widths", "the network of --init keeps its own widths")
        init, _ = load_change_checkpoint(Path(args.init))
    surface_of = (
        _model_surfaces(refs, args.frame_step)
        if args.prior_surface == "model"
        else phantom_step_mesh
    )
    pairs = build_prior_set(train_refs, frame_step=args.frame_step, surface_of=surface_of)
    val_pairs = (
        build_prior_set(val_refs, frame_step=args.frame_step, surface_of=surface_of)
        if val_refs
        else None
    )
    net_config = ChangeNetConfig(widths=args.widths or ChangeNetConfig().widths)
    result = train_change_aware(
        pairs, cfg, net_config, init=init, val_pairs=val_pairs, progress=True
    )
    info = {
        "kind": "train",
        "command": canonical_command(args, TRAIN_OPTS),
        "init": None if args.init is None else str(args.init),
        "prior_surface": args.prior_surface,
        "train_phantom_seeds": sorted(set(seeds) - val_seeds),
        "val_phantom_seeds": sorted(val_seeds),
        "train_sequences": [str(r.path) for r in train_refs],
        "num_train_frames": len(pairs),
        "num_val_frames": 0 if val_pairs is None else len(val_pairs),
        "changed_pixel_fraction": float(pairs.changed.float().mean()),
        "image_size": [int(pairs.rgb.shape[2]), int(pairs.rgb.shape[1])],
        "train_config": cfg.to_dict(),
        "num_parameters": num_parameters(result.net),
        "val_metrics": result.val_metrics,
        "best_step": result.best_step,
        "stopped_early": result.stopped_early,
        "train_seconds": round(result.seconds, 1),
        "history": result.history,
        "note": args.note,
        "environment": environment(),
    }
    save_change_checkpoint(args.out, result.net, info)
    summary = {"checkpoint": str(args.out), "val_metrics": result.val_metrics}
    write_summary(summary | {"train_seconds": info["train_seconds"]})
    return 0


def _model_surfaces(
    refs: list[StepSequenceRef], frame_step: int
) -> Callable[[Path, int], trimesh.Trimesh]:
    """``surface_of`` for :func:`build_prior_set`: each phantom step's mesh as a CT-built
    model holds it (:func:`chisel.build.voxel_copies`, the default voxel and truncation), on
    one grid per phantom over what its frames see: the box of their true depth, back-
    projected at the true poses, grown by the build's margin (the whole CT's grid would
    cost ~20x the signed distances)."""
    from chisel.build import BuildConfig, voxel_copies  # noqa: PLC0415

    margin = BuildConfig.margin_mm
    boxes: dict[Path, tuple[np.ndarray, np.ndarray]] = {}
    last_step: dict[Path, int] = {}
    for ref in refs:
        seq = Sequence(ref.path)
        assert seq.true_poses is not None  # build_prior_set refuses such a sequence first
        last_step[ref.phantom_dir] = max(last_step.get(ref.phantom_dir, 0), ref.step)
        for i in range(0, len(seq), max(frame_step, 1)):
            T = seq.true_poses[i]
            cam_pts = seq.camera.backproject(seq.depth_mm(i))[::4, ::4].reshape(-1, 3)
            cam_pts = cam_pts[np.isfinite(cam_pts).all(axis=1)]
            pts = np.vstack([transform_points(T, cam_pts), T[None, :3, 3]])
            lo, hi = boxes.get(ref.phantom_dir, (pts.min(axis=0), pts.max(axis=0)))
            boxes[ref.phantom_dir] = (
                np.minimum(lo, pts.min(axis=0)),
                np.maximum(hi, pts.max(axis=0)),
            )
    cache: dict[Path, list[trimesh.Trimesh]] = {}

    def surface_of(phantom_dir: Path, step: int) -> trimesh.Trimesh:
        if phantom_dir not in cache:
            lo, hi = boxes[phantom_dir]
            meshes = [phantom_step_mesh(phantom_dir, k) for k in range(last_step[phantom_dir] + 1)]
            cache.clear()  # build_prior_set goes phantom by phantom: keep one in memory
            cache[phantom_dir] = voxel_copies(meshes, lo - margin, hi + margin)
        return cache[phantom_dir][step]

    return surface_of


def _prior_surface(args: argparse.Namespace) -> tuple[trimesh.Trimesh, Literal["ct", "model"]]:
    """The surface rendered as the fine-tuning prior (and target), and which it is.

    --model: the preoperative model's surface as the updater renders M_t (marching cubes
    of the TSDF, :class:`chisel.render.ModelRenderer`), so the network is fine-tuned on the
    prior it is given in use: a voxel-sized, smoothed copy of the CT surface whose thin
    lamellae can be thicker, holed or missing.
    """
    if args.model is not None:
        from chisel.mesh import extract_mesh  # noqa: PLC0415
        from chisel.model import TsdfModel  # noqa: PLC0415

        return extract_mesh(TsdfModel.load(args.model), with_color=False), "model"
    return read_mesh_file(args.mesh, "--mesh", READABLE_MESH_SUFFIXES), "ct"


def finetune(args: argparse.Namespace) -> int:
    """``chisel depth finetune --kind change-aware --mesh CT_SURFACE | --model PREOP_MODEL``."""
    if (args.mesh is None) == (args.model is None):
        raise InvalidInputError(
            "--mesh/--model",
            "change-aware fine-tuning needs exactly one prior: the CT surface mesh (--mesh) "
            "or the preoperative model (--model)",
        )
    parent = Path(args.checkpoint)
    net, parent_info = load_change_checkpoint(parent)
    mesh, surface = _prior_surface(args)
    seqs = [Sequence(p) for p in args.sequence]
    parts = [preop_prior_set(s, mesh, args.frame_step, surface=surface) for s in seqs]
    targets = sorted({what for _, what in parts})
    pairs = parts[0][0]
    if len(parts) > 1:
        import torch  # noqa: PLC0415

        from chisel.depth.change_train import PriorSet  # noqa: PLC0415

        def cat(key: str) -> torch.Tensor:
            return torch.cat([getattr(p, key) for p, _ in parts])

        pairs = PriorSet(
            cat("rgb"), cat("prior_mm"), cat("target_mm"), cat("changed"),
            sum((p.sources for p, _ in parts), []),
        )  # fmt: skip
    pairs = add_synthetic_removal(pairs, args.synthetic_removal, args.seed)
    overrides = trainer_options(args)
    if args.synthetic_removal > 0:
        # With removals in the pairs the change head has something true to learn again.
        overrides.setdefault("bce_weight", ChangeTrainConfig.bce_weight)
    cfg = ChangeTrainConfig.finetune_defaults(steps=args.steps, **overrides)
    result = train_change_aware(pairs, cfg, init=net, progress=True)
    info = finetune_info(
        canonical_command(args, FINETUNE_OPTS),
        parent,
        parent_info,
        [str(s.path) for s in seqs],
        len(pairs),
        cfg,
        result,
        target=targets,
    )
    save_change_checkpoint(args.out, result.net, info)
    final = result.history[-1]["loss"] if result.history else None
    write_summary({"checkpoint": str(args.out), "target": targets, "final_loss": final})
    return 0


def export(args: argparse.Namespace) -> int:
    """``chisel depth export --kind change-aware``: TorchScript only."""
    net, _ = load_change_checkpoint(args.checkpoint)
    out = export_change_aware(ChangeAwarePredictor(net), args.out)
    write_summary({"exported": str(out), "kind": "change-aware"})
    return 0
