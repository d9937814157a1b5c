"""``chisel depth train|finetune|predict|evaluate|export``: the monocular depth network."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from chisel.cli.args import Output, finite_float, trainer_options
from chisel.cli.provenance import (
    canonical_command,
    environment,
    finetune_info,
    sha256_file,
    write_summary,
)
from chisel.core.errors import InvalidInputError
from chisel.depth import (
    DEFAULT_CHECKPOINT,
    DepthNetConfig,
    DepthPredictor,
    TrainConfig,
    check_training_seeds,
    evaluate_source,
    export_model,
    find_sequences,
    load_checkpoint,
    load_depth_source,
    load_frames,
    predict_sequence,
    save_checkpoint,
    split_by_group,
    train,
)
from chisel.depth.checkpoint import sidecar_path
from chisel.depth.data import AugmentConfig, SequenceRef
from chisel.io.sequence import Sequence

log = logging.getLogger(__name__)

_HELP = """\
Monocular depth network (relative z-depth from one RGB frame; the updater solves scale).

  train     train from scratch on rendered sequences (phantom seeds 0-99 are reserved for
            evaluation and refused; the shipped model uses seeds >= 1000); validation is split by phantom seed
  finetune  per-patient fine-tuning on the preoperative sequence, whose depth is the CT
            surface rendered at the tracked poses
  predict   write a NEW sequence folder: the input's RGB/poses/masks + predicted depth
  evaluate  median-scaled abs-rel, RMSE (mm), delta<1.25 against sequences' own depth
  export    TorchScript (.pt) or ONNX (.onnx, needs the onnx package): uint8
            (B, H, W, 3) RGB -> (B, H, W) float32 relative depth

