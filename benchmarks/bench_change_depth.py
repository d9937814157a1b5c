"""Change-aware depth network benchmark: per-frame accuracy on held-out phantoms, speed.

    python benchmarks/bench_change_depth.py --data EVAL_DATASET [--checkpoint CK]
                                            [--mono CK] [--frame-step 1] [--threads 1]

EVAL_DATASET: a ``python -m sim dataset`` folder of evaluation phantoms (seeds 0-99, never
trained on), e.g. ``python -m sim dataset --seeds 0-1 --out DIR --bites 3 --phantom-args
'--procedure uncinectomy' --frames 16 --preop-frames 12 --spp 4``. Every intraoperative
frame's prior is the previous step's phantom mesh rendered at the tracked pose
(``chisel.depth.prior_data``); the change label comes from the true pose.

Per frame, abs-rel in the changed region's neighbourhood (label dilated by 8 px) and on
the unchanged tissue, averaged over frames, against two references: ``vs_tracked`` = the
current surface rendered at the tracked pose (the network's training target: the depth
the updater compares and fuses at the tracked pose) and ``vs_true`` = the rendered true
depth (true pose; the tracking error alone puts the prior ~4 % off it):

- ``change_aware``: the checkpoint (default: the shipped one), metric, no scale solved;
- ``prior``: the render itself (what "no update" believes);
- ``monocular``: the shipped monocular network on the same frames, median-scaled to the
  true depth per frame (it is relative; this flatters it).

Pixel change mask of the change-aware output (depth - prior > 1 mm) against the label:
precision and recall over all frames. Speed: frames/s of one streaming step's depth
work at the frame size (ray-cast render of the model surface at the tracked pose +
the network, batch 1, ``--threads`` torch threads); the TSDF fusion is not included.
``--stream-update`` also times the whole streaming update (``ChiselUpdater``: render,
network, change mask, fusion; without and with per-frame registration, and with it and
the poses corrected by the frames' shading as the shipped experiments run the row) on a
model built from the previous step's mesh: ``process_stream`` (the next frame's render and network
overlap this frame's carving) and, as its peer in the same run, ``process`` frame by
frame. Prints ``name: value`` lines, ``change_aware_abs_rel`` last (mean of near and unchanged,
vs_tracked).
On a shared machine the timings are pessimistic.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from chisel.core.raycast import MeshRaycaster
from chisel.depth import DEFAULT_CHECKPOINT, load_depth_source
from chisel.depth.change_aware import DEFAULT_CHANGE_CHECKPOINT
from chisel.depth.change_source import load_change_aware_source
from chisel.depth.change_train import change_metrics
from chisel.depth.prior_data import build_prior_set, phantom_step_mesh, read_step_dataset
from chisel.io.sequence import Frame, Sequence

sys.path.insert(0, str(Path(__file__).resolve().parent))
from host import cpu_simd, shipped_noise_with_depth  # noqa: E402


def _median_scaled(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    ok = np.isfinite(pred) & np.isfinite(target) & (pred > 0)
    return pred * (np.median(target[ok]) / np.median(pred[ok]))


def _stream_update(ref, seq: Sequence, change, repeats: int = 5) -> None:  # noqa: ANN001
    """frames/s of the streaming update (render M_t, the network, change mask, fusion) on
    a model built from the previous step's mesh at the preop sweep's poses (voxel 0.5 mm):
    ``ChiselUpdater.process_stream`` (the next frame's render and network overlap this
    frame's detection and carving) against ``process`` frame by frame, same run, each the
    median of ``repeats`` alternating passes over the step."""
    from chisel.build import BuildConfig, build_preop_model
    from chisel.change import ChangeConfig
    from chisel.shading import ShadingConfig
    from chisel.update_config import UpdateConfig
    from chisel.updater import ChiselUpdater

    preop = Sequence(ref.path.parent / "preop")
    mesh = phantom_step_mesh(ref.phantom_dir, ref.step - 1)
    model = build_preop_model(mesh, seq.camera, preop.poses, BuildConfig(voxel_size_mm=0.5))
    frames = [seq.frame(i, depth=False) for i in range(len(seq))]
    warm = ChiselUpdater(model, seq.camera, change)
    warm.begin_step()
    list(warm.process_stream(frames[:3]))  # JIT kernels, allocator, the worker thread
    variants = {
        "no_registration": UpdateConfig(register=False),
        "registration": UpdateConfig(register=True),
        # as the shipped experiments run the change-aware row: poses corrected by shading,
        # the change threshold growing with depth where config/config.yaml says so
        "registration_shading": UpdateConfig(
            shading=ShadingConfig(align_by_shading=True),
            change=ChangeConfig(noise_with_depth=shipped_noise_with_depth()),
        ),
    }
    for name, cfg in variants.items():
        runs: dict[str, list[float]] = {"process": [], "process_stream": []}
        for _ in range(repeats):  # alternating, the median of each
            for mode, rates in runs.items():
                upd = ChiselUpdater(model, seq.camera, change, cfg)
                upd.begin_step()
                t = time.perf_counter()
                if mode == "process":
                    reports = [upd.process(f) for f in frames]
                else:
                    reports = list(upd.process_stream(frames))
                rates.append(len(reports) / (time.perf_counter() - t))
        fps = {mode: float(np.median(rates)) for mode, rates in runs.items()}
        print(f"stream_update_{name}_frame_by_frame_fps: {fps['process']:.1f}")
        print(f"stream_update_{name}_fps: {fps['process_stream']:.1f}")
        print(f"stream_update_{name}_overlap_speedup: {fps['process_stream'] / fps['process']:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, nargs="+", help="evaluation dataset folder(s)")
    ap.add_argument("--checkpoint", default=str(DEFAULT_CHANGE_CHECKPOINT))
    ap.add_argument("--mono", default=str(DEFAULT_CHECKPOINT), help="monocular checkpoint")
    ap.add_argument("--frame-step", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--stream-update",
        action="store_true",
        help="also time ChiselUpdater.process per frame (builds a TSDF model first; slow)",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    refs = [r for r in read_step_dataset(args.data) if r.step >= 1]
    pairs = build_prior_set(refs, frame_step=args.frame_step)
    change = load_change_aware_source(args.checkpoint)
    mono = load_depth_source(args.mono)
    names = ("change_aware", "prior", "monocular")
    rows: dict[tuple[str, str], list[dict[str, float]]] = {
        (n, ref): [] for n in names for ref in ("tracked", "true")
    }
    tp = fp = fn = 0
    for i in range(len(pairs)):
        rgb = pairs.rgb[i].numpy()
        prior = pairs.prior_mm[i].numpy()
        label = pairs.changed[i].numpy()
        depth, _ = change.predict(rgb, prior)
        mono_rel = mono.predict(rgb)
        for ref, target in (
            ("tracked", pairs.target_mm[i].numpy()),
            ("true", pairs.true_mm[i].numpy()),
        ):
            mono_depth = _median_scaled(mono_rel, target)
            for name, d in (("change_aware", depth), ("prior", prior), ("monocular", mono_depth)):
                rows[(name, ref)].append(change_metrics(d, target, label))
        with np.errstate(invalid="ignore"):
            pred = np.isfinite(depth) & (depth - prior > 1.0)
        tp += int((pred & label).sum())
        fp += int((pred & ~label).sum())
        fn += int((~pred & label).sum())
    print(f"frames: {len(pairs)} (seeds {sorted({r.seed for r in refs})}, steps >= 1)")
    print(f"frames_with_change: {sum(bool(pairs.changed[i].any()) for i in range(len(pairs)))}")
    summary = {}
    for (name, ref), ms in rows.items():
        near = [m["abs_rel_near"] for m in ms if m["pixels_near"] > 0]
        unch = [m["abs_rel_unchanged"] for m in ms if m["pixels_unchanged"] > 0]
        summary[(name, ref)] = (float(np.nanmean(near)), float(np.nanmean(unch)))
        print(f"{name}_vs_{ref}_abs_rel_near_change: {summary[(name, ref)][0]:.4f}")
        print(f"{name}_vs_{ref}_abs_rel_unchanged: {summary[(name, ref)][1]:.4f}")
    print(f"change_aware_mask_precision: {tp / max(tp + fp, 1):.3f}")
    print(f"change_aware_mask_recall: {tp / max(tp + fn, 1):.3f}")
    # Streaming: render the model surface at the tracked pose, then the network.
    ref = refs[0]
    seq = Sequence(ref.path)
    mesh = phantom_step_mesh(ref.phantom_dir, ref.step - 1)
    rc = MeshRaycaster(mesh.vertices, mesh.faces)
    frames = [seq.frame(i, depth=False) for i in range(len(seq))]
    for f in frames[:3]:  # warm-up (JIT kernels, allocator)
        change(f, prior_mm=rc.render_depth(seq.camera, f.T_world_from_cam))
    times = []
    for f in frames:
        t = time.perf_counter()
        change(Frame(f.index, f.T_world_from_cam, rgb=f.rgb, mask=f.mask),
               prior_mm=rc.render_depth(seq.camera, f.T_world_from_cam))  # fmt: skip
        times.append(time.perf_counter() - t)
    if args.stream_update:
        _stream_update(ref, seq, change)
    print(f"image_size: {seq.camera.width}x{seq.camera.height}")
    print(f"cpu_simd: {cpu_simd()}")
    print(f"noise_with_depth: {shipped_noise_with_depth()}")
    print(f"threads: {args.threads}")
    print(f"load_average_1min: {Path('/proc/loadavg').read_text().split()[0]}")
    print(f"stream_render_plus_infer_fps_median: {1.0 / float(np.median(times)):.1f}")
    print(f"stream_render_plus_infer_fps_best: {1.0 / float(np.min(times)):.1f}")
    print(f"change_aware_abs_rel: {0.5 * sum(summary[('change_aware', 'tracked')]):.4f}")


if __name__ == "__main__":
    main()
