"""``python -m sim``: render phantoms into sequence folders, export, build training sets.

Subcommands: ``render``, ``export-nerfstudio``, ``dataset``, ``retrack``. Errors the user can fix
(bad phantom, mesh, path, config) print one line naming the file/argument and exit 1.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from chisel.core.errors import run_command
from sim.config import SimConfig, load_config, replace_in

_DESCRIPTION = """\
Endoscope simulator: Mitsuba 3 renders of a phantom's tissue meshes along seeded,
collision-checked camera paths, with ground-truth depth and tracked (noisy) poses.

Units: millimetres and degrees. Poses are T_world_from_cam (world = the phantom's CT
frame) with OpenCV camera axes (+x right, +y down, +z forward). Depth is z-depth in mm
(float32 .npy, 0 = invalid on disk). Output folders follow the sequence contract of
chisel.io.sequence (docs/sim.md, docs/conventions.md).
"""

_RENDER_EPILOG = """\
Writes OUT atomically:
  OUT/render.json        {"format": "endoscopic-chisel/render", "version": 1, "phantom",
                         "variant", "num_steps", "sequences": {"preop", "steps", "eval"}, "config"}
  OUT/preop/             preoperative sweep along the airway (step 0's mesh)
  OUT/step_NN/           intraoperative sequence of step NN (that step's mesh)
  OUT/eval/step_NN/      fixed evaluation poses on step NN's mesh (exact poses)
Each sequence: sequence.json, poses.txt (tracked), poses_true.txt, rgb/*.png,
depth/*.npy (z-depth mm, 0 = invalid), mask/*.png (valid depth), camera_mask.png (field stop).
With --tools, intraoperative sequences add depth_visible/*.npy (tool included),
tool_mask/*.png (255 = instrument) and tools.json; depth/ is the tissue behind the tool and
mask/ leaves the tool out.
"""


def _add_render_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="YAML configuration (see config/sim_default.yaml)")
    p.add_argument("--frames", type=int, help="frames per intraoperative sequence (default 80)")
    p.add_argument("--preop-frames", type=int, help="frames of the preoperative sweep (default 60)")
    p.add_argument("--width", type=int, help="image width in pixels (default 320)")
    p.add_argument("--height", type=int, help="image height in pixels (default 256)")
    p.add_argument("--spp", type=int, help="samples per pixel of the RGB render (default 16)")
    p.add_argument("--seed", type=int, help="master seed for paths, texture and noise (default 0)")
    p.add_argument(
        "--pose-noise-mm", type=float, help="tracking jitter, std per axis in mm (default 0.2)"
    )
    p.add_argument(
        "--pose-noise-deg",
        type=float,
        help="tracking jitter, std per axis in degrees (default 0.1)",
    )
    p.add_argument("--depth-only", action="store_true", help="render depth and masks only (no RGB)")
    p.add_argument(
        "--tools",
        action="store_true",
        help="instruments in view in the intraoperative sequences (config tools.*): adds "
        "depth_visible/ (z-depth mm with the tool) and tool_mask/ (255 = tool) per sequence; "
        "depth/ stays the tissue's depth and mask/ excludes the tool",
    )
    p.add_argument(
        "--variant",
        choices=["auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"],
        help="Mitsuba variant (default auto: cuda on a GPU, else llvm, else scalar with a warning)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _config_from_args(args: argparse.Namespace) -> SimConfig:
    cfg = load_config(args.config)
    cfg = replace_in(
        cfg,
        **{
            "paths.intraop_frames": args.frames,
            "paths.preop_frames": args.preop_frames,
            "paths.eval_poses": getattr(args, "eval_poses", None),
            "camera.width": args.width,
            "camera.height": args.height,
            "imaging.spp": args.spp,
            "seed": args.seed,
            "tracking.jitter_mm": args.pose_noise_mm,
            "tracking.jitter_deg": args.pose_noise_deg,
            "variant": args.variant,
        },
    )
    if args.depth_only:
        cfg = replace_in(cfg, depth_only=True)
    if args.tools:
        cfg = replace_in(cfg, **{"tools.enabled": True})
    return cfg


def _cmd_render(args: argparse.Namespace) -> int:
    from sim.pipeline import render_phantom  # noqa: PLC0415 - keep --help fast

    cfg = _config_from_args(args)
    header = render_phantom(
        args.phantom,
        args.out,
        cfg,
        progress=not args.quiet,
        allow_outside_phantom=args.allow_outside_phantom,
    )
    logging.getLogger("sim").info(
        "rendered %d step(s) with %s into %s", header["num_steps"], header["variant"], args.out
    )
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from sim.nerfstudio import export_nerfstudio  # noqa: PLC0415

    path = export_nerfstudio(
        args.sequence, args.out, use_true_poses=args.true_poses, units=args.units
    )
    logging.getLogger("sim").info("wrote %s", path)
    return 0


def _cmd_dataset(args: argparse.Namespace) -> int:
    from sim.dataset import build_dataset, parse_seeds  # noqa: PLC0415

    cfg = _config_from_args(args)
    ds = build_dataset(
        args.out,
        parse_seeds(args.seeds),
        cfg,
        bites=args.bites,
        phantom_cmd=args.phantom_cmd,
        phantom_args=args.phantom_args,
        resume=args.resume,
        progress=not args.quiet,
        command=["python", "-m", "sim", *args.argv],
        write_index=not args.no_index,
        phantom_ct=args.phantom_ct,
    )
    logging.getLogger("sim").info(
        "dataset: %d sequences, %d frames in %s", ds["num_sequences"], ds["num_frames"], args.out
    )
    return 0


def _cmd_retrack(args: argparse.Namespace) -> int:
    from sim.config import TrackingConfig  # noqa: PLC0415
    from sim.retrack import retrack_sequence  # noqa: PLC0415

    cfg = TrackingConfig(
        args.jitter_mm, args.jitter_deg, args.handeye_mm, args.handeye_deg, args.latency_frames
    )
    retrack_sequence(args.sequence, args.out, cfg, args.seed)
    logging.getLogger("sim").info("re-tracked %s -> %s", args.sequence, args.out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sim",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    r = sub.add_parser(
        "render",
        help="render a phantom's preop sweep, per-step sequences and evaluation poses",
        description="Render a phantom folder (phantom.json + meshes) into sequence folders.",
        epilog=_RENDER_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    r.add_argument(
        "--phantom", type=Path, required=True, help="phantom folder holding phantom.json"
    )
    r.add_argument("--out", type=Path, required=True, help="output folder (replaced atomically)")
    r.add_argument("--eval-poses", type=int, help="number of fixed evaluation poses (default 8)")
    r.add_argument(
        "--allow-outside-phantom",
        action="store_true",
        help="let phantom.json name meshes outside the phantom folder (links resolved); "
        "refused by default so that one phantom cannot render another's files",
    )
    _add_render_options(r)
    r.set_defaults(func=_cmd_render)

    e = sub.add_parser(
        "export-nerfstudio",
        help="export a sequence folder as nerfstudio transforms.json",
        description=(
            "Write DIR/transforms.json (camera_model OPENCV, OpenGL camera axes, pixel-centre "
            "offset +0.5 applied to cx/cy), DIR/images/*.png, DIR/depth/*.npy (z-depth mm, "
            "0 = invalid) and DIR/masks/*.png. Poses are in metres by default, which matches "
            "nerfstudio's default depth_unit_scale_factor of 1e-3."
        ),
    )
    e.add_argument("--sequence", type=Path, required=True, help="sequence folder (sequence.json)")
    e.add_argument("--out", type=Path, required=True, help="output folder (replaced atomically)")
    e.add_argument(
        "--true-poses", action="store_true", help="export poses_true.txt instead of tracked poses"
    )
    e.add_argument(
        "--units",
        choices=["m", "mm"],
        default="m",
        help="translation units of the poses (default m)",
    )
    e.set_defaults(func=_cmd_export)

    d = sub.add_parser(
        "dataset",
        help="generate phantoms for many seeds and render a randomised training set",
        description=(
            "For each seed, run `python -m phantoms generate --seed S --bites N --out "
            "DIR/phantoms/seed_S`, draw appearance from the config's randomization ranges, and "
            "render the preop sweep and per-step sequences (RGB + depth, direct lighting) into "
            "DIR/seed_S/. Each render's master seed is its phantom seed; a non-zero --seed "
            "is mixed into it (another draw of paths, appearance and noise on the same "
            "phantoms). Writes DIR/dataset.json listing sequence folders with their phantom seed."
        ),
    )
    d.add_argument("--seeds", required=True, help="phantom seeds: '100-119', '1,4,9' or '1-3,8'")
    d.add_argument("--out", type=Path, required=True, help="output folder")
    d.add_argument("--bites", type=int, default=2, help="surgical bites per phantom (default 2)")
    d.add_argument(
        "--phantom-cmd", help="generator command (default: '<python> -m phantoms generate')"
    )
    d.add_argument(
        "--phantom-args", default="", help="extra arguments for the generator, one string"
    )
    d.add_argument(
        "--phantom-ct",
        action="store_true",
        help="the default generator also writes each phantom's CT volumes (NIfTI); without it "
        "it runs with --no-ct, as rendering needs the meshes only",
    )
    d.add_argument("--resume", action="store_true", help="keep seeds already rendered in DIR")
    d.add_argument(
        "--no-index",
        action="store_true",
        help="render the seeds only, without DIR/dataset.json and the card (one job per seed; "
        "a final --resume run over every seed writes them)",
    )
    _add_render_options(d)
    d.set_defaults(func=_cmd_dataset)

    t = sub.add_parser(
        "retrack",
        help="same frames, new tracked poses with another tracking-noise model",
        description=(
            "Copy a synthetic sequence (it needs poses_true.txt) and redraw its tracked poses: "
            "T_tracked = T_true[i - latency] @ E_handeye @ J_i (camera frame), E a constant "
            "hand-eye error of exactly --handeye-mm / --handeye-deg, J_i per-frame jitter with "
            "std --jitter-mm / --jitter-deg per axis. All zero = exact poses."
        ),
    )
    t.add_argument("--sequence", type=Path, required=True, help="input sequence folder")
    t.add_argument("--out", type=Path, required=True, help="output folder (replaced atomically)")
    t.add_argument("--jitter-mm", type=float, default=0.0, help="jitter std per axis, mm (0)")
    t.add_argument("--jitter-deg", type=float, default=0.0, help="jitter std per axis, degrees (0)")
    t.add_argument(
        "--handeye-mm", type=float, default=0.0, help="hand-eye translation error, mm (0)"
    )
    t.add_argument(
        "--handeye-deg", type=float, default=0.0, help="hand-eye rotation error, deg (0)"
    )
    t.add_argument("--latency-frames", type=int, default=0, help="tracking latency in frames (0)")
    t.add_argument("--seed", type=int, default=0, help="seed of the noise draws (0)")
    t.set_defaults(func=_cmd_retrack)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # recorded in dataset cards
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.command is None else 2
    # Named if memory runs out outside every reader (which name their own file).
    inputs = [
        f"--{dest.replace('_', '-')} {value}"
        for dest, value in vars(args).items()
        if dest != "out" and isinstance(value, Path) and value.exists()
    ]
    return run_command(f"sim {args.command}", lambda: args.func(args), inputs)
