"""Benchmark: how far the shading's step correction brings the frames onto their true view,
with the image shift converted into a translation at the render's median depth (shipped)
and at the depth whose parallax the shift measures.

The shading correction (:mod:`chisel.shading`) turns each frame's best image shift into a
sideways camera translation at one depth, the render's median. A sideways translation t
moves a surface at depth z by f t / z pixels, so a view that spans depths has no single
shift: to first order the best-correlating shift is the flow averaged with the predicted
pattern's squared gradient along each axis as weights (Lucas-Kanade's normal equations for
one shift), i.e. the shift of a surface at the "parallax depth" 1 / mean_w(1 / z). On the
phantoms that depth lies beyond the median: the folded, far part of a view holds the
shading's structure, its near walls are smooth. Converting there reads each frame's shift
better on average but gives no better step correction (docs/results.md, forty-third
session), so the shipped code keeps the median.

For each seed and step of a finished workflow run (`table` or `all`), with M_t the
method's model before the step (the preop model at step 1) rendered at the step's tracked
poses, it prints the image misalignment between each frame's corrected pose and its true
pose (median pixel displacement of the model's visible points, mean over frames) for: no
correction, the step correction with the shift converted at the median depth, and at the
parallax depth; with ``--oracle`` also the best constant sideways translation (searched
on the true poses: a bound no frame-based estimate can beat); with ``--odometry`` also the
poses smoothed by the frames' odometry (:mod:`chisel.odometry`, every frame of the step)
alone and then corrected by the shading's step correction measured from them. Per step it also prints the
measured shifts' least-squares slope against the true flow at each depth, both axes
pooled (1 = the conversion matches the shift).

Prints ``name: value`` lines: per seed and step ``seed_S_step_K_{none,median,parallax}_px``
(and ``_oracle_px``, ``_odometry_px``, ``_odometry_median_px``),
``seed_S_step_K_slope_{median,parallax}``; then means,
``parallax_better_steps``, with ``--odometry`` ``odometry_better_steps`` and
``odometry_over_median_misalignment_geomean``, and last ``parallax_over_median_misalignment_geomean`` (< 1: the
parallax depth aligns better).

    .venv/bin/python benchmarks/bench_shading_alignment.py --run RUN/results/default \\
        --seeds 0-4 [--steps 1-5] [--method updated] [--frame-step 1] [--oracle] [--odometry]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chisel.core.geometry import Camera  # noqa: E402
from chisel.core.raycast import MeshRaycaster  # noqa: E402
from chisel.io.sequence import Sequence  # noqa: E402
from chisel.model import TsdfModel  # noqa: E402
from chisel.odometry import OdometryConfig, smooth_poses  # noqa: E402
from chisel.render import ModelRenderer  # noqa: E402
from chisel.shading import (  # noqa: E402
    ShadingConfig,
    high_pass,
    log_shading,
    shading_shift,
    shading_translation,
    shift_passes,
    step_correction,
    translation_for_shift,
)
from chisel.update_config import UpdateConfig  # noqa: E402
from sim.dataset import parse_seeds  # noqa: E402


def parallax_inverse_depth(
    pattern: np.ndarray, valid: np.ndarray, depth_mm: np.ndarray
) -> tuple[float, float] | None:
    """Per image axis, 1/z (1/mm) averaged with the pattern's squared central difference
    along that axis as weights, over pixels whose both neighbours are valid; None where
    an axis has no gradient."""
    z = np.asarray(depth_mm, dtype=np.float64)
    ok = np.asarray(valid, bool) & np.isfinite(z) & (z > 0)
    inv = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
    p = np.asarray(pattern, dtype=np.float64)
    out = []
    for axis in (1, 0):
        lo = [slice(None), slice(None)]
        hi = [slice(None), slice(None)]
        mid = [slice(None), slice(None)]
        lo[axis], hi[axis], mid[axis] = slice(None, -2), slice(2, None), slice(1, -1)
        both = ok[tuple(lo)] & ok[tuple(hi)] & ok[tuple(mid)]
        g = np.where(both, p[tuple(hi)] - p[tuple(lo)], 0.0)
        w = g * g
        if not w.sum() > 0:
            return None
        out.append(float((w * inv[tuple(mid)]).sum() / w.sum()))
    return out[0], out[1]


def misalignment_px(
    depth_true_mm: np.ndarray, camera: Camera, T_true: np.ndarray, T_pose: np.ndarray
) -> float:
    """Median pixel displacement of the surface points the true view sees (z-depth
    ``depth_true_mm`` at ``T_true``) when projected from ``T_pose`` instead; NaN if none."""
    v, u = np.nonzero(np.isfinite(depth_true_mm))
    if len(u) == 0:
        return float("nan")
    P = camera.backproject(depth_true_mm)[v, u]
    C = np.linalg.inv(T_pose) @ T_true
    uv, _ = camera.project(P @ C[:3, :3].T + C[:3, 3])
    return float(np.median(np.hypot(uv[:, 0] - u, uv[:, 1] - v)))


def _slope(measured: list[float], expected: list[float]) -> float:
    x, y = np.asarray(expected), np.asarray(measured)
    return float(x @ y / (x @ x)) if x @ x > 0 else float("nan")


def _odometry(seq: Sequence, rc: MeshRaycaster, cfg: ShadingConfig) -> dict[str, float]:
    """Misalignment of every frame of the step after the odometry's smoothing, alone and
    followed by the shading's step correction (median depth) measured from its poses."""
    cam = seq.camera
    n = len(seq)
    tracked = [seq.poses[i] for i in range(n)]
    true = np.stack([seq.true_poses[i] for i in range(n)])
    frames = [seq.frame(i, depth=False) for i in range(n)]
    renders = rc.render_depths(cam, np.stack(tracked))
    truths = rc.render_depths(cam, true)
    smoothed, _ = smooth_poses(
        [f.rgb for f in frames], [f.mask for f in frames], list(renders), tracked, cam,
        OdometryConfig(),
    )  # fmt: skip
    R = rc.render_depths(cam, np.stack(smoothed))
    found = [shading_translation(f.rgb, R[k], cam, f.mask, cfg) for k, f in enumerate(frames)]
    F = step_correction([t for t in found if t is not None])

    def mean_misalignment(poses: list[np.ndarray]) -> float:
        return float(
            np.nanmean([misalignment_px(truths[k], cam, true[k], poses[k]) for k in range(n)])
        )

    return {
        "odometry_px": mean_misalignment(smoothed),
        "odometry_median_px": mean_misalignment([T @ F for T in smoothed]),
    }


