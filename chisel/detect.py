"""Change detection of one frame, and the multi-view confirmation of a step's detections.

:func:`detect` registers a frame's depth estimate to the model surface and measures its
change mask against M_t; it touches no model and returns a frozen :class:`Detection`.
:func:`confirm_changes` is a pure function over a step's detections. The streaming
updater and the batch step (:mod:`chisel.updater`, :mod:`chisel.batch`) share both.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import cast

import cv2
import numpy as np

from chisel.change import (
    ChangeConfig,
    change_mask,
    clean_mask,
    frame_threshold,
    impute,
    multiview_support,
    shift_to_render,
    solve_scale,
    threshold_map,
    typical_threshold,
    warp_depth,
)
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.geometry import Camera, invert_rigid, transform_points
from chisel.depth_source import is_metric
from chisel.icp import icp_similarity
from chisel.io.sequence import Frame, check_depth_mm
from chisel.registration import (
    REJECTED_BY_TRACKING_ACCURACY,
    RegistrationResult,
    check_result,
    register_global,
    robust_mean_transform,
    tracking_excess,
)
from chisel.render import ModelRenderer
from chisel.update_config import UpdateConfig


@dataclass(frozen=True)
class FrameInput:
    """What detection needs of one frame: its checked tracked pose, the depth source's
    validated estimate, and what is already known of M_t and the scale."""

    frame: Frame
    T_world_from_cam: np.ndarray
    """(4, 4) tracked pose, checked rigid and inside the model; with
    ``UpdateConfig.shading`` aligning, moved sideways by the step's shading correction
    (:func:`chisel.shading.step_correction`) after that check."""
    estimate: np.ndarray
    """(H, W) float32 depth up to scale, NaN = invalid (:func:`validate_estimate`)."""
    render_mm: np.ndarray | None = None
    """(H, W) float32 M_t at the tracked pose, mm; None = rendered at detection."""
    scale0: float | None = None
    """The estimate's scale against M_t if already solved; None = solved at detection."""
    reliable: np.ndarray | None = None
    """(H, W) bool: where a learnt estimate declared its depth reliable
    (:func:`chisel.depth_source.reliable_pixels`); carved as precise there."""


@dataclass(frozen=True)
class Detection:
    """One frame's change, measured against M_t at its tracked pose (model untouched)."""

    index: int
    used: bool
    reason: str = ""
    """Why the frame is not used (no overlap with the render for the scale)."""
    scale: float = float("nan")
    registration: dict | None = None
    threshold_mm: float = float("nan")
    """The frame's change threshold, mm (see ``ChangeConfig.noise_k``)..."""
    threshold_per_mm: float = 0.0
    """... at a pixel ``max(threshold_mm, threshold_per_mm * M_t)``: it grows with depth
    with ``ChangeConfig.noise_with_depth`` (:func:`chisel.change.frame_threshold`)."""
    shift_mm: float = 0.0
    """Depth shift of a relative estimate (``UpdateConfig.relative_depth``), mm: M' is
    ``a * scale * estimate + shift_mm`` with ``a`` near 1 (fitted with the shift)."""
    T_world_from_cam: np.ndarray | None = field(default=None, repr=False)
    """(4, 4) the pose the maps are expressed in (the tracked pose)."""
    mask: np.ndarray | None = field(default=None, repr=False)
    """(H, W) bool change mask."""
    m_prime: np.ndarray | None = field(default=None, repr=False)
    """(H, W) float32 M' after imputation, mm."""
    m_t: np.ndarray | None = field(default=None, repr=False)
    """(H, W) float32 render of the model M_t, mm."""
    m_raw: np.ndarray | None = field(default=None, repr=False)
    """(H, W) float32 M' before imputation (NaN = lost), mm."""
    unconfirmed_px: int = 0
    """Changed pixels dropped because other frames did not confirm them (batch)."""
    correction: np.ndarray | None = field(default=None, repr=False)
    """(4, 4) camera-side correction this frame's registration found and that the
    tracker can need (None = none): what the hand-eye estimate learns from."""
    fill: np.ndarray | None = field(default=None, repr=False)
    """(H, W) bool pixels whose estimate other frames confirmed, fused into the voxels the
    model never observed where carving fused nothing (:func:`chisel.fill.confirm_fill`;
    batch); None = none."""

    @property
    def typical_threshold_mm(self) -> float:
        """The threshold as one number, mm: at the render's median depth where it grows
        with depth (what carving's tolerance, the precision test and the report take)."""
        if self.m_t is None:
            return self.threshold_mm
        return typical_threshold(self.threshold_mm, self.threshold_per_mm, self.m_t)


