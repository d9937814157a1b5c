"""``chisel import video|images|reference``: real data -> sequence folders."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from chisel.cli.args import Output, finite_float
from chisel.io.import_frames import FrameConfig, FrameFiles, import_images, import_video
from chisel.io.import_poses import PoseConfig, read_transform
from chisel.io.import_reference import import_reference
from chisel.io.undistort import Circle

log = logging.getLogger(__name__)

_FORMATS = """\
Output: a sequence folder (README.md, "On-disk contracts"): poses T_world_from_cam in mm, OpenCV camera
axes (+x right, +y down, +z forward), frames undistorted to a pinhole camera (zero
distortion) unless --no-undistort, the endoscope's field stop as camera_mask.png.

Poses (--poses), one per frame or with timestamps:
  N x 16     one row-major 4x4 per line (spaces or commas)
  4-column   N blocks of 4 lines (blank lines and # comments allowed)
  TUM        'timestamp tx ty tz qx qy qz qw' (seconds, quaternion scalar last)
  .npy       (N, 4, 4) or (N, 16) float array (never unpickled)
  A pose of NaNs means tracking was lost for that sample.
  Translations in --pose-units (mm or m; converted to mm). The camera pose is
    T_world_from_cam = T_world_from_tracker @ P_i @ T_marker_from_cam
  with P_i from the file, --hand-eye = T_marker_from_cam (the camera in the tracked
  marker's frame) and --world-from-tracker = T_world_from_tracker (tracker -> CT
  registration), both 4x4 (.npy or 16 numbers of text) in --pose-units.

Matching (--match):
  index      frame i takes pose i; the frame and pose counts must be equal
  timestamp  frame i at time --frame-times[i] (CSV, seconds, last column) or
             --time-offset-s + i / fps; then --interp nearest (the nearest valid sample
             within --tolerance-s) or --interp slerp (rotation SLERP + linear translation
             between the samples just before and after, each within --tolerance-s)

Calibration (--calib): OpenCV FileStorage .yaml/.xml (camera_matrix,
distortion_coefficients, image_width, image_height), ROS camera_info .yaml, or .json
({"width", "height", "K" or fx/fy/cx/cy, "dist"}); it must be for the frames'
resolution (or --rescale-intrinsics for the same aspect ratio).

Field stop (circular endoscope image): fitted to the bright region by default (or
--field-stop none, --field-stop-circle CX,CY,R in raw pixels, --camera-mask PNG on the
raw grid), shrunk by --mask-margin-px.

Optional per frame, one file per source frame in natural name order, raw image grid:
  --depth DIR  z-depth .npy (float) or 16-bit .png, times --depth-scale-mm -> mm
  --masks DIR  PNG, 255 = use the pixel (or --mask-invert: 255 = tool/blood, exclude)
"""

_REFERENCE = """\
Imports the dataset layout of the reference implementation (Mangulabnan et al.,
github.com/janemilym/ct-update): input.json with "intrinsics": "fx,fy,cx,cy",
"preop_data": {...}, "steps": n and one entry "1".."n" per surgical step, each with
"base_dir" (relative to input.json's folder if not absolute), optional "img_dir"
(default images/, *.jpg), "poses" (default trajectories.npy: (N, 4, 4)
T_world_from_cam, translations in --pose-units), "seg" (a mesh), undistorted_mask.bmp,
and for the steps depths/*.npy (monocular estimates; --with-depth, scaled by
--depth-scale-mm to mm).

Writes OUT/preop/, OUT/step_<i>/ (sequence folders: frames already undistorted, zero
distortion, camera_mask from undistorted_mask.bmp), OUT/<part>_surface.<ext> (copied
seg meshes) and OUT/reference.json (the list). All or nothing.

Every path input.json names must lie inside input.json's folder (links resolved) unless
--allow-outside-manifest; each file is read as its kind first (the seg mesh must parse
as a mesh and is written anew, poses must be N 4x4 numbers, images must decode).
"""


def _transform(path: str | None, what: str):
    return None if path is None else read_transform(Path(path), what)


def _run_frames(args: argparse.Namespace) -> int:
    pose_cfg = PoseConfig(
        format=args.pose_format,
        units=args.pose_units,
        match=args.match,
        interpolation=args.interp,
        time_tolerance_s=args.tolerance_s,
        fps=args.fps,
        frame_time_offset_s=args.time_offset_s,
        T_marker_from_cam=_transform(args.hand_eye, "hand-eye T_marker_from_cam"),
        T_world_from_tracker=_transform(args.world_from_tracker, "T_world_from_tracker"),
        drop_unposed=args.drop_unposed,
        check_units=not args.no_units_check,
    )
    frame_cfg = FrameConfig(
        undistort=not args.no_undistort,
        alpha=args.alpha,
        field_stop=args.field_stop,
        field_stop_circle=None
        if args.field_stop_circle is None
        else Circle.parse(args.field_stop_circle, "--field-stop-circle"),
        mask_margin_px=args.mask_margin_px,
        start=args.start,
        stop=args.stop,
        step=args.step,
        depth_scale_mm=args.depth_scale_mm,
        mask_invert=args.mask_invert,
        rescale_intrinsics=args.rescale_intrinsics,
    )
    fn = import_video if args.kind == "video" else import_images
    report = fn(
        args.source,
        args.poses,
        args.calib,
        args.out,
        pose_cfg=pose_cfg,
        frame_cfg=frame_cfg,
        files=FrameFiles(
            frame_times_path=args.frame_times,
            depth_dir=args.depth,
            mask_dir=args.masks,
            camera_mask_path=args.camera_mask,
        ),
        progress=True,
    )
    log.info(
        "wrote %s: %d of %d source frames (%d dropped), %s, camera %dx%d fx=%.2f",
        report.path,
        report.num_frames,
        report.num_source_frames,
        len(report.dropped),
        "undistorted" if report.undistorted else "raw (with distortion)",
        report.camera.width,
        report.camera.height,
        report.camera.fx,
    )
    return 0


def _run_reference(args: argparse.Namespace) -> int:
    result = import_reference(
        args.input_json,
        args.out,
        with_depth=args.with_depth,
        depth_scale_mm=args.depth_scale_mm,
        pose_units=args.pose_units,
        allow_outside_manifest=args.allow_outside_manifest,
    )
    for p in result.parts:
        log.info(
            "%s: %d frames -> %s%s",
            p.name,
            p.num_frames,
            result.path / p.sequence,
            "" if p.surface is None else f" (+ {p.surface})",
        )
    return 0


def _add_frame_parser(sub: argparse._SubParsersAction, kind: str) -> None:
    what = (
        "a video file (anything OpenCV's VideoCapture reads)"
        if kind == "video"
        else "a folder of images (png/jpg/bmp/tif, natural name order)"
    )
    p = sub.add_parser(
        kind,
        help=f"import {kind}: frames + tracked poses + calibration -> a sequence",
        description=f"Import endoscope frames from {what} with tracked poses and a "
        f"calibration into a sequence folder. Lengths in mm.\n\n{_FORMATS}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.set_defaults(func=_run_frames, kind=kind)
    p.add_argument("source", help=what)
    p.add_argument("--poses", required=True, help="pose file (see above)")
    p.add_argument("--calib", required=True, help="calibration .yaml/.xml/.json")
    p.add_argument(
        "--out", required=True, help="sequence folder to write (replaced atomically)", action=Output
    )
    g = p.add_argument_group("poses")
    g.add_argument(
        "--pose-format",
        choices=["auto", "matrix", "tum"],
        default="auto",
        help="default: by column count",
    )
    g.add_argument(
        "--pose-units",
        choices=["mm", "m"],
        default="mm",
        help="translation units of the pose file (default mm)",
    )
    g.add_argument(
        "--no-units-check",
        action="store_true",
        help="accept translations that look like the other unit",
    )
    g.add_argument("--match", choices=["index", "timestamp"], default="index")
    g.add_argument("--interp", choices=["nearest", "slerp"], default="nearest")
    g.add_argument(
        "--tolerance-s",
        type=finite_float,
        default=0.02,
        help="max frame-to-sample time, seconds (default 0.02)",
    )
    g.add_argument("--frame-times", help="CSV of frame times in seconds (last column)")
    g.add_argument(
        "--fps", type=finite_float, help="frame rate for frame times (default: the video's)"
    )
    g.add_argument(
        "--time-offset-s",
        type=finite_float,
        default=0.0,
        help="time of frame 0 on the pose clock, s",
    )
    g.add_argument("--hand-eye", help="T_marker_from_cam, 4x4 (.npy or text)")
    g.add_argument("--world-from-tracker", help="T_world_from_tracker, 4x4 (.npy or text)")
    g.add_argument(
        "--drop-unposed",
        action="store_true",
        help="leave out frames without a valid pose instead of failing",
    )
    g = p.add_argument_group("frames")
    g.add_argument(
        "--no-undistort",
        action="store_true",
        help="keep raw frames (sequence keeps the distortion)",
    )
    g.add_argument(
        "--alpha",
        type=finite_float,
        default=0.0,
        help="getOptimalNewCameraMatrix alpha in [0, 1] (default 0)",
    )
    g.add_argument(
        "--rescale-intrinsics",
        action="store_true",
        help="scale K to frames of another resolution, same aspect",
    )
    g.add_argument(
        "--field-stop",
        choices=["fit", "none"],
        default="fit",
        help="fit the circular field stop (default) or none",
    )
    g.add_argument(
        "--field-stop-circle", metavar="CX,CY,R", help="field stop on the raw image, pixels"
    )
    g.add_argument("--camera-mask", help="PNG mask on the raw grid (255 = inside the field stop)")
    g.add_argument(
        "--mask-margin-px",
        type=finite_float,
        default=2.0,
        help="shrink the field stop by this, px (default 2)",
    )
    g.add_argument("--start", type=int, default=0, help="first source frame")
    g.add_argument("--stop", type=int, help="source frame to stop before")
    g.add_argument("--step", type=int, default=1, help="take every STEP-th frame")
    g.add_argument("--depth", help="folder of per-frame depth (.npy / 16-bit .png)")
    g.add_argument(
        "--depth-scale-mm",
        type=finite_float,
        default=1.0,
        help="mm per stored depth unit (default 1)",
    )
    g.add_argument("--masks", help="folder of per-frame mask PNGs (tools, blood)")
    g.add_argument("--mask-invert", action="store_true", help="mask PNGs mark pixels to exclude")


def register(subparsers: argparse._SubParsersAction) -> None:
    imp = subparsers.add_parser(
        "import",
        help="import real data (video, image folder, reference layout) as sequences",
        description="Import real endoscopy data into sequence folders (mm, T_world_from_cam).",
    )
    sub = imp.add_subparsers(dest="import_kind", metavar="KIND", required=True)
    _add_frame_parser(sub, "video")
    _add_frame_parser(sub, "images")
    p = sub.add_parser(
        "reference",
        help="import the reference implementation's input.json layout",
        description=_REFERENCE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.set_defaults(func=_run_reference)
    p.add_argument("input_json", help="the dataset's input.json")
    p.add_argument(
        "--out", required=True, help="folder to write (replaced atomically)", action=Output
    )
    p.add_argument("--with-depth", action="store_true", help="also import depths/*.npy")
    p.add_argument(
        "--depth-scale-mm", type=finite_float, default=1.0, help="mm per depth unit (default 1)"
    )
    p.add_argument(
        "--pose-units", choices=["mm", "m"], default="mm", help="translation units (default mm)"
    )
    p.add_argument(
        "--allow-outside-manifest",
        action="store_true",
        help="let input.json name files outside its own folder (after resolving links); "
        "by default such a path is refused, so a dataset cannot make the import read or "
        "copy a file from elsewhere (e.g. ../../etc/shadow)",
    )
