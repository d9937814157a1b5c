"""``chisel depth train|finetune|export --kind change-aware``: the change-aware network.

Thin wrappers: read the dataset / sequence / mesh, call :mod:`chisel.depth.change_train`,
write the checkpoint (``kind: change-aware``) with the exact command that reproduces it
(:mod:`chisel.cli.provenance`, as the monocular commands). Called by
``chisel.cli.cmd_depth``, which owns the parser; this module does not import it back.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Literal

import trimesh

from chisel.cli.args import trainer_options
from chisel.cli.provenance import canonical_command, environment, finetune_info, write_summary
from chisel.core.errors import InvalidInputError
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
    add_synthetic_removal,
    build_prior_set,
    check_change_training_seeds,
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
    pairs = build_prior_set(train_refs, frame_step=args.frame_step)
    val_pairs = build_prior_set(val_refs, frame_step=args.frame_step) if val_refs else None
    net_config = ChangeNetConfig(widths=args.widths or ChangeNetConfig().widths)
    result = train_change_aware(pairs, cfg, net_config, val_pairs=val_pairs, progress=True)
    info = {
        "kind": "train",
        "command": canonical_command(args, TRAIN_OPTS),
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