--kind change-aware (train, finetune, export): the change-aware network instead, whose
input is the frame plus the model's depth render at the tracked pose and whose output is
metric depth in mm (docs/depth.md); it trains on `python -m sim dataset` folders (priors
rendered from the phantoms' previous-step meshes), bounded by --steps.
"""

_KINDS = ("monocular", "change-aware")


def _change_aware(args: argparse.Namespace) -> bool:
    """True for --kind change-aware; --steps/--mesh/--model/--eval-every/--prior-surface are
    refused for the monocular kind."""
    if args.kind == "change-aware":
        for flag in ("size", "blocks"):
            if getattr(args, flag, None) is not None:
                raise InvalidInputError(f"--{flag}", "is an option of the monocular kind only")
        if args.steps is None:
            args.steps = 600 if args.depth_command == "train" else 60
        if getattr(args, "eval_every", 0) is None:
            args.eval_every = 100
        if getattr(args, "prior_surface", "") is None:
            args.prior_surface = "mesh"
        return True
    for flag in ("steps", "mesh", "model", "eval_every", "prior_surface"):
        if getattr(args, flag, None) is not None:
            raise InvalidInputError(
                "--" + flag.replace("_", "-"), "is an option of --kind change-aware only"
            )
    return False


def _checkpoint_sidecar(args: argparse.Namespace) -> Path:
    return sidecar_path(args.out)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT, e.g. 320x256, got {text!r}"
        ) from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size must be at least 8x8, got {text!r}")
    return w, h


def _ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None


def _seeds(refs: list[SequenceRef]) -> list[int]:
    return sorted({r.seed for r in refs if r.seed is not None})


_TRAIN_OPTS = [
    "data",
    "out",
    "epochs",
    "batch_size",
    "lr",
    "seed",
    "val_fraction",
    "frame_step",
    "size",
    "widths",
    "blocks",
    "init",
    "max_minutes",
    "threads",
    "device",
    "no_augment",
    "note",
]


def _cmd_train(args: argparse.Namespace) -> int:
    if _change_aware(args):
        from chisel.cli import cmd_change_aware  # noqa: PLC0415 - torch-heavy, only when asked

        return cmd_change_aware.train(args)
    out = Path(args.out)
    init = None
    if args.init is not None:  # before the frames load: a wrong parent fails at once
        for flag in ("widths", "blocks"):
            if getattr(args, flag) is not None:
                raise InvalidInputError(f"--{flag}", "the network of --init keeps its own")
        init, _ = load_checkpoint(Path(args.init))
    refs = find_sequences(args.data, args.allow_outside_manifest)
    check_training_seeds(refs)
    train_refs, val_refs = split_by_group(refs, args.val_fraction, args.seed)
    log.info(
        "%d sequences: %d train (seeds %s), %d validation (seeds %s)",
        len(refs),
        len(train_refs),
        _seeds(train_refs),
        len(val_refs),
        _seeds(val_refs),
    )
    frames = load_frames(train_refs, size=args.size, frame_step=args.frame_step)
    val_frames = (
        load_frames(val_refs, size=args.size, frame_step=args.frame_step) if val_refs else None
    )
    net_config = DepthNetConfig(
        widths=args.widths or DepthNetConfig().widths,
        blocks=args.blocks or DepthNetConfig().blocks,
    )
    cfg = TrainConfig(
        epochs=args.epochs,
        augment=None if args.no_augment else AugmentConfig(),
        max_minutes=args.max_minutes,
        **trainer_options(args),
    )
    result = train(frames, cfg, net_config, init=init, val_frames=val_frames, progress=True)
    info = {
        "kind": "train",
        "command": canonical_command(args, _TRAIN_OPTS),
        "init": None if args.init is None else str(args.init),
        "train_phantom_seeds": _seeds(train_refs),
        "val_phantom_seeds": _seeds(val_refs),
        "train_sequences": [str(r.path) for r in train_refs],
        "val_sequences": [str(r.path) for r in val_refs],
        "num_train_frames": len(frames),
        "num_val_frames": 0 if val_frames is None else len(val_frames),
        "image_size": [int(frames.rgb.shape[2]), int(frames.rgb.shape[1])],
        "train_config": cfg.to_dict(),
        "val_metrics": None if result.val_metrics is None else result.val_metrics.to_dict(),
        "best_epoch": result.best_epoch,
        "stopped_early": result.stopped_early,
        "train_seconds": round(result.seconds, 1),
        "train_cpu_seconds": round(result.cpu_seconds, 1),
        "history": result.history,
        "note": args.note,
        "environment": environment(),
    }
    save_checkpoint(out, result.net, info)
    write_summary(
        {
            "checkpoint": str(out),
            "val_metrics": info["val_metrics"],
            "train_seconds": info["train_seconds"],
        }
    )
    return 0


_FINETUNE_OPTS = [
    "checkpoint",
    "sequence",
    "out",
    "epochs",
    "batch_size",
    "lr",
    "seed",
    "frame_step",
    "threads",
    "device",
    "no_augment",
]


def _cmd_finetune(args: argparse.Namespace) -> int:
    if _change_aware(args):
        from chisel.cli import cmd_change_aware  # noqa: PLC0415 - torch-heavy, only when asked

        return cmd_change_aware.finetune(args)
    parent = Path(args.checkpoint)
    net, parent_info = load_checkpoint(parent)
    refs = [SequenceRef(Path(p), None) for p in args.sequence]
    frames = load_frames(refs, size=None, frame_step=args.frame_step)
    cfg = TrainConfig.finetune_defaults(
        epochs=args.epochs,
        augment=None if args.no_augment else AugmentConfig(),
        **trainer_options(args),
    )
    result = train(frames, cfg, init=net, progress=True)
    info = finetune_info(
        canonical_command(args, _FINETUNE_OPTS),
        parent,
        parent_info,
        [str(r.path) for r in refs],
        len(frames),
        cfg,
        result,
    )
    save_checkpoint(Path(args.out), result.net, info)
    write_summary(
        {
            "checkpoint": args.out,
            "train_seconds": info["train_seconds"],
            "final_loss": result.history[-1]["loss"],
        }
    )
    return 0


def _cmd_predict(args: argparse.Namespace) -> int:
    ck = Path(args.checkpoint)
    source = load_depth_source(ck, device=args.device)
    seq = Sequence(args.sequence)
    meta = {"model": str(ck), "model_sha256": sha256_file(ck), "relative_depth": True}
    predict_sequence(source, seq, args.out, meta=meta, progress=True)
    write_summary({"sequence": args.out, "frames": len(seq)})
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    source = load_depth_source(args.checkpoint, device=args.device)
    refs = find_sequences(args.data, args.allow_outside_manifest)
    metrics = evaluate_source(source, [Sequence(r.path) for r in refs])
    write_summary({"checkpoint": str(args.checkpoint), "sequences": len(refs), **metrics.to_dict()})
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    if args.kind == "change-aware":
        from chisel.cli import cmd_change_aware  # noqa: PLC0415 - torch-heavy, only when asked

        return cmd_change_aware.export(args)
    net, _ = load_checkpoint(args.checkpoint)
    out = export_model(DepthPredictor(net), args.out)
    write_summary({"exported": str(out)})
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``chisel depth ...`` to the top-level parser."""
    p = subparsers.add_parser(
        "depth",
        help="monocular depth network: train, finetune, predict, evaluate, export",
        description=_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="depth_command", metavar="SUBCOMMAND", required=True)
    _add_train(sub)
    _add_finetune(sub)
    _add_predict(sub)
    _add_evaluate(sub)
    _add_export(sub)


def _add_device(q: argparse.ArgumentParser) -> None:
    q.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N")


def _add_kind(q: argparse.ArgumentParser) -> None:
    q.add_argument(
        "--kind",
        choices=_KINDS,
        default="monocular",
        help="monocular (default): relative depth from RGB; change-aware: RGB + the "
        "model's render at the tracked pose -> metric depth (mm)",
    )


def _add_data(q: argparse.ArgumentParser) -> None:
    q.add_argument(
        "--data",
        nargs="+",
        required=True,
        help="dataset folders (dataset.json), dataset.json files or sequence folders",
    )
    q.add_argument(
        "--allow-outside-manifest",
        action="store_true",
        help="let a dataset.json name sequence folders outside its own folder",
    )


def _add_shipped_checkpoint(q: argparse.ArgumentParser) -> None:
    q.add_argument(
        "--checkpoint",
        default=str(DEFAULT_CHECKPOINT),
        help="checkpoint (.pt) or TorchScript export (default: the shipped model)",
    )


def _add_training(q: argparse.ArgumentParser, epochs: int, lr: float) -> None:
    """The options train and finetune share; only the defaults of the two differ."""
    q.add_argument(
        "--epochs", type=int, default=epochs, help=f"passes over the frames (default {epochs})"
    )
    q.add_argument("--batch-size", type=int, default=8, help="frames per step (default 8)")
    q.add_argument(
        "--lr", type=finite_float, default=lr, help=f"peak learning rate (default {lr:g})"
    )
    q.add_argument("--seed", type=int, default=0, help="seeds init, split, shuffling, augmentation")
    q.add_argument("--frame-step", type=int, default=1, help="use every N-th frame (default 1)")
    q.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    q.add_argument("--no-augment", action="store_true", help="no flips / colour jitter")
    _add_kind(q)
    q.add_argument(
        "--steps",
        type=int,
        default=None,
        help="change-aware only: optimisation steps (default 600 train, 60 finetune)",
    )
    _add_device(q)


def _add_train(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser("train", help="train from scratch on rendered sequences")
    _add_data(t)
    t.add_argument(
        "--out",
        required=True,
        help="checkpoint to write (.pt; a .json sidecar beside it)",
        action=Output,
        sidecar=_checkpoint_sidecar,
    )
    _add_training(t, epochs=30, lr=2e-3)
    t.add_argument(
        "--val-fraction",
        type=finite_float,
        default=0.15,
        help="fraction of phantom seeds held out for validation (default 0.15)",
    )
    t.add_argument(
        "--size",
        type=_size,
        default=None,
        help="train at WIDTHxHEIGHT (default: the sequences' own size)",
    )
    t.add_argument("--widths", type=_ints, default=None, help="encoder widths, e.g. 16,24,32,48,64")
    t.add_argument(
        "--eval-every",
        type=int,
        default=None,
        help="change-aware only: validate every N steps, keep the best (default 100)",
    )
    t.add_argument(
        "--prior-surface",
        choices=("mesh", "model"),
        default=None,
        help="change-aware only: the surface rendered as prior and target: the phantom's mesh "
        "(default) or what a CT-built model holds of it (0.5 mm voxels), as the updater "
        "renders M_t",
    )
    t.add_argument(
        "--init",
        default=None,
        help="start from this checkpoint's weights, of the kind being trained (default: from "
        "scratch); its architecture is kept",
    )
    t.add_argument(
        "--blocks", type=_ints, default=None, help="residual blocks per stage, e.g. 1,1,1,2,2"
    )
    t.add_argument(
        "--note",
        default=None,
        help="free text stored in the checkpoint (e.g. the command that made the data)",
    )
    t.add_argument(
        "--max-minutes",
        type=finite_float,
        default=None,
        help="stop after the epoch that passes this wall time (safety cap)",
    )
    t.set_defaults(func=_cmd_train)


def _add_finetune(sub: argparse._SubParsersAction) -> None:
    f = sub.add_parser("finetune", help="fine-tune on a preoperative sequence (depth = CT render)")
    f.add_argument("--checkpoint", required=True, help="checkpoint to start from (.pt)")
    f.add_argument(
        "--sequence",
        nargs="+",
        required=True,
        help="preoperative sequence folder(s) with RGB and depth (CT surface renders)",
    )
    f.add_argument(
        "--out",
        required=True,
        help="fine-tuned checkpoint to write (.pt; a .json sidecar beside it)",
        action=Output,
        sidecar=_checkpoint_sidecar,
    )
    _add_training(f, epochs=3, lr=1e-4)
    f.add_argument(
        "--mesh",
        default=None,
        help="change-aware only: the CT surface mesh (PLY/STL/OBJ, mm) rendered as the prior",
    )
    f.add_argument(
        "--model",
        default=None,
        help="change-aware only, instead of --mesh: the preoperative model (.npz, chisel "
        "build); its surface, rendered as the updater renders it, is the prior and the target",
    )
    f.add_argument(
        "--synthetic-removal",
        type=finite_float,
        default=1.0,
        help="change-aware only: fraction of the preop frames whose prior gets a synthetic "
        "removal (a lamella 1.5-5 mm in front of the surface), so that fine-tuning on a sweep "
        "without change does not teach the network to copy its prior (default 1.0; 0 = off)",
    )
    f.set_defaults(func=_cmd_finetune)


def _add_predict(sub: argparse._SubParsersAction) -> None:
    pr = sub.add_parser("predict", help="write a new sequence with predicted depth")
    _add_shipped_checkpoint(pr)
    pr.add_argument("--sequence", required=True, help="input sequence folder (needs RGB)")
    pr.add_argument(
        "--out", required=True, help="new sequence folder to write (atomically)", action=Output
    )
    _add_device(pr)
    pr.set_defaults(func=_cmd_predict)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("evaluate", help="median-scaled metrics against sequences' own depth")
    _add_shipped_checkpoint(e)
    _add_data(e)
    _add_device(e)
    e.set_defaults(func=_cmd_evaluate)


def _add_export(sub: argparse._SubParsersAction) -> None:
    x = sub.add_parser("export", help="export to TorchScript (.pt) or ONNX (.onnx)")
    x.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT), help="checkpoint (.pt)")
    x.add_argument(
        "--out", required=True, help="model.pt (TorchScript) or model.onnx", action=Output
    )
    _add_kind(x)
    x.set_defaults(func=_cmd_export)
