"""Depth network benchmark: accuracy on held-out phantoms and CPU inference speed.

    python benchmarks/bench_depth.py [--checkpoint CK] [--data DATASET_OR_SEQS ...]
                                     [--seeds 0-3] [--frames 30] [--bites 1] [--threads 2]
                                     [--effects-config config/sim_eval_effects.yaml]
                                     [--baseline CK]

Accuracy: median-scaled abs-rel / RMSE (mm) / delta<1.25 of the checkpoint (default: the
shipped one) on evaluation phantoms (seeds 0-99, never trained on). Without ``--data``
it renders ``--seeds`` with ``python -m sim dataset`` into a temporary folder. The peer
in the same run is a constant-depth predictor (what median scaling alone achieves).

With ``--effects-config`` the same phantoms are rendered a second time with that simulator
configuration and ``--tools`` (instruments, blood, smoke, blur, smears: issue 22) and the
checkpoint is scored on those frames too (``abs_rel_effects``; tool pixels are outside
the sequence masks, so not scored). ``--baseline`` scores a second checkpoint (e.g. the
network trained without the effects) on the same frames: ``baseline_abs_rel`` and
``baseline_abs_rel_effects``.

Speed: frames/s of the depth source (uint8 RGB frame -> depth map, batch 1, 320x256,
``--threads`` torch threads), eager checkpoint and TorchScript export. Prints
``name: value`` lines, ``infer_fps`` last (the path ``load_depth_source`` gives the
updater for a checkpoint: scripted, ``--threads`` threads, default 1), after the same
path with 2 threads. Timings on a shared machine are pessimistic.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from chisel.depth import (
    DEFAULT_CHECKPOINT,
    evaluate_source,
    export_model,
    find_sequences,
    load_depth_source,
    load_predictor,
)
from chisel.io.sequence import Frame, Sequence


class ConstantDepth:
    """Peer: the same depth everywhere (median scaling makes it the median truth)."""

    def __call__(self, frame: Frame) -> np.ndarray:
        assert frame.rgb is not None
        return np.ones(frame.rgb.shape[:2], np.float32)


def render_eval_set(
    seeds: str, frames: int, out: Path, config: Path | None = None, bites: int = 1
) -> Path:
    cmd = [sys.executable, "-m", "sim", "dataset", "--seeds", seeds, "--out", str(out)]
    cmd += [
        "--bites",
        str(bites),
        "--frames",
        str(frames),
        "--preop-frames",
        str(frames),
        "--quiet",
    ]
    if config is not None:
        cmd += ["--config", str(config), "--tools"]
    subprocess.run(cmd, check=True)
    return out


def fps(source, rgb: np.ndarray, seconds: float = 5.0) -> float:  # noqa: ANN001
    frame = Frame(index=0, T_world_from_cam=np.eye(4), rgb=rgb)
    for _ in range(5):
        source(frame)
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        source(frame)
        n += 1
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    ap.add_argument("--data", nargs="*", default=None, help="held-out dataset(s) or sequences")
    ap.add_argument("--seeds", default="0-3", help="evaluation phantom seeds to render (0-99)")
    ap.add_argument("--frames", type=int, default=20, help="frames per rendered sequence")
    ap.add_argument(
        "--bites",
        type=int,
        default=1,
        help="steps of the uncinectomy to render (default 1; 5: every step the workflow's "
        "table updates, the close-up views into the opening)",
    )
    ap.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads for the headline figure (default 1: on this shared 2-core "
        "machine 2 threads stall on descheduled OpenMP workers; infer_fps_threads2 shows it)",
    )
    ap.add_argument(
        "--effects-config",
        type=Path,
        default=None,
        help="sim config of a second evaluation set with effects (rendered with --tools)",
    )
    ap.add_argument(
        "--baseline", default=None, help="a second checkpoint scored on the same frames"
    )
    args = ap.parse_args()
    if args.effects_config is not None and args.data:
        ap.error("--effects-config renders --seeds; it does not go with --data")
    torch.set_num_threads(args.threads)
    ck = Path(args.checkpoint)
    print(f"checkpoint: {ck}")

    with tempfile.TemporaryDirectory(prefix="bench_depth_") as tmp:
        data = args.data
        if not data:
            t0 = time.perf_counter()
            data = [render_eval_set(args.seeds, args.frames, Path(tmp) / "eval", bites=args.bites)]
            print(f"render_seconds: {time.perf_counter() - t0:.1f}")
        refs = find_sequences(data)
        seeds = sorted({r.seed for r in refs if r.seed is not None})
        if any(s >= 100 for s in seeds):
            print(f"warning: seeds {seeds} include non-evaluation phantoms", file=sys.stderr)
        seqs = [Sequence(r.path) for r in refs]
        print(f"eval_phantom_seeds: {seeds}")
        print(f"eval_frames: {sum(len(s) for s in seqs)}")
        peer = evaluate_source(ConstantDepth(), seqs)
        print(f"abs_rel_constant_depth_peer: {peer.abs_rel:.4f}")
        source = load_depth_source(ck)
        m = evaluate_source(source, seqs)
        print(f"rmse_mm: {m.rmse_mm:.3f}")
        print(f"delta_1_25: {m.delta_1_25:.4f}")
        print(f"abs_rel: {m.abs_rel:.4f}")
        fx: list[Sequence] = []
        if args.effects_config is not None:
            fx_dir = render_eval_set(
                args.seeds, args.frames, Path(tmp) / "fx", args.effects_config, args.bites
            )
            fx = [Sequence(r.path) for r in find_sequences([fx_dir])]
            print(f"effects_config: {args.effects_config}")
            print(f"eval_frames_effects: {sum(len(s) for s in fx)}")
            print(
                f"abs_rel_effects_constant_depth_peer: {evaluate_source(ConstantDepth(), fx).abs_rel:.4f}"
            )
            print(f"abs_rel_effects: {evaluate_source(source, fx).abs_rel:.4f}")
        if args.baseline is not None:
            base = load_depth_source(Path(args.baseline))
            print(f"baseline: {args.baseline}")
            print(f"baseline_abs_rel: {evaluate_source(base, seqs).abs_rel:.4f}")
            if fx:
                print(f"baseline_abs_rel_effects: {evaluate_source(base, fx).abs_rel:.4f}")

        rng = np.random.default_rng(0)
        rgb = seqs[0].rgb(0) if seqs else rng.integers(0, 256, (256, 320, 3), dtype=np.uint8)
        print(f"infer_size: {rgb.shape[1]}x{rgb.shape[0]}")
        ts_path = export_model(load_predictor(ck)[0], Path(tmp) / "model.pt")
        print(f"infer_fps_eager: {fps(load_depth_source(ck, script=False), rgb):.1f}")
        print(f"infer_fps_torchscript_export: {fps(load_depth_source(ts_path), rgb):.1f}")
        torch.set_num_threads(2)
        print(f"infer_fps_threads2: {fps(source, rgb):.1f}")
        torch.set_num_threads(args.threads)
        print(f"infer_fps: {fps(source, rgb):.1f}")


if __name__ == "__main__":
    main()