class HandEye:
    """The camera-side (hand-eye) correction F, ``T_corrected = T_tracked @ F``.

    Fixed (a batch step's F from the whole sequence) or, streaming, the robust mean of
    the corrections of the last ``HISTORY`` registered frames; once 3 frames agree, each
    frame's ICP is held near it by a weak prior. Until then a frame whose ICP fails may
    be retried with RANSAC (``UpdateConfig.frame_ransac``); after a retry that fails, the
    next 1, 2, 4, ... (at most ``RETRY_WAIT_MAX``) frames are not retried.
    """

    HISTORY = 15
    """Frames whose corrections form the streaming estimate of F."""
    RETRY_WAIT_MAX = 16
    """Longest wait, in frames, between RANSAC retries that keep failing. A retry costs
    ~0.1 s at 320x256; on bench_update's sweep-only model 2 of 32 retries succeeded, one per
    frame until the prior formed, which halved the streaming rate. Neighbouring frames see
    nearly the same surface: a retry that failed on one fails on the next."""

    def __init__(self) -> None:
        self.F = np.eye(4)
        self.fixed = False
        self.history: list[np.ndarray] = []
        self._failed_retries = 0
        self._wait = 0

    def current(self) -> np.ndarray:
        if self.fixed or not self.history:
            return self.F.copy()
        return robust_mean_transform(self.history[-self.HISTORY :])

    @property
    def prior(self) -> bool:
        return self.fixed or len(self.history) >= 3

    def may_retry(self, frame_ransac: str) -> bool:
        """Whether the next frame's failed ICP may be retried with RANSAC + ICP."""
        return frame_ransac == "always" or (not self.prior and self._wait == 0)

    def learn(self, det: Detection) -> None:
        if det.correction is not None:
            self.history.append(det.correction)
        retry = (det.registration or {}).get("global_retry")
        if retry == "ok":
            self._failed_retries, self._wait = 0, 0
        elif retry == "failed":
            self._failed_retries += 1
            self._wait = min(2 ** (self._failed_retries - 1), self.RETRY_WAIT_MAX)
        elif self._wait > 0:
            self._wait -= 1


def scale_free(cfg: UpdateConfig, source: object) -> bool:
    """True when the depth's scale must be solved (not declared metric, or forced)."""
    return cfg.solve_scale == "always" or (cfg.solve_scale == "auto" and not is_metric(source))


