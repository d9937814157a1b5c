"""Speed and memory of the updater on a generated phantom (``name: value`` lines).

Scene: ``python -m phantoms generate`` (seed, 1 bite) when the phantom generator is
installed; camera poses along the phantom's airway path looking at the bite target
(``chisel.core.geometry.look_at``), ground-truth depth by ray casting the step meshes
(``sim`` is not needed). Falls back to the analytic test room with ``--scene room``.

Measured, at 320x256 and 0.5 mm voxels by default:

* plain fusion of the preoperative frames: ours (``chisel.fusion.integrate``) vs Open3D
  ``o3d.t.geometry.VoxelBlockGrid.integrate`` on the same depth maps in the same run
  (best of ``--repeats``; depth rendering excluded from both);
* one surgical step of 80 frames with a monocular-like depth (ground truth times an
  unknown scale) and tracked poses carrying a 2 mm / 2 deg hand-eye error plus jitter:
  ``update_fps`` is the per-frame update of a navigation system (``ChiselUpdater.process``:
  render of the model, scale, ICP from the running hand-eye estimate with a RANSAC
  fallback, re-projection, noise-adaptive change mask, masked integration), frames / wall
  time; ``batch_update_fps`` is the whole step through ``update_step`` (``chisel update``),
  which adds step-level work that needs every frame first (sequence RANSAC + ICP, the
  hand-eye pass, the multi-view confirmation of the masks);
* ``update_fps_process_stream``: the same streaming step through
  ``ChiselUpdater.process_stream`` (the next frame's render and depth overlap this frame's
  detection and carving on a worker thread; the same model, checked);
* peak resident memory of the process.

* the same streaming step from a whole-CT model (``build_preop_model(..., ct=...)``, the
  CT's signed distance over the grid): ``update_fps_from_ct`` (issue 19: >= 30 too);
  ``update_fps_from_ct_shading``: that step's frames with the simulator's tracking error
  (0.5 mm / 0.5 deg hand-eye) and RGB shaded from the true depth by a light at the lens
  (cos / r^2, gamma 2.2), the poses corrected by the frames' shading
  (``UpdateConfig.shading``, on in the shipped experiments' network rows);
  ``shading_fps_ratio``: its rate over the same frames' without the correction
  (``update_fps_from_ct_sim_tracker``), same run; the ``..._stream`` figures are the same
  two steps through ``process_stream`` (the shading's shift on a thread of its own;
  ``update_shading_stream_same_model`` checks it carves what ``process`` carves).

Every update below grows its change threshold with depth as the shipped experiments do
(``update.change.noise_with_depth`` in ``config/config.yaml``; ``--no-noise-with-depth``:
the library's default, one threshold per frame); with it, the whole-CT stream is timed
again with one threshold per frame (``update_fps_from_ct_fixed_threshold``) and
``noise_with_depth_fps_ratio`` is the rule's rate over that one's (one pass each: +-5 %).

Goals: update_fps >= 30, update_fps_from_ct >= 30 (with the shading too, streaming),
fusion_ratio_vs_open3d >= 1.0, peak_rss_mib <= 4096.
Both fusions are timed best of ``--repeats`` (default 9) alternating passes: Open3D's
figure moves by tens of % from run to run on this machine even when it is idle.
numba runs on its default threading layer, the one users get (``omp`` here: TBB is too
old); ``NUMBA_THREADING_LAYER=workqueue`` measures the other one. ``omp`` spin-waits
and slows down a lot when the CPU is oversubscribed: run alone for figures worth quoting.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import trimesh

from chisel.batch import update_step
from chisel.build import BuildConfig, build_preop_model, preop_bounds
from chisel.change import ChangeConfig
from chisel.core.geometry import Camera, invert_rigid, look_at, rotation_angle_deg
from chisel.core.raycast import MeshRaycaster
from chisel.ct_model import ct_from_mesh
from chisel.depth_source import CallableDepth
from chisel.fusion import integrate
from chisel.io.sequence import Frame
from chisel.model import TsdfModel
from chisel.reports import FrameReport
from chisel.shading import ShadingConfig, log_shading
from chisel.update_config import UpdateConfig
from chisel.updater import ChiselUpdater

sys.path.insert(0, str(Path(__file__).resolve().parent))
from host import cpu_simd, shipped_noise_with_depth  # noqa: E402


def _pose_error(shift_mm: float, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    t = rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(axis * np.radians(angle_deg)).as_matrix()
    T[:3, 3] = t / np.linalg.norm(t) * shift_mm
    return T


def phantom_scene(seed: int, workdir: Path) -> dict:
    """Meshes and camera poses from a generated phantom (1 bite)."""
    out = workdir / "phantom"
    subprocess.run(
        [sys.executable, "-m", "phantoms", "generate", "--seed", str(seed), "--bites", "1",
         "--out", str(out)],
        check=True, capture_output=True,
    )  # fmt: skip
    man = json.loads((out / "phantom.json").read_text())
    meshes = [trimesh.load(out / s["mesh"], force="mesh") for s in man["steps"]]
    c = np.asarray(man["target"]["center_mm"], float)
    n = np.asarray(man["target"]["normal"], float)
    path = np.asarray(man["airway_path_mm"], float)
    # Densify the airway polyline; keep points on the airway side of the target, 6-25 mm away.
    t = np.linspace(0.0, 1.0, 10, endpoint=False)[:, None]
    dense = np.concatenate([a + (b - a) * t for a, b in zip(path[:-1], path[1:], strict=True)])
    d = np.linalg.norm(dense - c, axis=1)
    ok = (d > 6.0) & (d < 25.0) & ((dense - c) @ n > 2.0)
    eyes = dense[ok]
    if len(eyes) < 3:
        raise RuntimeError("phantom: no airway point sees the target from 6-25 mm")
    return {"name": f"phantom seed {seed}", "preop": meshes[0], "step": meshes[1],
            "eyes": eyes, "target": c}  # fmt: skip


def room_scene() -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_updater_scenes import bitten_mesh, tissue_mesh

    tissue = tissue_mesh()
    eyes = np.random.default_rng(0).uniform(-3, 3, (50, 3)) + [0, 0, 2]
    return {"name": "analytic room", "preop": tissue, "step": bitten_mesh(tissue),
            "eyes": eyes, "target": np.array([-3.0, -3.0, 25.0])}  # fmt: skip


def make_poses(scene: dict, n: int, spread_mm: float, rng: np.random.Generator) -> np.ndarray:
    out = []
    for _ in range(n):
        eye = scene["eyes"][rng.integers(len(scene["eyes"]))]
        target = scene["target"] + rng.uniform(-spread_mm, spread_mm, 3)
        out.append(look_at(eye, target, [0.0, 0.0, 1.0] if scene["name"] != "analytic room"
                           else [0.0, -1.0, 0.0]))  # fmt: skip
    return np.stack(out)


def bench_fusion(model0: TsdfModel, cam: Camera, poses: np.ndarray, depths: list, repeats: int):
    """Seconds per frame of (ours, Open3D): each the best of ``repeats`` passes over the
    frames, the passes of the two alternating so that a slow spell of the machine hits
    both (Open3D's figure moves by tens of % between runs even on an idle machine)."""
    import open3d as o3d

    K = o3d.core.Tensor(cam.K, o3d.core.float64)
    trunc_mult = model0.trunc_mm / model0.voxel_size_mm
    imgs = [o3d.t.geometry.Image(o3d.core.Tensor(np.nan_to_num(d, nan=0.0))) for d in depths]
    exts = [o3d.core.Tensor(invert_rigid(T), o3d.core.float64) for T in poses]
    ours, theirs = [], []
    for _ in range(repeats):
        m = model0.copy()
        t0 = time.perf_counter()
        for T, d in zip(poses, depths, strict=True):
            integrate(m, cam, T, d)
        ours.append(time.perf_counter() - t0)
        vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(o3d.core.float32, o3d.core.float32),
            attr_channels=((1), (1)),
            voxel_size=model0.voxel_size_mm,
            block_resolution=8,
            block_count=100_000,
        )
        t0 = time.perf_counter()
        for img, ext in zip(imgs, exts, strict=True):
            blocks = vbg.compute_unique_block_coordinates(
                img, K, ext, depth_scale=1.0, depth_max=200.0, trunc_voxel_multiplier=trunc_mult
            )
            vbg.integrate(blocks, img, K, ext, depth_scale=1.0, depth_max=200.0,
                          trunc_voxel_multiplier=trunc_mult)  # fmt: skip
        theirs.append(time.perf_counter() - t0)
    return min(ours) / len(poses), min(theirs) / len(poses)


