"""Parameters of one update step: one home, from which ``chisel update``'s flags and its
``--config FILE.yaml`` are generated (:mod:`chisel.core.config`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from chisel.change import ChangeConfig
from chisel.core.config import check_fields, check_ranges
from chisel.io.limits import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE_PX
from chisel.odometry import OdometryConfig
from chisel.registration import RegistrationConfig
from chisel.shading import ShadingConfig

MIN_POINTS = 100
"""Fewest pixels per frame a registration samples (``max_points``, ``sequence_points``)."""


@dataclass(frozen=True)
class UpdateConfig:
    """Parameters of one update step."""

    change: ChangeConfig = field(default_factory=ChangeConfig)
    """Change-mask threshold and cleaning."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    """RANSAC + ICP parameters."""
    register: bool = True
    """False = the paper's registration ablation: scale only, no RANSAC/ICP."""
    sequence_ransac: bool = True
    """Batch mode: when ICP from the tracked poses does not register the step (no frame,
    or a median fitness below ``MIN_TRACKER_FITNESS``), first register the whole step's
    point cloud globally (FPFH + RANSAC + ICP)."""
    solve_scale: Literal["auto", "always", "never"] = "auto"
    """Solve the depth's scale (robust median of ratios to the render, then jointly with
    the pose in per-frame ICP): "auto" = unless the depth source declares metric depth
    (``is_metric``), whose scale is 1."""
    relative_depth: Literal["scale", "scale_shift"] = "scale_shift"
    """What a relative estimate (one whose scale is solved) is known up to: "scale_shift" =
    a scale and a shift, fitted robustly to the render per frame
    (:func:`chisel.change.shift_to_render`; how monocular networks are evaluated, Ranftl et
    al.); "scale" = a scale alone (the paper)."""
    occluder_margin_px: float = 0.0
    """Pixels within this distance of an occluder in a frame's mask (a pixel it leaves out
    inside the view: an instrument) are left out too, for every depth source
    (:func:`chisel.detect.occluder_margin`); 0 = the mask as given. A depth network's
    estimate bleeds across an instrument's edge: beside the simulator's tools the
    monocular network's abs-rel was 0.25 within 2 px and 0.13 at 12-16 px, against 0.065
    at the same pixels without the tool. 16 px brought every step of seeds 0-4 and 8-10
    within issue 22's 10 % of the tool-free run, but on a seed it had not seen (12) the
    paper's row moved further from it (1.20-1.73x at steps 2-5 against 1.02-1.48x), and
    the change-aware row on seed 3 too (1.13x against 1.06x at step 2): off by default
    (docs/updater.md)."""
    skip_occluded_frames: bool = False
    """Batch mode, an estimate (a relative one, whose scale is solved, or one that declares
    ``is_estimate``): a frame whose mask hides tissue that the step's other frames see (an
    instrument in view, :func:`chisel.fill.occluded_frames`) is left out of the step, as
    the paper picked tool-free frames by hand; the report lists it as skipped. A step
    whose every frame has one uses them all. A network's estimate changes across the
    whole frame when a tool is in it, not only beside the tool; metric depth does not,
    and exact depth lost 1.24x at a step without those frames' views (docs/updater.md).
    Off by default: it helps the paper's row, and loses the registration ablation (1.27x)
    and the change-aware row (1.13x) a step each on seeds 0-4 that they pass without it."""
    shading: ShadingConfig = field(default_factory=ShadingConfig)
    """Poses corrected by the frames' shading (off by default; :mod:`chisel.shading`)."""
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    """Tracked poses smoothed by the frames' odometry (off by default; :mod:`chisel.odometry`)."""
    max_points: int = 1500
    """About this many pixels (a regular stride) per frame in per-frame registration."""
    sequence_points: int = 500
    """About this many pixels per frame in the sequence-level registration stages."""
    hand_eye_frames: int = 20
    """Batch mode: at most this many frames, evenly spaced, estimate the hand-eye
    correction F (a robust median: more frames add time, not accuracy)."""
    hand_eye_estimator: Literal["median", "joint"] = "median"
    """Batch mode: how the step's hand-eye correction F is found. "median" = the robust
    median of the sampled frames' own ICP corrections; "joint" = refined from it by one
    robust ICP over every frame's points at once, F shared and each frame's depth scale
    its own (:func:`chisel.icp.icp_hand_eye`). A frame that sees little more than one
    wall fixes only some of F's six degrees of freedom and its own correction carries the
    others wherever its ICP left them; the joint solve weighs each direction by the
    frames that fix it. Off by default: on the benchmark exact depth ties (0.998x) and a
    network's F is its shape error either way (docs/updater.md)."""
    relative_hand_eye: Literal["step", "frame"] = "step"
    """Batch mode, an estimate whose scale is solved (a monocular network's): "step" = the
    step's hand-eye correction F places every frame (beyond the tracking accuracy it is
    rejected and every frame keeps its tracked pose, scale only); "frame" = F is reported
    but not applied: each frame is registered on its own from its tracked pose, its own
    correction gated by the tracking accuracy, the running mean of the accepted ones its
    prior (as in streaming use); a frame with an instrument in view registers but does
    not teach that mean (:func:`chisel.batch._teaching_frames`). The network's F was
    never the true correction (its rotation was worse after it at all 25 steps of seeds
    0-4), and one decision for the whole step flipped on a fraction of a degree between
    runs that differed only in instruments in view; per-frame decisions average over the
    frames (docs/updater.md, docs/results.md thirty-fifth and thirty-sixth sessions).
    Exact or metric depth: always "step"."""
    carve: Literal["deletion", "paper"] = "deletion"
    """How a change is carved: "deletion" = delete the first layer along a changed ray up to
    the next surface the model holds, fuse the new depth only where it holds nothing
    behind (:func:`chisel.carve.carve_first_layer`); "paper" = fuse the new depth at every
    changed pixel (the masked update alone)."""
    noisy_carve: bool = True
    """Deletion carving of a frame whose estimate is noisier than the change threshold (its
    noise-adaptive threshold above ``change.threshold_mm``; a network's depth): delete at
    most one layer, only where the estimate lies past the middle of the cavity behind it,
    and never fuse a new surface inside tissue the model holds (a partial cut needs depth
    precise to the threshold): docs/updater.md. Exact depth keeps the 1 mm threshold and
    is carved as before. False = every frame carved as precise."""
    noisy_votes: int = 3
    """Deletion carving of a noisy frame (see ``noisy_carve``): a voxel is set free once
    this many frames of the step have deleted it (one vote per frame; exact depth deletes
    at once). On the default experiment one frame's estimate, wrong through a whole region
    (a network's depth inside a dark cavity), deleted hundreds of voxels of tissue that
    other views did not confirm (docs/updater.md). 1 = every noisy frame deletes alone."""
    noisy_layer_mm: float = 4.0
    """Deletion carving of a noisy frame (see ``noisy_carve``): the layer it deletes is at
    most this thick along the ray, mm; a thicker one is left alone. What FESS takes is
    lamellae 0.4-2 mm thick (uncinate, bulla and ethmoid cell walls: docs/phantoms.md),
    4 mm along a ray through a 2 mm lamella at 60 deg. A network's "deeper here" across a
    thicker layer (a turbinate, the lateral wall) deleted tissue that was still there, up to
    9 mm from the true removal (docs/updater.md). Exact depth deletes any thickness."""
    noisy_max_depth_mm: float = 20.0
    """Deletion carving of a noisy frame (see ``noisy_carve``): a changed pixel whose old
    surface lies deeper than this (z-depth, mm) is left alone. A network's error grows with
    depth (abs-rel 0.06-0.1: 1.2-2 mm at 20 mm, the thickness of the layers it decides on)
    and the far field is dark (the tip light falls off with the square of the distance);
    the endoscope inspects a cut from close up (its working distance is 5-30 mm).
    Over the `table` run's seeds 0-4 (layer limit on) every truly removed voxel the network
    row found lay within 20 mm of a camera of its step, 29 % of its false deletions beyond
    (docs/updater.md). Exact depth carves at any depth."""
    rim_px: int = 5
    """Deletion carving of a precise frame (exact depth; see ``noisy_carve``): within this
    many pixels of its carved change, where the estimate lies deeper than the model by
    less than the threshold, the tissue the model holds in front of the estimate goes (a
    cut's edge, where the depth grows from 0 to the threshold and the paper's mask sees
    nothing). 5 = the mask's closing; 0 = off. Exact depth's removed-tissue Dice on seeds
    0-4: worst step 0.865 -> 0.889 (docs/updater.md)."""
    fill_unseen: bool = True
    """Fuse a frame's estimate where the model shows no surface at all (M_t invalid), into
    the voxels the model never observed (weight 0; or rewrote in this step) only. A model
    built from the preoperative sweep alone has holes wherever the sweep did not look, and
    the paper's masked update never fills them (invalid M_t counts as unchanged). On the
    sweep-only row (seeds 0-4 and held-out 8-12) it cut the missing fraction from 0.23 and
    0.19 to 0.04 and raised the F-score at 1 mm from 0.50 to 0.53 and 0.55, with the
    paper's metric over the larger surface 1.017x and 0.943x (geometric mean per step).
    A whole-CT model shows a surface in front of its never-observed voxels (outside the
    CT): it was left bit-identical (seed 0, checked). False: the paper."""
    fill_confirmed: bool = True
    """With ``fill_unseen``, in batch mode: also fuse the estimate into never-observed voxels
    next to a surface the model shows (within the truncation distance of the estimate),
    and behind what carving deleted, where at least ``change.min_views`` other frames,
    and ``change.min_agreement`` of those that see the point, put the surface within the
    truncation distance of it (:func:`chisel.fill.confirm_fill`; two frames with an
    instrument in view do not count for each other). One view is all there
    is of a hole the model shows nothing in; next to a surface, one frame's wrong depth
    would write into every unobserved voxel it reaches. The streaming updater has no
    other frames: unseen only. Sweep-built models only: a whole-CT model's
    never-observed voxels lie outside the CT, and filling them made the paper's row worse
    on seed 0 (0.534 -> 0.588 mm at step 2, 0.512 -> 0.569 at step 5). On the sweep-only
    row the missing fraction fell from 0.044 to 0.015 (seeds 0-4) and from 0.045 to
    0.018 (held-out 8-12) (docs/updater.md)."""
    frame_ransac: Literal["always", "until_prior"] = "until_prior"
    """When a frame's ICP fails: "until_prior" = retry it with RANSAC + ICP on its own
    points only while the hand-eye estimate has no prior (lost track at the start), and
    after a retry that failed not for the next 1, 2, 4, ... (at most 16) frames
    (:class:`chisel.detect.HandEye`); otherwise the frame keeps its tracked pose, scale
    only. "always" = every time
    (~0.1 s per retry at 320x256). On a large removal most of a close view has changed:
    ICP fails on many frames, and the retries set the streaming rate and landed on worse
    registrations (benchmarks/bench_update.py, docs/updater.md)."""
    allow_unused_step: bool = False
    """When no frame of a step can be used (every registration failed): False = raise
    :class:`EmptyResultError`; True = keep the model as it was (the step counter still
    advances) and say so in the report. Benchmarks use True so one bad step is scored as
    "no update" instead of stopping the run."""

    def __post_init__(self) -> None:
        check_fields(self)  # kinds, NaN and infinity
        px = MAX_IMAGE_SIDE_PX
        checks = (
            ("max_points", MIN_POINTS <= self.max_points <= MAX_IMAGE_PIXELS,
             f"in [{MIN_POINTS}, {MAX_IMAGE_PIXELS}] points per frame"),
            ("sequence_points", MIN_POINTS <= self.sequence_points <= MAX_IMAGE_PIXELS,
             f"in [{MIN_POINTS}, {MAX_IMAGE_PIXELS}] points per frame"),
            ("hand_eye_frames", self.hand_eye_frames >= 1, ">= 1"),
            ("noisy_votes", 1 <= self.noisy_votes <= 255, "in [1, 255]"),  # a uint8 count
            ("noisy_layer_mm", self.noisy_layer_mm > 0, "> 0 mm"),
            ("noisy_max_depth_mm", self.noisy_max_depth_mm > 0, "> 0 mm"),
            # Wider than any image is meaningless; OpenCV refuses (rim) or masks everything.
            ("occluder_margin_px", 0 <= self.occluder_margin_px <= px,
             f">= 0 pixels and at most {px} (the widest image read)"),
            ("rim_px", 0 <= self.rim_px <= px,
             f">= 0 pixels and at most {px} (the widest image read)"),
        )  # fmt: skip
        check_ranges(self, "", checks)