def occluder_margin(mask: np.ndarray, margin_px: float) -> np.ndarray:
    """``mask`` (True = use the pixel) less every pixel within ``margin_px`` of an occluder.

    An occluder is a pixel the mask leaves out inside the view: the filled convex hull of
    the pixels it keeps, less a 2-pixel rim so that a rasterised field stop's edge is no
    occluder. An instrument that enters from the edge of the view is one. A depth
    network's estimate bleeds across an occluder's edge: beside the simulator's
    instruments the monocular network's abs-rel was 0.25 within 2 px, 0.13 at 12-16 px
    and 0.065 at the same pixels of the tool-free frames (docs/updater.md).
    """
    m = np.asarray(mask, dtype=bool)
    if margin_px <= 0 or m.all() or not m.any():
        return m
    hull = np.zeros(m.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(cv2.findNonZero(m.astype(np.uint8))), 1)
    view = cv2.erode(hull, np.ones((5, 5), np.uint8)) > 0
    occluder = view & ~m
    if not occluder.any():
        return m
    # Euclidean distance to the nearest occluder pixel (0 on it).
    dist = cv2.distanceTransform((~occluder).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return m & (dist > margin_px)


def validate_estimate(
    depth: np.ndarray, frame: Frame, camera: Camera, metric: bool, margin_px: float = 0.0
) -> np.ndarray:
    """Check a depth source's output for ``frame``; returns (H, W) float32, NaN = invalid.

    Pixels the frame's mask leaves out are invalid, and those within ``margin_px`` of an
    occluder in it (:func:`occluder_margin`). Raises :class:`InvalidInputError` on a wrong
    shape or an all-invalid map, and (for metric sources)
    :class:`~chisel.core.errors.DepthUnitsError` on depth that looks like metres.
    """
    source = f"depth of frame {frame.index}"
    d = np.asarray(depth)
    camera.check_image(d, source)
    if metric:
        d = check_depth_mm(d, source)
    else:
        d = np.asarray(d, dtype=np.float32)
        d = np.where(np.isfinite(d) & (d > 0), d, np.float32(np.nan)).astype(np.float32)
        if not np.isfinite(d).any():
            raise InvalidInputError(source, "depth map has no valid pixel (all 0/NaN/negative)")
    if frame.mask is not None:
        use = occluder_margin(frame.mask, margin_px)
        d = np.where(use, d, np.float32(np.nan)).astype(np.float32)
    return d


def sample_points(
    camera: Camera, depth_mm: np.ndarray, T_world_from_cam: np.ndarray, max_points: int
) -> np.ndarray:
    """World points (N, 3) float64 of a regular pixel stride giving ~``max_points``, mm."""
    n_valid = int(np.isfinite(depth_mm).sum())
    stride = max(1, int(np.ceil(np.sqrt(n_valid / max_points))))
    rays = camera.rays_cam()[::stride, ::stride]
    d = np.asarray(depth_mm, dtype=np.float64)[::stride, ::stride]
    ok = np.isfinite(d) & (d > 0)
    pc = rays[ok] * d[ok][:, None]
    return transform_points(T_world_from_cam, pc)


@dataclass(frozen=True)
class Context:
    """What a frame is detected against: the step's M_t and configuration, and the
    hand-eye estimate at this frame."""

    camera: Camera
    renderer: ModelRenderer
    """M_t: renders and the registration target."""
    cfg: UpdateConfig
    solve_for_scale: bool
    """The estimate is up to scale (:func:`scale_free`)."""
    hand_eye: np.ndarray
    """(4, 4) camera-side correction F to start registration from."""
    prior: bool
    """Hold the frame's ICP near ``hand_eye``."""
    retry_global: bool
    """Retry a failed ICP with RANSAC + ICP on the frame's own points
    (:meth:`HandEye.may_retry`)."""


def detect(inp: FrameInput, ctx: Context) -> Detection:
    """Registration and change mask of one frame (the model is not touched).

    A frame with no overlap for its scale is returned unused.
    """
    T, cfg = inp.T_world_from_cam, ctx.cfg
    R = ctx.renderer.render(ctx.camera, T) if inp.render_mm is None else inp.render_mm
    try:
        m_raw, scale, reg = register_frame(T, inp.estimate, R, inp.scale0, ctx)
    except EmptyResultError as exc:
        return Detection(index=inp.frame.index, used=False, reason=str(exc))
    shift_mm = 0.0
    if ctx.solve_for_scale and cfg.relative_depth == "scale_shift":
        # After registration, so that the shift cannot absorb a pose error: fitted to the
        # render, a shift absorbs the pose error and biases the registration.
        try:
            shifted, shift, a = shift_to_render(R, m_raw, cfg.change.threshold_mm)
        except EmptyResultError:  # too little of M' left after re-projection: scale only
            shift = 0.0
        if shift != 0.0:
            m_raw, shift_mm = (a * shifted).astype(np.float32), a * shift
    correction = None
    if reg is not None and reg.ok and "rejected" not in reg.extra:
        correction = invert_rigid(T) @ reg.T_model_from_est @ T
    m_prime = impute(m_raw, R)
    floor_mm, per_mm = frame_threshold(m_raw, R, cfg.change)
    return Detection(
        index=inp.frame.index,
        used=True,
        scale=scale,
        registration=None if reg is None else reg.to_dict(),
        threshold_mm=floor_mm,
        threshold_per_mm=per_mm,
        shift_mm=shift_mm,
        T_world_from_cam=T,
        mask=change_mask(
            m_prime, R, cfg.change, threshold_map(floor_mm, per_mm, R) if per_mm > 0 else floor_mm
        ),
        m_prime=m_prime,
        m_t=R,
        m_raw=m_raw,
        correction=correction,
    )


def register_frame(
    T: np.ndarray, E: np.ndarray, R: np.ndarray, scale0: float | None, ctx: Context
) -> tuple[np.ndarray, float, RegistrationResult | None]:
    """M' before imputation (NaN = lost), the scale, and the registration (None = off).

    T : tracked pose; E : the estimate; R : M_t at T; scale0 : E's scale if solved.
    Raises :class:`EmptyResultError` when the scale cannot be solved (no overlap)."""
    camera, renderer, cfg = ctx.camera, ctx.renderer, ctx.cfg
    solve_for_scale, hand_eye, prior = ctx.solve_for_scale, ctx.hand_eye, ctx.prior
    if not solve_for_scale:
        s0 = 1.0
    elif scale0 is not None:
        s0 = float(scale0)
    else:
        s0 = solve_scale(R, E, cfg.change.threshold_mm)[0]
    if not cfg.register:
        return (s0 * E).astype(np.float32), s0, None
    rcfg = cfg.registration
    C = T @ hand_eye @ invert_rigid(T)
    src = sample_points(camera, s0 * E, T, cfg.max_points)  # placed with the tracked pose
    center = T[:3, 3]
    index = renderer.index
    sim = icp_similarity(src, center, index, C, rcfg, estimate_scale=solve_for_scale, prior=prior)
    res = check_result(
        sim.T_model_from_est, sim.fitness, sim.rmse_mm, "icp", src.mean(axis=0), rcfg, sim.scale
    )
    retried = ""
    if not res.ok and ctx.retry_global:
        # Lost track (first frame, a jump): global RANSAC on this frame alone, then ICP.
        lo, hi = src.min(axis=0) - 5.0, src.max(axis=0) + 5.0
        tv, tn = renderer.surface_points(lo, hi)
        if len(tv) >= 10:
            retried = "failed"
            glob = register_global(src, tv, tn, rcfg, init=C)
            if glob.ok:
                sim = icp_similarity(
                    src, center, index, glob.T_model_from_est, rcfg, estimate_scale=solve_for_scale
                )
                res = check_result(
                    sim.T_model_from_est, sim.fitness, sim.rmse_mm, "ransac+icp",
                    src.mean(axis=0), rcfg, sim.scale,
                )  # fmt: skip
                retried = "ok" if res.ok else "failed"
    s = s0 * sim.scale
    res.extra.update({"scale_refinement": sim.scale, "icp_iterations": sim.iterations})
    if retried:
        res.extra["global_retry"] = retried
    if not res.ok:
        # A noisy estimate never fails the frame: it keeps its tracked pose and the
        # scale anchored to the render (as the registration ablation), and says so.
        res.extra["fallback"] = f"registration failed ({res.reason}): tracked pose, scale only"
        return (s0 * E).astype(np.float32), s0, res
    # Registered estimate (camera at C @ T) re-projected into the tracked camera T.
    T_tracked_from_registered = invert_rigid(T) @ res.T_model_from_est @ T
    excess = tracking_excess(T_tracked_from_registered, rcfg)
    if excess:
        # As for a whole step (chisel.batch): a correction the tracker cannot need is
        # the estimate's shape error; the frame keeps its tracked pose, scale only.
        res.extra["rejected"] = f"{excess}: tracked pose, scale only"
        res.extra["rejected_by"] = REJECTED_BY_TRACKING_ACCURACY
        return (s0 * E).astype(np.float32), s0, res
    return warp_depth(s * E, camera, T_tracked_from_registered), s, res


def stack_maps(dets: list[Detection], name: str, shape: tuple[int, int]) -> np.ndarray:
    """(N, H, W) float32 map ``name`` of a step's detections, NaN for frames not used."""
    return np.stack(
        [getattr(d, name) if d.used else np.full(shape, np.nan, np.float32) for d in dets]
    )


def stack_poses(dets: list[Detection]) -> np.ndarray:
    """(N, 4, 4) poses a step's detections are expressed in (identity for frames not used)."""
    # A used detection has its pose (detect).
    return np.stack([cast(np.ndarray, d.T_world_from_cam) if d.used else np.eye(4) for d in dets])


def confirm_changes(dets: list[Detection], camera: Camera, cfg: ChangeConfig) -> list[Detection]:
    """Multi-view check of a step's change masks (batch mode): the detections with their
    masks confirmed.

    A changed pixel stays changed when at least ``cfg.min_views`` other frames that see
    its old surface point also see it removed, and they are at least ``cfg.min_agreement``
    of the frames that see it (:func:`chisel.change.multiview_support`). Depth errors of a
    monocular network differ from view to view, tissue removal does not: this is what
    keeps one frame's error from carving the model for good. The mask is cleaned again
    afterwards (components below the minimum area go).
    """
    used = np.array([d.used for d in dets], dtype=bool)
    if used.sum() < 2:
        return list(dets)
    shape = camera.shape
    # A used detection has its mask.
    masks = np.stack([cast(np.ndarray, d.mask) if d.used else np.zeros(shape, bool) for d in dets])
    renders, estimates = stack_maps(dets, "m_t", shape), stack_maps(dets, "m_raw", shape)
    support, observed = multiview_support(
        masks, renders, estimates, camera, stack_poses(dets), used,
        np.array([d.threshold_mm if d.used else np.inf for d in dets]), cfg.visible_mm,
        cfg.contradict_fraction, np.array([d.threshold_per_mm for d in dets]),
    )  # fmt: skip
    keep = (support >= cfg.min_views) & (support >= cfg.min_agreement * observed)
    out = []
    for d, m, k in zip(dets, masks, keep, strict=True):
        if not d.used:
            out.append(d)
            continue
        new = clean_mask(m & k, cfg)
        out.append(replace(d, mask=new, unconfirmed_px=int(m.sum() - new.sum())))
    return out
