"""CLI: ``chisel ct-surface | build | update | mesh | render-depth`` (the updater's I/O).

Thin wrappers: they read files, call the method (:mod:`chisel.build`, :mod:`chisel.batch`), and write results
atomically. Units: millimetres; poses ``T_world_from_cam`` (world = CT frame).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from chisel.cli.args import Output, finite_float
from chisel.core.atomic import atomic_path, atomic_paths
from chisel.core.errors import InvalidInputError

log = logging.getLogger(__name__)

_FMT = argparse.RawDescriptionHelpFormatter

_FORMATS = """\
Formats and units:
  sequence folder  see chisel.io.sequence (sequence.json, poses.txt = tracked T_world_from_cam
                   row-major 4x4 in mm, rgb/*.png, depth/*.npy float32 z-depth mm, 0 = invalid)
  model file       .npz, format "endoscopic-chisel/model" version 1: tsdf (X,Y,Z) float32
                   in [-1, 1] (signed distance / trunc_mm), weight (X,Y,Z) float32,
                   optional color (X,Y,Z,3) uint8, T_world_from_voxel (4,4) mm,
                   voxel_size_mm, trunc_mm, step (see docs/updater.md)
  CT segmentation  surface mesh (.ply/.stl/.obj/.off, world mm) or NIfTI (.nii/.nii.gz):
                   intensity CT contoured at -480 HU, label volumes at 0.5 (tissue = label > 0),
                   mapped to world mm with the NIfTI affine
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``chisel ct-surface | build | update | mesh | render-depth``."""
    _add_ct_surface(sub)
    _add_build(sub)
    _add_update(sub)
    _add_mesh(sub)
    _add_render_depth(sub)


def _parser(
    sub: argparse._SubParsersAction, name: str, summary: str, description: str
) -> argparse.ArgumentParser:
    """A command's parser (``summary``: its line in ``chisel --help``); its description
    ends with the formats and units."""
    parser: argparse.ArgumentParser = sub.add_parser(
        name, help=summary, description=description + _FORMATS, formatter_class=_FMT
    )
    return parser


def _add_mesh_out(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--out", required=True, type=Path, help="output mesh (.ply/.stl/.obj)", action=Output
    )


def _add_allow_outside_sequence(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--allow-outside-sequence",
        action="store_true",
        help="read a sequence whose files or subfolders are links leading out of its folder "
        "(frames kept on another disk); refused by default, so that a sequence cannot make "
        "the program read another patient's or the system's files",
    )


def _add_ct_surface(sub: argparse._SubParsersAction) -> None:
    p = _parser(
        sub,
        "ct-surface",
        summary="turn a CT segmentation (NIfTI or mesh) into a surface mesh in world mm",
        description="Contour a CT volume (marching cubes) or re-save a mesh, in world mm.\n\n",
    )
    p.add_argument("--ct", required=True, type=Path, help="NIfTI volume or surface mesh")
    _add_mesh_out(p)
    p.add_argument(
        "--kind",
        choices=("auto", "intensity", "label"),
        default="auto",
        help="NIfTI contents: intensity HU, labels (0 = air), or auto (default)",
    )
    p.add_argument(
        "--iso-level",
        type=finite_float,
        default=None,
        help="iso-level (HU for intensity, default -480; default 0.5 for labels)",
    )
    p.set_defaults(func=_cmd_ct_surface)


def _add_build(sub: argparse._SubParsersAction) -> None:
    p = _parser(
        sub,
        "build",
        summary="build the preoperative TSDF model from the CT (whole CT or the preop sweep)",
        description="Two builds (the model file records which, field `build`):\n"
        "  --from-ct CT   (default in the workflow) every voxel the CT covers takes the CT's "
        "signed distance\n"
        "                 (truncated, normalised, initial weight --ct-weight), so surfaces no "
        "preop frame\n"
        "                 sees are in the model; the preop sweep adds weight and colour where "
        "it sees.\n"
        "                 CT = NIfTI label or intensity volume, or a closed segmentation mesh.\n"
        "  --surface CT   the paper's build: the CT surface rendered at every tracked preop "
        "pose, fused\n"
        "                 (Curless-Levoy, free space carved); nothing behind what the sweep "
        "sees.\n\n",
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--surface",
        "--ct",
        dest="surface",
        type=Path,
        help="sweep-only build (the paper's) from this CT segmentation: mesh or NIfTI",
    )
    which.add_argument(
        "--from-ct",
        dest="from_ct",
        type=Path,
        help="whole-CT build from this NIfTI volume (label or intensity) or closed mesh",
    )
    p.add_argument(
        "--kind",
        choices=("auto", "intensity", "label"),
        default="auto",
        help="--from-ct NIfTI contents: intensity HU, labels (0 = air), or auto (default)",
    )
    p.add_argument(
        "--iso-level",
        type=finite_float,
        default=None,
        help="--from-ct intensity iso-level, HU (default -480)",
    )
    p.add_argument(
        "--tissue-labels",
        type=int,
        nargs="+",
        default=None,
        help="--from-ct label volume: the labels that are tissue (default 1 2; 0 = air; any "
        "other label is refused)",
    )
    p.add_argument(
        "--max-miss-fraction",
        type=finite_float,
        default=0.05,
        help="--from-ct: refuse the CT when, in any preop frame, more than this fraction of "
        "the rays leave the CT's grid without meeting tissue (0.05)",
    )
    p.add_argument(
        "--ct-weight",
        type=finite_float,
        default=1.0,
        help="--from-ct: initial weight of every voxel the CT covers (1.0)",
    )
    p.add_argument("--sequence", required=True, type=Path, help="preoperative sequence folder")
    _add_allow_outside_sequence(p)
    p.add_argument(
        "--out", required=True, type=Path, help="output model file (.npz)", action=Output
    )
    p.add_argument("--voxel-size-mm", type=finite_float, default=0.5, help="voxel edge, mm (0.5)")
    p.add_argument(
        "--trunc-mm", type=finite_float, default=2.0, help="truncation distance, mm (2.0)"
    )
    p.add_argument("--margin-mm", type=finite_float, default=3.0, help="margin around the data, mm")
    p.add_argument("--color", action="store_true", help="fuse colour from the sequence's RGB")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_build)


def _add_update(sub: argparse._SubParsersAction) -> None:
    p = _parser(
        sub,
        "update",
        summary="apply one surgical step (a sequence) to a model: detect change, carve it",
        description="Detect the tissue removed in a new sequence and carve it into the model "
        "(the paper's masked TSDF update). Writes the new model and a JSON report "
        "(frames used/skipped, registration transform/fitness, changed-pixel fraction). "
        "The input model file is never modified; on any error nothing is written.\n\n",
    )
    p.add_argument("--model", required=True, type=Path, help="model of the previous step")
    p.add_argument("--sequence", required=True, type=Path, help="sequence of this step")
    _add_allow_outside_sequence(p)
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        help="updated model file (.npz)",
        action=Output,
        sidecar=_default_report,
    )
    p.add_argument(
        "--report", type=Path, default=None, help="JSON report (default OUT.json)", action=Output
    )
    p.add_argument(
        "--masks",
        type=Path,
        default=None,
        help="optional .npz of the change masks (N, H, W)",
        action=Output,
    )
    p.add_argument(
        "--depth-source",
        default="gt",
        help="gt (the sequence's depth, mm) | sequence:PATH (depth maps of another "
        "sequence folder) | network:CHECKPOINT (chisel.depth network, relative depth) | "
        "change-aware:CHECKPOINT (frame + the model's render at the tracked pose -> mm)",
    )
    p.add_argument(
        "--config",
        type=Path,
        default=None,
        help="YAML file of update parameters (the fields of chisel.update_config.UpdateConfig: "
        "change: {...}, registration: {...} and the top-level ones); the flags below "
        "override it, and what neither sets keeps its default",
    )
    from chisel.core.config import add_config_arguments
    from chisel.update_config import UpdateConfig

    group = p.add_argument_group(
        "update parameters (generated from UpdateConfig, ChangeConfig and RegistrationConfig)"
    )
    add_config_arguments(group, UpdateConfig, aliases={"register": ("--registration",)})
    p.add_argument(
        "--ct",
        type=Path,
        default=None,
        help="the CT the model was built on (NIfTI or mesh): refused when the model "
        "records another CT's content hash (whole-CT builds)",
    )
    p.add_argument("--max-frames", type=int, default=None, help="use the first N frames only")
    p.add_argument(
        "--depth-noise-mm",
        type=finite_float,
        default=0.0,
        help="robustness study: add Gaussian noise of this std (mm at the depth's own "
        "scale) to every estimate",
    )
    p.add_argument("--depth-noise-seed", type=int, default=0, help="seed of --depth-noise-mm")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_update)


def _add_mesh(sub: argparse._SubParsersAction) -> None:
    p = _parser(
        sub,
        "mesh",
        summary="extract the surface of a model (marching cubes at D = 0), world mm",
        description="Marching cubes at D = 0 over observed voxels; vertices in world mm.\n\n",
    )
    p.add_argument("--model", required=True, type=Path, help="model file (.npz)")
    _add_mesh_out(p)
    p.set_defaults(func=_cmd_mesh)


def _add_render_depth(sub: argparse._SubParsersAction) -> None:
    p = _parser(
        sub,
        "render-depth",
        summary="render z-depth of a model or mesh at every pose of a sequence",
        description="Render z-depth (mm) of a model's surface (--model) or of a mesh (--mesh) "
        "at the tracked poses of a sequence; writes a sequence folder with the same "
        "camera, poses, RGB and masks, and the rendered depth.\n\n",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="model file (.npz)")
    src.add_argument("--mesh", type=Path, help="mesh or CT segmentation (world mm)")
    p.add_argument("--sequence", required=True, type=Path, help="sequence folder (poses)")
    _add_allow_outside_sequence(p)
    p.add_argument("--out", required=True, type=Path, help="output sequence folder", action=Output)
    p.add_argument("--true-poses", action="store_true", help="render at the true poses")
    p.set_defaults(func=_cmd_render_depth)


def _progress(disable: bool, desc: str):  # noqa: ANN202
    from tqdm import tqdm

    return lambda it: tqdm(it, desc=desc, disable=disable, unit="frame", leave=False)


def _default_report(args: argparse.Namespace) -> Path | None:
    """The report ``update`` writes beside the model when no ``--report`` is given."""
    return None if args.report is not None else args.out.with_suffix(".json")


def _save_mesh(mesh, path: Path) -> None:  # noqa: ANN001 - trimesh.Trimesh
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in ("ply", "stl", "obj", "off", "glb"):
        raise InvalidInputError(path, f"unknown mesh type {path.suffix!r}; use .ply/.stl/.obj")
    with atomic_path(path) as tmp:
        mesh.export(str(tmp), file_type=suffix)


def _cmd_ct_surface(args: argparse.Namespace) -> int:
    from chisel.io.ct import load_ct_surface

    mesh = load_ct_surface(args.ct, args.kind, args.iso_level)
    _save_mesh(mesh, args.out)
    log.info("surface: %d vertices, %d faces -> %s", len(mesh.vertices), len(mesh.faces), args.out)
    return 0


def _read_ct_arrays(path: Path, kind: str = "auto"):  # noqa: ANN202 - CtVolume or Trimesh
    """A CT file as a :class:`chisel.io.ct.CtVolume` (NIfTI/NRRD, LPS world mm) or a mesh."""
    import trimesh

    from chisel.io import ct as ct_io
    from chisel.io.meshfile import READABLE_MESH_SUFFIXES

    if not path.is_file():
        raise InvalidInputError(path, "CT file is missing")
    name = path.name.lower()
    if name.endswith(ct_io.VOLUME_SUFFIXES):
        return ct_io.read_ct_volume(path, kind)  # type: ignore[arg-type]
    if name.endswith(READABLE_MESH_SUFFIXES):
        mesh = ct_io.load_ct_surface(path)
        if not isinstance(mesh, trimesh.Trimesh):
            raise InvalidInputError(path, "not a triangle mesh")
        return mesh
    raise InvalidInputError(
        path, f"unknown CT type; expected one of {ct_io.VOLUME_SUFFIXES + READABLE_MESH_SUFFIXES}"
    )


def _read_ct(args: argparse.Namespace):  # noqa: ANN202 - chisel.ct_model.CtInput
    from chisel.ct_model import TISSUE_LABELS, ct_from_mesh, ct_from_volume
    from chisel.io.ct import CtVolume

    got = _read_ct_arrays(args.from_ct, args.kind)
    if isinstance(got, CtVolume):
        labels = TISSUE_LABELS if args.tissue_labels is None else tuple(args.tissue_labels)
        if 0 in labels:
            raise InvalidInputError("--tissue-labels", "label 0 is air, not tissue")
        return ct_from_volume(
            got.data, got.T_world_from_voxel, got.kind, args.iso_level, labels, str(args.from_ct)
        )
    return ct_from_mesh(got, source=str(args.from_ct))


def _ct_fingerprint(path: Path) -> str:
    """The content hash a whole-CT build records for this CT file (see chisel.ct_model)."""
    from chisel.ct_model import fingerprint_arrays
    from chisel.io.ct import CtVolume

    got = _read_ct_arrays(path)
    if isinstance(got, CtVolume):
        return fingerprint_arrays(got.data, got.T_world_from_voxel)
    return fingerprint_arrays(
        np.asarray(got.vertices, dtype=np.float64), np.asarray(got.faces, dtype=np.int64)
    )


def _cmd_build(args: argparse.Namespace) -> int:
    from chisel.build import BuildConfig, build_preop_model
    from chisel.io.ct import load_ct_surface
    from chisel.io.sequence import Sequence

    cfg = BuildConfig(
        voxel_size_mm=args.voxel_size_mm,
        trunc_mm=args.trunc_mm,
        margin_mm=args.margin_mm,
        color=args.color,
        ct_weight=args.ct_weight,
        max_miss_fraction=args.max_miss_fraction,
    )
    seq = Sequence(args.sequence, allow_outside=args.allow_outside_sequence)
    ct = _read_ct(args) if args.from_ct is not None else None
    surface = None if ct is not None else load_ct_surface(args.surface)
    if args.color and not seq.has_rgb:
        raise InvalidInputError(args.sequence, "--color needs RGB in the sequence, it has none")
    rgbs = (seq.rgb(i) for i in range(len(seq))) if args.color else None
    masks = [seq.mask(i) for i in range(len(seq))]
    model = build_preop_model(
        surface,
        seq.camera,
        seq.poses,
        cfg,
        rgbs=rgbs,
        masks=masks,
        progress=_progress(args.no_progress, "fuse"),
        ct=ct,
    )
    model.save(args.out)
    log.info(
        "model (%s build) %s voxels of %.3g mm -> %s",
        model.build,
        model.shape,
        model.voxel_size_mm,
        args.out,
    )
    return 0


class _NoisyDepth:
    """A depth source plus seeded Gaussian noise (robustness study)."""

    def __init__(self, source, std: float, seed: int) -> None:  # noqa: ANN001
        self.source = source
        self.std = float(std)
        self.seed = int(seed)
        self.is_metric = bool(getattr(source, "is_metric", False))

    def __call__(self, frame):  # noqa: ANN001, ANN204
        d = np.asarray(self.source(frame), dtype=np.float32)
        rng = np.random.default_rng([self.seed, int(frame.index)])
        return (d + rng.normal(0.0, self.std, d.shape)).astype(np.float32)


def _cmd_update(args: argparse.Namespace) -> int:
    from chisel.batch import update_step
    from chisel.core.config import config_from_args, load_config_file
    from chisel.depth_source import depth_source_from_spec
    from chisel.io.sequence import Sequence
    from chisel.model import TsdfModel
    from chisel.update_config import UpdateConfig

    if args.max_frames is not None and args.max_frames < 1:
        raise InvalidInputError("--max-frames", f"must be >= 1, got {args.max_frames}")
    if args.depth_noise_mm < 0:
        raise InvalidInputError("--depth-noise-mm", f"must be >= 0, got {args.depth_noise_mm}")
    base = UpdateConfig() if args.config is None else load_config_file(UpdateConfig, args.config)
    cfg = config_from_args(UpdateConfig, args, base)
    model = TsdfModel.load(args.model)
    if args.ct is not None:
        if not model.ct_sha256:
            raise InvalidInputError(
                "--ct",
                f"{args.model} records no CT ({model.build} build): cannot check it was "
                f"built on {args.ct}",
            )
        if _ct_fingerprint(args.ct) != model.ct_sha256:
            raise InvalidInputError(
                "--ct",
                f"{args.model} was built on another CT than {args.ct} (content hashes differ)",
            )
    seq = Sequence(args.sequence, allow_outside=args.allow_outside_sequence)
    source = depth_source_from_spec(args.depth_source, seq)
    if args.depth_noise_mm > 0:
        source = _NoisyDepth(source, args.depth_noise_mm, args.depth_noise_seed)
    n = len(seq) if args.max_frames is None else min(args.max_frames, len(seq))
    needs_rgb = getattr(source, "needs_rgb", not getattr(source, "is_metric", False))
    for wanted, key in (
        (cfg.shading.align_by_shading, "update.shading.align_by_shading"),
        (cfg.odometry.smooth_by_odometry, "update.odometry.smooth_by_odometry"),
    ):
        if not wanted:
            continue
        # Without this the frames of a metric source were read without their RGB, and the
        # correction was silently skipped.
        if not seq.has_rgb:
            raise InvalidInputError(seq.path, f"{key} needs the frames' RGB; it has none")
        needs_rgb = True
    frames = [seq.frame(i, rgb=needs_rgb or model.color is not None) for i in range(n)]
    new_model, report = update_step(
        model,
        seq.camera,
        frames,
        source,
        cfg,
        progress=_progress(args.no_progress, "update"),
        keep_maps=args.masks is not None,
    )
    out_report = args.report or _default_report(args)
    rep = report.to_dict()
    rep.update(
        {
            "model_in": str(args.model),
            "sequence": str(args.sequence),
            "depth_source": args.depth_source,
            "frames_considered": n,
        }
    )
    # The outputs are staged, then moved into place together with Ctrl-C held: after a
    # failure or an interrupt they are all new or all as they were. The model moves last,
    # so even a SIGKILL between two moves leaves no new model without its report.
    masks_out = [] if args.masks is None else [args.masks]
    finals = [out_report, *masks_out, args.out]
    suffixes = [".json", *(".npz" for _ in masks_out), ".npz"]
    with atomic_paths(*finals, suffixes=suffixes) as temps:
        temps[0].write_text(json.dumps(rep, indent=2) + "\n", encoding="utf-8")
        if args.masks is not None:
            idx = np.array([f.index for f in report.frames], dtype=np.int64)
            shape = seq.camera.shape
            masks = np.stack(
                [f.mask if f.mask is not None else np.zeros(shape, bool) for f in report.frames]
            )
            used = np.array([f.used for f in report.frames], dtype=bool)
            # Each mask lies in the image of the pose the frame's model render was made at:
            # the tracked pose, corrected by the shading when that option is on (scored at
            # the tracked pose, a corrected step's masks met their truth in another view).
            pose_of = {f.index: f.T_world_from_cam for f in frames}
            poses = np.stack(
                [
                    pose_of[f.index] if f.mask_T_world_from_cam is None else f.mask_T_world_from_cam
                    for f in report.frames
                ]
            )
            with open(temps[1], "wb") as fh:
                np.savez_compressed(
                    fh, frame_index=idx, masks=masks, used=used, T_world_from_cam=poses
                )
        new_model.save(temps[-1])
    log.info("step %d: %d/%d frames used -> %s", report.step, len(report.frames_used), n, args.out)
    return 0


def _cmd_mesh(args: argparse.Namespace) -> int:
    from chisel.mesh import extract_mesh
    from chisel.model import TsdfModel

    mesh = extract_mesh(TsdfModel.load(args.model))
    _save_mesh(mesh, args.out)
    log.info("mesh: %d vertices, %d faces -> %s", len(mesh.vertices), len(mesh.faces), args.out)
    return 0


def _cmd_render_depth(args: argparse.Namespace) -> int:
    from chisel.core.raycast import MeshRaycaster
    from chisel.io.ct import load_ct_surface
    from chisel.io.sequence import Frame, Sequence, SequenceWriter
    from chisel.model import TsdfModel
    from chisel.render import ModelRenderer

    seq = Sequence(args.sequence, allow_outside=args.allow_outside_sequence)
    if args.model is not None:
        render = ModelRenderer(TsdfModel.load(args.model)).render
    else:
        render = MeshRaycaster.from_trimesh(load_ct_surface(args.mesh)).render_depth
    if args.true_poses and seq.true_poses is None:
        raise InvalidInputError(args.sequence, "--true-poses: the sequence has no true poses")
    meta = {
        "source": "chisel render-depth",
        "rendered_from": str(args.model or args.mesh),
        "input_sequence": str(args.sequence),
        "poses_rendered": "true" if args.true_poses else "tracked",
        "input_meta": seq.meta,
    }
    with SequenceWriter(args.out, seq.camera, meta, seq.camera_mask, seq.undistorted) as w:
        for i in range(len(seq)):
            f = seq.frame(i, depth=False)
            T = f.T_world_from_cam_true if args.true_poses else f.T_world_from_cam
            assert T is not None  # --true-poses: the sequence's true poses were checked above
            w.add(
                Frame(
                    index=i,
                    T_world_from_cam=f.T_world_from_cam,
                    rgb=f.rgb,
                    depth_mm=render(seq.camera, T),
                    mask=seq.mask(i) if seq.has_mask else None,
                    T_world_from_cam_true=f.T_world_from_cam_true,
                )
            )
    return 0
