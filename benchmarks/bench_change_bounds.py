"""What bounds a depth estimate near a change, frame by frame, without any network.

    python benchmarks/bench_change_bounds.py --data EVAL_DATASET [--frame-step 1]

EVAL_DATASET: a ``python -m sim dataset`` folder of evaluation phantoms, as for
``bench_change_depth.py`` (e.g. ``python -m sim dataset --seeds 0-3 --out DIR --bites 5
--phantom-args '--procedure uncinectomy' --frames 16 --preop-frames 12 --spp 4``).

Issue 20 scores the change-aware network per frame by abs-rel "near the change" (the
changed pixels dilated by 8 px) against the current surface rendered at the frame's
*tracked* pose, the depth the updater compares and fuses (``bench_change_depth.py``).
The frame's image, though, is taken at its *true* pose. Every figure here comes from the
phantom's meshes alone, against that same target:

- ``label_iou_tracked_true``: the change as the image shows it (labelled at the true pose)
  against the change the target holds (labelled at the tracked pose): intersection over
  union of the two pixel masks, mean over frames; ``label_recall_true_of_tracked`` the
  share of the target's changed pixels that the image shows changed;
- ``prior_near_abs_rel``: the previous surface at the tracked pose (no update);
- ``image_exact_near_abs_rel``: the frame's exact depth (the current surface at the true
  pose), an estimator without error in the image's own frame;
- ``next_layer_*``: the surface the previous model holds behind the first layer along
  each ray (the third crossing: the back of the layer, then the next surface), at the
  tracked pose. ``next_layer_where_changed`` puts it at every pixel the target labels
  changed and the previous surface elsewhere; ``next_layer_best`` takes per pixel the
  better of the two (an oracle choice between the two hypotheses the CT gives);
  ``next_layer_within_0p5mm`` is the share of changed pixels whose next surface lies
  within 0.5 mm of the target.

Prints ``name: value`` lines, ``image_exact_near_abs_rel`` last.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from chisel.core.raycast import MeshRaycaster, SurfaceQueries, unit_rays
from chisel.depth.change_train import change_metrics
from chisel.depth.prior_data import CHANGE_THRESHOLD_MM, phantom_step_mesh, read_step_dataset
from chisel.io.sequence import Sequence

sys.path.insert(0, str(Path(__file__).resolve().parent))
from host import cpu_simd  # noqa: E402


def next_surface_depth(
    surface: SurfaceQueries, rays_cam: np.ndarray, T_world_from_cam: np.ndarray
) -> np.ndarray:
    """(H, W) float32 z-depth of the third surface crossing along each pixel's ray (the
    next surface behind the first tissue layer), NaN where there is none."""
    d_cam = unit_rays(rays_cam)
    h, w = d_cam.shape[:2]
    d_world = d_cam.reshape(-1, 3) @ T_world_from_cam[:3, :3].T
    origins = np.broadcast_to(T_world_from_cam[:3, 3], d_world.shape)
    t = surface.hits(origins, d_world, 3)[:, 2]
    z = (t * d_cam.reshape(-1, 3)[:, 2]).reshape(h, w)
    return np.where(np.isfinite(z), z, np.nan).astype(np.float32)


def changed_label(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Pixels whose surface moved deeper by more than the paper's change threshold."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(before) & np.isfinite(after) & (after - before > CHANGE_THRESHOLD_MM)


def frame_figures(
    z_prior: np.ndarray,
    z_next: np.ndarray,
    target: np.ndarray,
    image_exact: np.ndarray,
    label: np.ndarray,
    label_true: np.ndarray,
) -> dict[str, float]:
    """One frame's figures (see the module doc); maps (H, W) float32 mm, NaN = invalid."""
    has_next = np.isfinite(z_next)
    where_changed = np.where(label & has_next, z_next, z_prior)
    closer = has_next & (np.abs(z_next - target) < np.abs(z_prior - target))
    best = np.where(closer, z_next, z_prior)
    union = (label | label_true).sum()
    out = {
        "label_iou_tracked_true": float((label & label_true).sum() / max(union, 1)),
        "label_recall_true_of_tracked": float((label & label_true).sum() / label.sum()),
        "next_layer_within_0p5mm": float(
            (np.abs(z_next - target)[label & has_next] <= 0.5).sum() / label.sum()
        ),
    }
    for name, depth in (
        ("prior", z_prior),
        ("image_exact", image_exact),
        ("next_layer_where_changed", where_changed),
        ("next_layer_best", best),
    ):
        out[f"{name}_near_abs_rel"] = change_metrics(depth, target, label)["abs_rel_near"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, nargs="+", help="evaluation dataset folder(s)")
    ap.add_argument("--frame-step", type=int, default=1)
    args = ap.parse_args()
    t0 = time.perf_counter()
    refs = [r for r in read_step_dataset(args.data) if r.step >= 1]
    rows: list[dict[str, float]] = []
    for ref in refs:
        seq = Sequence(ref.path)
        if seq.true_poses is None:
            raise SystemExit(f"{ref.path}: no true poses (not a rendered sequence)")
        before = phantom_step_mesh(ref.phantom_dir, ref.step - 1)
        after = phantom_step_mesh(ref.phantom_dir, ref.step)
        rc_before = MeshRaycaster(before.vertices, before.faces)
        rc_after = MeshRaycaster(after.vertices, after.faces)
        surface = SurfaceQueries.from_trimesh(before)
        rays = seq.camera.rays_cam()
        for i in range(0, len(seq), args.frame_step):
            T, T_true = seq.poses[i], seq.true_poses[i]
            z_prior = rc_before.render_depth(seq.camera, T)
            target = rc_after.render_depth(seq.camera, T)
            label = changed_label(z_prior, target)
            if not label.any():
                continue
            image_exact = rc_after.render_depth(seq.camera, T_true)
            label_true = changed_label(rc_before.render_depth(seq.camera, T_true), image_exact)
            z_next = next_surface_depth(surface, rays, T)
            rows.append(frame_figures(z_prior, z_next, target, image_exact, label, label_true))
    if not rows:
        raise SystemExit("no frame shows a change")
    print(f"frames_with_change: {len(rows)} (seeds {sorted({r.seed for r in refs})})")
    print(f"cpu_simd: {cpu_simd()}")
    print(f"elapsed_s: {time.perf_counter() - t0:.1f}")
    names = [k for k in rows[0] if k != "image_exact_near_abs_rel"] + ["image_exact_near_abs_rel"]
    for name in names:
        print(f"{name}: {float(np.nanmean([r[name] for r in rows])):.4f}")


if __name__ == "__main__":
    main()