def _shaded_rgb(depth_mm: np.ndarray, cam: Camera) -> np.ndarray:
    """uint8 RGB of a matte surface lit from the lens: radiance cos / r^2, its median at
    40 % of full scale, gamma 2.2; black where the depth has no surface."""
    log_rad, ok = log_shading(depth_mm, cam.rays_cam())
    rad = np.exp(log_rad - np.median(log_rad[ok])) * 0.4 if ok.any() else np.zeros(cam.shape)
    v = np.where(ok, np.clip(rad, 0.0, 1.0) ** (1.0 / 2.2) * 255.0, 0.0)
    return np.repeat(np.rint(v).astype(np.uint8)[..., None], 3, axis=-1)


def _stream_step(
    model: TsdfModel, cam: Camera, source: CallableDepth, cfg: UpdateConfig,
    frames: list[Frame], overlap: bool = False,
) -> tuple[ChiselUpdater, list[FrameReport], float]:  # fmt: skip
    """One streaming step (``process`` frame by frame, or ``process_stream`` when
    ``overlap``): the updater after it, its reports and the wall seconds it took."""
    upd = ChiselUpdater(model, cam, source, cfg)
    upd.begin_step()
    t0 = time.perf_counter()
    reports = list(upd.process_stream(frames)) if overlap else [upd.process(f) for f in frames]
    return upd, reports, time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scene", choices=("phantom", "room"), default="phantom")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--voxel-mm", type=float, default=0.5)
    ap.add_argument("--preop-frames", type=int, default=60)
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument(
        "--frame-ransac",
        choices=("always", "until_prior"),
        default=UpdateConfig().frame_ransac,
        help="UpdateConfig.frame_ransac for every update below (default: the config's)",
    )
    ap.add_argument(
        "--noise-with-depth",
        action=argparse.BooleanOptionalAction,
        default=shipped_noise_with_depth(),
        help="ChangeConfig.noise_with_depth for every update below (default: config/config.yaml's)",
    )
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        scene = phantom_scene(args.seed, Path(tmp)) if args.scene == "phantom" else room_scene()
    cam = Camera.from_fov(args.width, args.height, 80.0)
    import numba

    warnings.filterwarnings("ignore", message="The TBB threading layer requires")

    print(f"scene: {scene['name']}")
    print(f"cpu_threads: {numba.get_num_threads()}")
    print(f"cpu_simd: {cpu_simd()}")
    print(f"image: {args.width}x{args.height}")

    # --- preoperative fusion, ours vs Open3D on the same depth maps
    pre = make_poses(scene, args.preop_frames, 10.0, rng)
    rc_pre = MeshRaycaster.from_trimesh(scene["preop"])
    depths = [rc_pre.render_depth(cam, T) for T in pre]
    print(f"raycast_backend: {rc_pre.backend}")
    cfg = BuildConfig(voxel_size_mm=args.voxel_mm, trunc_mm=4 * args.voxel_mm)
    lo, hi = preop_bounds(scene["preop"], pre, cfg)
    model0 = TsdfModel.empty(lo, hi, cfg.voxel_size_mm, cfg.trunc_mm)
    integrate(model0.copy(), cam, pre[0], depths[0])  # JIT warm-up
    ours, o3d_t = bench_fusion(model0, cam, pre, depths, args.repeats)
    print(f"numba_threading_layer: {numba.threading_layer()}")
    print(f"model_voxels: {'x'.join(map(str, model0.shape))}")
    print(f"fusion_ms_per_frame: {ours * 1000:.2f}")
    print(f"open3d_fusion_ms_per_frame: {o3d_t * 1000:.2f}")
    print(f"fusion_ratio_vs_open3d: {o3d_t / ours:.2f}")
    model = model0.copy()
    for T, d in zip(pre, depths, strict=True):
        integrate(model, cam, T, d)

    # --- one surgical step: monocular-like depth, tracked poses with hand-eye error + jitter
    true = make_poses(scene, args.frames, 4.0, rng)
    E = _pose_error(2.0, 2.0, rng)
    tracked = np.stack([T @ E @ _pose_error(0.2, 0.2, rng) for T in true])
    rc_step = MeshRaycaster.from_trimesh(scene["step"])
    frames = [
        Frame(
            i,
            tracked[i],
            depth_mm=rc_step.render_depth(cam, true[i]),
            T_world_from_cam_true=true[i],
        )
        for i in range(args.frames)
    ]
    ucfg = UpdateConfig(
        frame_ransac=args.frame_ransac, change=ChangeConfig(noise_with_depth=args.noise_with_depth)
    )
    print(f"frame_ransac: {args.frame_ransac}")
    print(f"noise_with_depth: {args.noise_with_depth}")
    k = 0.0371  # unknown monocular scale
    source = CallableDepth(lambda f: f.depth_mm * k)
    update_step(model, cam, frames[:5], source, ucfg)  # warm-up (JIT, Open3D)
    t0 = time.perf_counter()
    new, report = update_step(model, cam, frames, source, ucfg)
    batch_s = time.perf_counter() - t0
    used = [f for f in report.frames if f.used]
    # Corrections beyond the tracking accuracy are not applied (tracked pose, scale only).
    applied = [f for f in used if f.registration and "rejected" not in f.registration]
    errs = []
    for f in applied:
        C = np.asarray(f.registration["T_model_from_est"])
        D = invert_rigid(true[f.index]) @ C @ tracked[f.index]
        errs.append((np.linalg.norm(D[:3, 3]), rotation_angle_deg(D[:3, :3]), abs(f.scale * k - 1)))
    errs_a = np.array(errs) if errs else np.full((1, 3), np.nan)
    print(f"update_frames_used: {len(used)}/{args.frames}")
    print(f"update_frames_registered: {len(applied)}/{len(used)}")
    print(f"update_changed_fraction_mean: {np.mean([f.changed_fraction for f in used]):.4f}")
    print(f"registration_error_mm_mean: {errs_a[:, 0].mean():.3f}")
    print(f"registration_error_deg_mean: {errs_a[:, 1].mean():.3f}")
    print(f"scale_error_pct_max: {100 * errs_a[:, 2].max():.3f}")

    print(f"batch_update_fps: {args.frames / batch_s:.1f}")
    # The streaming update from a whole-CT model (chisel build --from-ct: the CT's signed
    # distance over the grid, the sweep adding weight): issue 19's goal, >= 30 frames/s.
    ct_model = build_preop_model(
        None, cam, pre,
        # As the workflow (config model.max_miss_fraction): the phantom's block is cut
        # close to the sinus, some rays of a preop frame leave it.
        BuildConfig(voxel_size_mm=args.voxel_mm, trunc_mm=4 * args.voxel_mm, max_miss_fraction=0.75),
        ct=ct_from_mesh(scene["preop"], "preop mesh"),
    )  # fmt: skip
    _, streamed_ct, stream_ct_s = _stream_step(ct_model, cam, source, ucfg, frames)
    print(f"update_frames_used_streaming_ct: {sum(r.used for r in streamed_ct)}/{args.frames}")
    print(f"update_fps_from_ct: {args.frames / stream_ct_s:.1f}")
    if args.noise_with_depth:
        # The peer of the shipped rule: the same frames with one threshold per frame.
        fixed = dataclasses.replace(ucfg, change=ChangeConfig(noise_with_depth=False))
        _, _, fixed_s = _stream_step(ct_model, cam, source, fixed, frames)
        print(f"update_fps_from_ct_fixed_threshold: {args.frames / fixed_s:.1f}")
        print(f"noise_with_depth_fps_ratio: {fixed_s / stream_ct_s:.2f}")
    # The shading's step: the simulator's tracker (a 0.5 mm / 0.5 deg hand-eye error,
    # within the shift search's +-16 px; the 2 mm / 2 deg above is beyond it) and shaded
    # RGB, timed with and without the correction on the same frames.
    E_sim = _pose_error(0.5, 0.5, rng)
    sim_frames = [
        dataclasses.replace(
            f, T_world_from_cam=f.T_world_from_cam_true @ E_sim @ _pose_error(0.2, 0.1, rng),
            rgb=_shaded_rgb(f.depth_mm, cam),
        )
        for f in frames
    ]  # fmt: skip
    _, _, plain_s = _stream_step(ct_model, cam, source, ucfg, sim_frames)
    scfg = dataclasses.replace(ucfg, shading=ShadingConfig(align_by_shading=True))
    upd_s, _, shading_s = _stream_step(ct_model, cam, source, scfg, sim_frames)
    found = upd_s.end_step().pose_correction or {"frames_found": 0}
    print(f"shading_frames_found: {found['frames_found']}/{args.frames}")
    print(f"update_fps_from_ct_sim_tracker: {args.frames / plain_s:.1f}")
    print(f"update_fps_from_ct_shading: {args.frames / shading_s:.1f}")
    print(f"shading_fps_ratio: {plain_s / shading_s:.2f}")
    # The same two through process_stream: with the correction, the previous frame's
    # shift is measured on a thread of its own while this frame is rendered.
    _, _, plain_stream_s = _stream_step(ct_model, cam, source, ucfg, sim_frames, overlap=True)
    upd_ss, _, shading_stream_s = _stream_step(
        ct_model, cam, source, scfg, sim_frames, overlap=True
    )
    same = upd_ss.model.tsdf.tobytes() == upd_s.model.tsdf.tobytes()
    print(f"update_shading_stream_same_model: {same}")
    print(f"update_fps_from_ct_sim_tracker_stream: {args.frames / plain_stream_s:.1f}")
    print(f"update_fps_from_ct_shading_stream: {args.frames / shading_stream_s:.1f}")
    print(f"shading_stream_fps_ratio: {plain_stream_s / shading_stream_s:.2f}")
    upd, streamed, stream_s = _stream_step(model, cam, source, ucfg, frames)
    print(f"update_frames_used_streaming: {sum(r.used for r in streamed)}/{args.frames}")
    fell_back = sum(1 for r in streamed if r.registration and "fallback" in r.registration)
    print(f"update_frames_tracked_pose_streaming: {fell_back}/{args.frames}")
    # The same step through process_stream: the next frame's render of M_t and depth
    # estimate (here a ray cast) overlap this frame's detection and carving.
    upd_o, overlapped, overlap_s = _stream_step(model, cam, source, ucfg, frames, overlap=True)
    same = upd_o.model.tsdf.tobytes() == upd.model.tsdf.tobytes()
    print(f"update_process_stream_same_model: {same} ({len(overlapped)} frames)")
    print(f"update_fps_process_stream: {args.frames / overlap_s:.1f}")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"peak_rss_mib: {peak:.0f}")
    print(f"update_fps: {args.frames / stream_s:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