def _step(
    run: Path, seed: int, step: int, method: str, frame_step: int, oracle: bool, odometry: bool
) -> dict[str, float]:
    cfg = UpdateConfig().shading
    base = run / f"seed_{seed}"
    seq = Sequence(base / "render" / f"step_{step:02d}")
    if seq.true_poses is None:
        raise SystemExit(f"{seq.path}: no true poses (a synthetic sequence is needed)")
    cam = seq.camera
    model_path = (
        base / "preop" / "model.npz"
        if step == 1
        else base / "base" / method / f"step_{step - 1:02d}" / "model.npz"
    )
    if not model_path.is_file():
        raise SystemExit(f"{model_path}: missing (is {run} a finished run with {method}?)")
    rc = ModelRenderer(TsdfModel.load(model_path)).raycaster
    idx = list(range(0, len(seq), frame_step))
    tracked = np.stack([seq.poses[i] for i in idx])
    true = np.stack([seq.true_poses[i] for i in idx])
    renders = rc.render_depths(cam, tracked)
    truths = rc.render_depths(cam, true)
    rays = cam.rays_cam()
    t_median, t_parallax = [], []
    shifts, flow_median, flow_parallax = [], [], []
    for k, i in enumerate(idx):
        R = renders[k]
        finite = np.isfinite(R)
        if not finite.any():
            continue
        f = seq.frame(i, depth=False)
        sh = shading_shift(f.rgb, R, cam, f.mask, cfg)
        if not shift_passes(sh, cfg):
            continue
        s, ms = log_shading(R, rays)
        b, mb = high_pass(s, ms, cfg.shading_sigma_px)
        inv = parallax_inverse_depth(b, mb, R)
        if inv is None:
            continue
        d = float(np.median(R[finite]))
        t_median.append(translation_for_shift(cam, sh.dx_px, sh.dy_px, d)[:3, 3])
        t_parallax.append(
            np.array([sh.dx_px / (cam.fx * inv[0]), sh.dy_px / (cam.fy * inv[1]), 0.0])
        )
        # The true flow of a point on the optical axis at each conversion's depth, per axis.
        C = np.linalg.inv(tracked[k]) @ true[k]
        for axis, shift, focal in ((0, sh.dx_px, cam.fx), (1, sh.dy_px, cam.fy)):
            for depth, flows in ((d, flow_median), (1.0 / inv[axis], flow_parallax)):
                p = C[:3, :3] @ np.array([0.0, 0.0, depth]) + C[:3, 3]
                flows.append(focal * p[axis] / p[2])
            shifts.append(float(shift))

    def mean_misalignment(F: np.ndarray) -> float:
        return float(
            np.nanmean(
                [misalignment_px(truths[k], cam, true[k], tracked[k] @ F) for k in range(len(idx))]
            )
        )

    out = {
        "none_px": mean_misalignment(np.eye(4)),
        "median_px": mean_misalignment(step_correction(t_median)),
        "parallax_px": mean_misalignment(step_correction(t_parallax)),
        "slope_median": _slope(shifts, flow_median),
        "slope_parallax": _slope(shifts, flow_parallax),
        "frames": float(len(t_median)),
    }
    if oracle:
        from scipy.optimize import minimize

        def cost(xy: np.ndarray) -> float:
            F = np.eye(4)
            F[:2, 3] = xy
            return mean_misalignment(F)

        start = step_correction(t_median)[:2, 3]
        out["oracle_px"] = float(minimize(cost, start, method="Nelder-Mead").fun)
    if odometry:
        out.update(_odometry(seq, rc, cfg))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, type=Path, help="a finished run's results/EXP")
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--steps", default="1-5")
    ap.add_argument("--method", default="updated", help="whose M_t (a network row)")
    ap.add_argument("--frame-step", type=int, default=1)
    ap.add_argument("--oracle", action="store_true", help="also the best constant translation")
    ap.add_argument(
        "--odometry", action="store_true", help="also the poses smoothed by odometry (all frames)"
    )
    args = ap.parse_args()
    if args.frame_step < 1:
        ap.error("--frame-step must be >= 1")
    rows = {}
    for seed in parse_seeds(args.seeds):
        for step in parse_seeds(args.steps):
            r = _step(
                args.run, seed, step, args.method, args.frame_step, args.oracle, args.odometry
            )
            rows[(seed, step)] = r
            for key, value in r.items():
                fmt = ".0f" if key == "frames" else ".3f"
                print(f"seed_{seed}_step_{step}_{key}: {value:{fmt}}", flush=True)
    keys = ["none_px", "median_px", "parallax_px"] + (["oracle_px"] if args.oracle else [])
    keys += ["odometry_px", "odometry_median_px"] if args.odometry else []
    for key in keys + ["slope_median", "slope_parallax"]:
        print(f"mean_{key}: {np.nanmean([r[key] for r in rows.values()]):.3f}")
    better = sum(r["parallax_px"] < r["median_px"] for r in rows.values())
    print(f"parallax_better_steps: {better} of {len(rows)}")
    if args.odometry:
        ratios = [r["odometry_median_px"] / r["median_px"] for r in rows.values()]
        print(f"odometry_better_steps: {sum(q < 1 for q in ratios)} of {len(rows)}")
        geo_odometry = math.exp(np.mean(np.log(ratios)))
        print(f"odometry_over_median_misalignment_geomean: {geo_odometry:.3f}")
    geo = math.exp(np.mean([math.log(r["parallax_px"] / r["median_px"]) for r in rows.values()]))
    print(f"parallax_over_median_misalignment_geomean: {geo:.3f}")


if __name__ == "__main__":
    main()
