"""The updater: preoperative model, per-step change detection and the masked update.

Pure functions at the boundaries (:func:`build_preop_model`, :func:`update_step`,
:func:`render_depth`) and one streaming class (:class:`ChiselUpdater`) that takes one
frame at a time for a navigation system. File I/O lives in ``chisel.cli.cmd_model``.

Per frame of a surgical step (paper, section 2; deviations in ``docs/updater.md``):

1. render M_t: the model's surface at step start (marching cubes, cached per step) ray
   cast at the frame's tracked pose;
2. the depth source gives an estimate of the new depth (possibly up to scale);
3. registration (unless switched off): a sequence-level RANSAC (FPFH) + robust ICP of all
   frames' scaled estimates to the model surface, then a camera-side hand-eye
   correction F (robust mean of per-frame ICP results), then per frame a robust 7-DoF
   ICP (pose and depth scale) from ``T_tracked @ F`` with a weak prior near it; frames
   whose fitness is too low are skipped and reported, never fused;
4. the registered estimate is re-projected into the frame at its tracked pose -> M',
   pixels lost in projection take M_t ("imputation");
5. change mask m = (M' - M_t) > threshold, cleaned;
6. masked integration of M' with ``w = 0 * W_t + m`` (see :mod:`chisel.fusion`).

Registration off (the paper's ablation): the estimate is only scaled to the render
(robust median of ratios) and used as M' directly.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Literal, cast

import cv2
import numpy as np
import trimesh

from chisel.carve import CARVE_DELETED, CARVE_FUSE, carve_first_layer
from chisel.change import (
    ChangeConfig,
    change_mask,
    clean_mask,
    frame_threshold,
    impute,
    multiview_support,
    solve_scale,
    warp_depth,
)
from chisel.core.config import check_fields
from chisel.core.errors import EmptyResultError, InvalidInputError, PoseError
from chisel.core.geometry import (
    Camera,
    check_rigid,
    invert_rigid,
    rotation_angle_deg,
    transform_points,
)
from chisel.core.raycast import MeshRaycaster
from chisel.ct_model import CtInput, check_ct_covers_views, ct_tsdf
from chisel.depth_source import estimate_depth, is_metric, wants_prior
from chisel.fusion import (
    check_pose_in_model,
    integrate,
)
from chisel.icp import SurfaceIndex, icp_similarity
from chisel.io.sequence import Frame, check_depth_mm
from chisel.mesh import extract_mesh
from chisel.model import TsdfModel
from chisel.registration import (
    RegistrationConfig,
    RegistrationResult,
    check_result,
    register_global,
    robust_mean_transform,
)

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- configs
@dataclass(frozen=True)
class BuildConfig:
    """Parameters of the preoperative model."""

    voxel_size_mm: float = 0.5
    """Voxel edge, mm."""
    trunc_mm: float = 2.0
    """Truncation of the signed distance, mm (>= voxel size; ~4 voxels is usual)."""
    margin_mm: float = 3.0
    """Margin added around the data's bounds, mm."""
    max_view_mm: float = 60.0
    """The grid is cropped to the camera centres' box grown by this, mm (large CT scans)."""
    color: bool = False
    """Keep colour (from the frames' RGB) in the model."""
    ct_weight: float = 1.0
    """CT build: the initial weight of every voxel the CT covers (the sweep adds its own)."""
    max_miss_fraction: float = 0.05
    """CT build: a preop frame with more than this fraction of its rays leaving the CT
    without meeting tissue means the CT's grid does not cover the view (refused)."""

    def __post_init__(self) -> None:
        if not (self.ct_weight > 0 and np.isfinite(self.ct_weight)):
            raise InvalidInputError("ct_weight", f"must be > 0, got {self.ct_weight}")
        if not 0.0 <= self.max_miss_fraction <= 1.0:
            raise InvalidInputError(
                "max_miss_fraction", f"must be in [0, 1], got {self.max_miss_fraction}"
            )
        if not self.voxel_size_mm > 0:
            raise InvalidInputError("voxel_size_mm", f"must be > 0, got {self.voxel_size_mm}")
        if not self.trunc_mm >= self.voxel_size_mm:
            raise InvalidInputError(
                "trunc_mm", f"must be >= voxel_size_mm ({self.voxel_size_mm}), got {self.trunc_mm}"
            )
        if self.margin_mm < 0 or self.max_view_mm <= 0:
            raise InvalidInputError("margin_mm", "margin must be >= 0 and max_view_mm > 0")


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
    max_points: int = 1500
    """About this many pixels (a regular stride) per frame in per-frame registration."""
    sequence_points: int = 500
    """About this many pixels per frame in the sequence-level registration stages."""
    hand_eye_frames: int = 20
    """Batch mode: at most this many frames, evenly spaced, estimate the hand-eye
    correction F (a robust median: more frames add time, not accuracy)."""
    carve: Literal["deletion", "paper"] = "deletion"
    """How a change is carved: "deletion" = delete the first layer along a changed ray up to
    the next surface the model holds, fuse the new depth only where it holds nothing
    behind (:func:`chisel.carve.carve_first_layer`); "paper" = fuse the new depth at every
    changed pixel (the masked update alone)."""
    allow_unused_step: bool = False
    """When no frame of a step can be used (every registration failed): False = raise
    :class:`EmptyResultError`; True = keep the model as it was (the step counter still
    advances) and say so in the report. Benchmarks use True so one bad step is scored as
    "no update" instead of stopping the run."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.max_points < 100 or self.sequence_points < 100:
            raise InvalidInputError("max_points", "use at least 100 points per frame")
        if self.carve not in ("deletion", "paper"):
            raise InvalidInputError("carve", f"expected 'deletion' or 'paper', got {self.carve!r}")
        if self.hand_eye_frames < 1:
            raise InvalidInputError("hand_eye_frames", f"must be >= 1, got {self.hand_eye_frames}")


MIN_TRACKER_FITNESS = 0.5
"""Batch mode: below this median ICP fitness from the tracked poses, search globally."""


# ---------------------------------------------------------------------------- rendering
class ModelRenderer:
    """Depth renders of a model's surface (marching cubes once, then ray casting with
    :class:`~chisel.core.raycast.MeshRaycaster`: Mitsuba where a JIT variant works, else Open3D)."""

    def __init__(self, model: TsdfModel) -> None:
        self.mesh: trimesh.Trimesh = extract_mesh(model, with_color=False)
        self._grid = (model.origin_mm, model.voxel_size_mm, model.shape)
        self.raycaster = MeshRaycaster(self.mesh.vertices, self.mesh.faces)
        self._normals = np.asarray(self.mesh.vertex_normals)
        self._index: SurfaceIndex | None = None

    @property
    def index(self) -> SurfaceIndex:
        """k-d tree of the surface's vertices with normals (registration target), lazily built."""
        if self._index is None:
            self._index = SurfaceIndex(self.mesh.vertices, self._normals, grid=self._grid)
        return self._index

    def render(self, camera: Camera, T_world_from_cam: np.ndarray) -> np.ndarray:
        """(H, W) float32 z-depth of the model surface, mm, NaN where nothing is hit."""
        return self.raycaster.render_depth(camera, T_world_from_cam)

    def surface_points(self, lo_mm: np.ndarray, hi_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mesh vertices and normals inside a world box: ((N, 3), (N, 3)) float64 mm."""
        v = self.mesh.vertices
        sel = np.all((v >= lo_mm) & (v <= hi_mm), axis=1)
        return v[sel], self._normals[sel]


def render_depth(model: TsdfModel, camera: Camera, T_world_from_cam: np.ndarray) -> np.ndarray:
    """Depth of the model's surface at a pose: (H, W) float32 mm, NaN = no surface.

    Convenience for one pose; for many poses keep a :class:`ModelRenderer`.
    """
    return ModelRenderer(model).render(camera, T_world_from_cam)


# ---------------------------------------------------------------------------- preop
def preop_bounds(
    surface: trimesh.Trimesh, poses: np.ndarray, cfg: BuildConfig
) -> tuple[np.ndarray, np.ndarray]:
    """World box of the preoperative grid: the surface's bounds plus a margin, cropped to
    the camera centres' box grown by ``max_view_mm``, and always holding every camera."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in surface.bounds)
    lo, hi = lo - cfg.margin_mm, hi + cfg.margin_mm
    cams = poses[:, :3, 3]
    lo = np.maximum(lo, cams.min(axis=0) - cfg.max_view_mm)
    hi = np.minimum(hi, cams.max(axis=0) + cfg.max_view_mm)
    lo = np.minimum(lo, cams.min(axis=0) - cfg.margin_mm)
    hi = np.maximum(hi, cams.max(axis=0) + cfg.margin_mm)
    return lo, hi


def build_preop_model(
    surface: trimesh.Trimesh | None,
    camera: Camera,
    poses: np.ndarray,
    cfg: BuildConfig = BuildConfig(),  # noqa: B008 - frozen dataclass
    rgbs: Iterable[np.ndarray | None] | None = None,
    masks: Iterable[np.ndarray | None] | None = None,
    progress: Callable[[Iterable], Iterable] | None = None,
    ct: CtInput | None = None,
) -> TsdfModel:
    """The preoperative TSDF model: the whole CT (``ct`` given) or the preop sweep alone.

    surface : CT segmentation surface, world mm (see :func:`chisel.io.ct.load_ct_surface`);
        ignored (may be None) when ``ct`` is given, whose own surface is used.
    poses : (N, 4, 4) float64 ``T_world_from_cam`` of the preop sequence, mm.
    rgbs : N (H, W, 3) uint8 images (or None) for colour; masks : N (H, W) bool or None.
    ct : the CT as signed distances (:mod:`chisel.ct_model`). Given, every voxel the CT
        covers takes its normalised truncated signed distance and weight ``cfg.ct_weight``
        (``build = "ct"``), and the sweep adds observation weight and colour where it sees;
        the CT's grid must cover the preop views (else :class:`InvalidInputError`).
        Without it (the paper, ``build = "sweep"``): the surface rendered at every pose is
        fused with Curless-Levoy averaging, w = 1 per valid pixel, free space carved (+1).
    """
    P = check_rigid(poses, "poses")
    if P.ndim != 3 or len(P) == 0:
        raise PoseError("poses", f"expected (N, 4, 4) poses with N >= 1, got shape {P.shape}")
    rgb_list = [None] * len(P) if rgbs is None else list(rgbs)
    mask_list = [None] * len(P) if masks is None else list(masks)
    if len(rgb_list) != len(P) or len(mask_list) != len(P):
        raise PoseError(
            "poses",
            f"{len(P)} poses but {len(rgb_list)} images and {len(mask_list)} masks: counts differ",
        )
    if ct is not None:
        surface = ct.surface
        check_ct_covers_views(ct, P, np.zeros(len(P)), cfg.max_miss_fraction)  # the cameras
    if surface is None or len(surface.faces) == 0:
        raise InvalidInputError("surface", "CT surface has no triangle")
    lo, hi = preop_bounds(surface, P, cfg)
    model = TsdfModel.empty(lo, hi, cfg.voxel_size_mm, cfg.trunc_mm, with_color=cfg.color)
    rc = MeshRaycaster(surface.vertices, surface.faces)
    items = list(zip(P, rgb_list, mask_list, strict=True))
    it = progress(items) if progress is not None else items
    seen = masked_out = 0
    misses: list[float] = []
    for T, rgb, mask in it:
        depth = rc.render_depth(camera, T)
        if mask is not None:
            masked_out += not mask.any()
            depth = np.where(mask, depth, np.nan).astype(np.float32)
        keep = np.ones(camera.shape, bool) if mask is None else np.asarray(mask, bool)
        misses.append(float((~np.isfinite(depth) & keep).sum() / max(int(keep.sum()), 1)))
        if np.isfinite(depth).any():
            seen += 1
            integrate(model, camera, T, depth, rgb=rgb)
    if ct is not None and masked_out < len(P):
        check_ct_covers_views(ct, P, misses, cfg.max_miss_fraction)
    if seen == 0:
        if masked_out == len(P):
            raise EmptyResultError("every preoperative frame's mask keeps no pixel")
        raise EmptyResultError("the CT surface is not visible from any preoperative pose")
    if ct is None:
        return model
    tsdf, covered = ct_tsdf(ct, model.T_world_from_voxel, model.shape, cfg.trunc_mm)
    weight = np.where(covered, np.float32(cfg.ct_weight), np.float32(0)) + model.weight
    return replace(
        model, tsdf=tsdf, weight=weight.astype(np.float32), build="ct", ct_sha256=ct.fingerprint
    )


# ---------------------------------------------------------------------------- reports
@dataclass
class FrameReport:
    """What happened to one frame of a step."""

    index: int
    used: bool
    reason: str = ""
    scale: float = float("nan")
    registration: dict | None = None
    changed_fraction: float = 0.0
    voxels_updated: int = 0
    mask: np.ndarray | None = field(default=None, repr=False)
    """(H, W) bool change mask (not serialised)."""
    m_prime: np.ndarray | None = field(default=None, repr=False)
    """(H, W) float32 M' after imputation, mm (not serialised)."""
    m_t: np.ndarray | None = field(default=None, repr=False)
    """(H, W) float32 render of the model M_t, mm (not serialised)."""
    m_raw: np.ndarray | None = field(default=None, repr=False)
    """(H, W) float32 M' before imputation (NaN = lost), mm; kept until fused."""
    T_world_from_cam: np.ndarray | None = field(default=None, repr=False)
    """(4, 4) the pose the maps are expressed in (the tracked pose); kept until fused."""
    unconfirmed_px: int = 0
    """Changed pixels dropped because other frames did not confirm them (batch)."""
    threshold_mm: float = float("nan")
    """The change threshold used for this frame, mm (see ``ChangeConfig.noise_k``)."""
    deleted_px: int = 0
    """Changed pixels whose first layer was deleted up to a surface the model holds."""
    voxels_deleted: int = 0
    """Voxels set free by deletion-first carving (included in ``voxels_updated``)."""

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "used": self.used,
            "reason": self.reason,
            "scale": None if not np.isfinite(self.scale) else float(self.scale),
            "registration": self.registration,
            "changed_fraction": float(self.changed_fraction),
            "voxels_updated": int(self.voxels_updated),
            "unconfirmed_px": int(self.unconfirmed_px),
            "threshold_mm": None if not np.isfinite(self.threshold_mm) else self.threshold_mm,
            "deleted_px": int(self.deleted_px),
            "voxels_deleted": int(self.voxels_deleted),
        }


@dataclass
class StepReport:
    """Summary of one update step (serialised as the JSON report of ``chisel update``)."""

    step: int
    frames: list[FrameReport]
    sequence_registration: dict | None
    config: dict

    @property
    def frames_used(self) -> list[int]:
        return [f.index for f in self.frames if f.used]

    @property
    def frames_skipped(self) -> list[dict]:
        return [{"index": f.index, "reason": f.reason} for f in self.frames if not f.used]

    def to_dict(self) -> dict:
        used = [f for f in self.frames if f.used]
        return {
            "step": self.step,
            "num_frames": len(self.frames),
            "frames_used": self.frames_used,
            "frames_skipped": self.frames_skipped,
            "frames_unregistered": [
                f.index for f in self.frames if f.used and "fallback" in (f.registration or {})
            ],
            "changed_pixel_fraction_mean": float(np.mean([f.changed_fraction for f in used]))
            if used
            else 0.0,
            "sequence_registration": self.sequence_registration,
            "frames": [f.to_dict() for f in self.frames],
            "config": self.config,
        }


def _config_dict(cfg: UpdateConfig) -> dict:
    from dataclasses import asdict

    return asdict(cfg)


# ---------------------------------------------------------------------------- streaming
class ChiselUpdater:
    """Keeps a model current, one frame at a time (streaming use in a navigation system).

    Usage::

        upd = ChiselUpdater(model, camera, depth_source)
        upd.begin_step()                 # M_t := the model now
        for frame in frames:             # Frame with rgb and/or depth, tracked pose
            report = upd.process(frame)
        step_report = upd.end_step()     # model.step += 1
        upd.model.save("step_01.npz")

    The model passed in is copied; ``upd.model`` is the current one. Tracking error is
    modelled as a constant camera-side (hand-eye) correction F, ``T_corrected =
    T_tracked @ F``, plus per-frame jitter. In streaming use F is the robust mean of the
    corrections of the last ``HISTORY`` registered frames (kept across steps); each
    frame's ICP starts from it and, once 3 frames agree, is held near it by a weak prior.
    A frame whose ICP fails is retried with RANSAC + ICP on its own points.
    """

    HISTORY = 15
    """Frames whose corrections form the streaming estimate of F."""

    def __init__(
        self,
        model: TsdfModel,
        camera: Camera,
        depth_source: Callable[[Frame], np.ndarray] | None = None,
        cfg: UpdateConfig = UpdateConfig(),  # noqa: B008 - frozen dataclass
    ) -> None:
        self.model = model.copy()
        self.camera = camera
        self.depth_source = depth_source
        self.cfg = cfg
        self._renderer: ModelRenderer | None = None
        self._reset: np.ndarray | None = None
        self._frames: list[FrameReport] = []
        self._F = np.eye(4)
        self._F_hist: list[np.ndarray] = []
        self._fixed = False
        self._seq_reg: dict | None = None

    # ----------------------------------------------------------------- step control
    def begin_step(
        self,
        hand_eye: np.ndarray | None = None,
        fixed: bool = False,
        sequence_registration: dict | None = None,
        renderer: ModelRenderer | None = None,
    ) -> None:
        """Start a surgical step: M_t is the model as it is now.

        hand_eye : (4, 4) camera-side correction F (``T_corrected = T_tracked @ F``) to
        start from, e.g. from a sequence-level registration; fixed : use F as is for
        every frame (batch) instead of re-estimating it from the frames (streaming);
        renderer : a :class:`ModelRenderer` of this same model, if one was already built.
        """
        self._renderer = ModelRenderer(self.model) if renderer is None else renderer
        self._reset = np.zeros(self.model.shape, dtype=np.uint8)
        self._frames = []
        if hand_eye is not None:
            self._F = check_rigid(hand_eye, "hand_eye")
        self._fixed = fixed
        self._seq_reg = sequence_registration

    @property
    def hand_eye(self) -> np.ndarray:
        """(4, 4) current camera-side correction F (``T_corrected = T_tracked @ F``)."""
        if self._fixed or not self._F_hist:
            return self._F.copy()
        return robust_mean_transform(self._F_hist[-self.HISTORY :])

    @property
    def renderer(self) -> ModelRenderer:
        if self._renderer is None:
            raise RuntimeError("call begin_step() before processing frames")
        return self._renderer

    def end_step(self) -> StepReport:
        """Finish the step: the model's step counter advances; returns the report."""
        if self._renderer is None:
            raise RuntimeError("end_step() without begin_step()")
        if not any(f.used for f in self._frames):
            reasons = sorted({f.reason for f in self._frames})[:5]
            message = f"no frame of the step could be used ({len(self._frames)} frames; reasons: {reasons})"
            if not self.cfg.allow_unused_step:
                raise EmptyResultError(message)
            log.warning("%s: the model is kept as it was", message)
        self.model = _with_step(self.model, self.model.step + 1)
        rep = StepReport(self.model.step, self._frames, self._seq_reg, _config_dict(self.cfg))
        self._renderer = None
        self._reset = None
        return rep

    # ----------------------------------------------------------------- one frame
    def estimate(self, frame: Frame, render_mm: np.ndarray | None = None) -> np.ndarray:
        """The depth source's estimate for ``frame``, validated; (H, W) float32, NaN invalid.

        render_mm : M_t at the frame's tracked pose, handed to a source that wants a prior."""
        if self.depth_source is None:
            raise InvalidInputError("depth_source", "no depth source given to the updater")
        return validate_estimate(
            estimate_depth(self.depth_source, frame, render_mm),
            frame,
            self.camera,
            is_metric(self.depth_source),
        )

    def process(
        self,
        frame: Frame,
        estimate: np.ndarray | None = None,
        render_mm: np.ndarray | None = None,
        keep_maps: bool = False,
        scale0: float | None = None,
    ) -> FrameReport:
        """Detect the change in one frame and carve it into the model.

        frame : tracked pose plus image and/or depth; estimate : (H, W) float32 depth up to
        scale (None = ask the depth source); render_mm : (H, W) float32 M_t at the
        tracked pose if already rendered; scale0 : the estimate's scale solved against
        ``render_mm`` if already known (batch). Returns the frame's report; a frame that fails
        registration is skipped (``used = False``) and leaves the model untouched.
        Same as :meth:`detect` then :meth:`fuse`.
        """
        return self.fuse(self.detect(frame, estimate, render_mm, scale0), frame.rgb, keep_maps)

    def detect(
        self,
        frame: Frame,
        estimate: np.ndarray | None = None,
        render_mm: np.ndarray | None = None,
        scale0: float | None = None,
    ) -> FrameReport:
        """Registration and change mask of one frame, without touching the model.

        Arguments as :meth:`process`. The report carries the maps (mask, M', M_t) until
        :meth:`fuse` applies it; a batch may edit ``mask`` in between (multi-view check).
        """
        renderer = self.renderer
        T = check_pose_in_model(self.model, frame.T_world_from_cam, f"frame {frame.index} pose")
        R = renderer.render(self.camera, T) if render_mm is None else render_mm
        E = self.estimate(frame, R) if estimate is None else estimate
        rep = FrameReport(index=frame.index, used=False)
        try:
            m_raw, scale, reg_res = self._m_prime(T, E, R, scale0)
        except EmptyResultError as exc:
            rep.reason = str(exc)
            return rep
        rep.scale = scale
        rep.registration = None if reg_res is None else reg_res.to_dict()
        if reg_res is not None and reg_res.ok and "rejected" not in reg_res.extra:
            self._F_hist.append(invert_rigid(T) @ reg_res.T_model_from_est @ T)
        m_prime = impute(m_raw, R)
        rep.threshold_mm = frame_threshold(m_raw, R, self.cfg.change)
        rep.mask = change_mask(m_prime, R, self.cfg.change, rep.threshold_mm)
        rep.m_prime, rep.m_t, rep.m_raw, rep.T_world_from_cam = m_prime, R, m_raw, T
        rep.used = True
        return rep

    def fuse(
        self, rep: FrameReport, rgb: np.ndarray | None = None, keep_maps: bool = False
    ) -> FrameReport:
        """Carve a detected frame's change mask into the model (masked update); returns ``rep``.

        rgb : (H, W, 3) uint8 colour of the frame (used when the model has colour).
        Frames not used (failed registration) only join the step's report.
        """
        if rep.used:
            if (
                rep.mask is None
                or rep.m_prime is None
                or rep.m_t is None
                or rep.T_world_from_cam is None
            ):
                raise InvalidInputError("rep", f"frame {rep.index}: maps already dropped")
            mask = rep.mask
            fuse_mask = mask
            if self.cfg.carve == "deletion" and mask.any():
                # Deletion first: where the model already holds the surface behind the
                # removed layer, delete the layer and keep that surface; fuse the new
                # depth only where the model holds nothing behind.
                status, rep.voxels_deleted = carve_first_layer(
                    self.model, self.camera, rep.T_world_from_cam, rep.m_t, rep.m_prime,
                    mask, rep.threshold_mm, reset=self._reset,
                )  # fmt: skip
                rep.deleted_px = int((status == CARVE_DELETED).sum())
                fuse_mask = mask & (status == CARVE_FUSE)
            lateral = cv2.distanceTransform(
                fuse_mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            )
            rep.voxels_updated = rep.voxels_deleted + integrate(
                self.model,
                self.camera,
                rep.T_world_from_cam,
                rep.m_prime,
                pixel_weight=fuse_mask,
                rgb=rgb,
                reset=self._reset,
                lateral_px=lateral,
            )
            valid = np.isfinite(rep.m_t)
            rep.changed_fraction = float(mask.sum() / max(int(valid.sum()), 1))
        rep.m_raw = rep.T_world_from_cam = None
        if not keep_maps:
            rep.mask = rep.m_prime = rep.m_t = None
        self._frames.append(rep)
        return rep

    def _m_prime(
        self, T: np.ndarray, E: np.ndarray, R: np.ndarray, scale0: float | None = None
    ) -> tuple[np.ndarray, float, RegistrationResult | None]:
        """M' before imputation (NaN = lost), the scale, and the registration (None = off)."""
        cfg = self.cfg
        scale_free = _scale_free(cfg, self.depth_source)
        if not scale_free:
            s0 = 1.0
        elif scale0 is not None:
            s0 = float(scale0)
        else:
            s0 = solve_scale(R, E, cfg.change.threshold_mm)[0]
        if not cfg.register:
            return (s0 * E).astype(np.float32), s0, None
        rcfg = cfg.registration
        C = T @ self.hand_eye @ invert_rigid(T)
        prior = self._fixed or len(self._F_hist) >= 3
        src = _points(self.camera, s0 * E, T, cfg.max_points)  # placed with the tracked pose
        center = T[:3, 3]
        index = self.renderer.index
        sim = icp_similarity(src, center, index, C, rcfg, estimate_scale=scale_free, prior=prior)
        res = check_result(
            sim.T_model_from_est, sim.fitness, sim.rmse_mm, "icp", src.mean(axis=0), rcfg, sim.scale
        )
        if not res.ok:
            # Lost track (first frame, a jump): global RANSAC on this frame alone, then ICP.
            lo, hi = src.min(axis=0) - 5.0, src.max(axis=0) + 5.0
            tv, tn = self.renderer.surface_points(lo, hi)
            if len(tv) >= 10:
                glob = register_global(src, tv, tn, rcfg, init=C)
                if glob.ok:
                    sim = icp_similarity(
                        src, center, index, glob.T_model_from_est, rcfg, estimate_scale=scale_free
                    )
                    res = check_result(
                        sim.T_model_from_est,
                        sim.fitness,
                        sim.rmse_mm,
                        "ransac+icp",
                        src.mean(axis=0),
                        rcfg,
                        sim.scale,
                    )
        s = s0 * sim.scale
        res.extra.update({"scale_refinement": sim.scale, "icp_iterations": sim.iterations})
        if not res.ok:
            # A noisy estimate never fails the frame: it keeps its tracked pose and the
            # scale anchored to the render (as the registration ablation), and says so.
            res.extra["fallback"] = f"registration failed ({res.reason}): tracked pose, scale only"
            return (s0 * E).astype(np.float32), s0, res
        # Registered estimate (camera at C @ T) re-projected into the tracked camera T.
        T_tracked_from_registered = invert_rigid(T) @ res.T_model_from_est @ T
        excess = _tracking_excess(T_tracked_from_registered, rcfg)
        if excess:
            # As for a whole step (update_step): a correction the tracker cannot need is
            # the estimate's shape error; the frame keeps its tracked pose, scale only.
            res.extra["rejected"] = f"{excess}: tracked pose, scale only"
            return (s0 * E).astype(np.float32), s0, res
        return warp_depth(s * E, self.camera, T_tracked_from_registered), s, res


def _scale_free(cfg: UpdateConfig, source: object) -> bool:
    """True when the depth's scale must be solved (not declared metric, or forced)."""
    return cfg.solve_scale == "always" or (cfg.solve_scale == "auto" and not is_metric(source))


def _with_step(model: TsdfModel, step: int) -> TsdfModel:
    return replace(model, step=step)


def _points(
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


def validate_estimate(depth: np.ndarray, frame: Frame, camera: Camera, metric: bool) -> np.ndarray:
    """Check a depth source's output for ``frame``; returns (H, W) float32, NaN = invalid.

    Raises :class:`InvalidInputError` on a wrong shape or an all-invalid map, and (for
    metric sources) :class:`~chisel.core.errors.DepthUnitsError` on depth that looks like metres.
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
        d = np.where(frame.mask, d, np.float32(np.nan)).astype(np.float32)
    return d


# ---------------------------------------------------------------------------- batch
def update_step(
    model: TsdfModel,
    camera: Camera,
    frames: Iterable[Frame],
    depth_source: Callable[[Frame], np.ndarray],
    cfg: UpdateConfig = UpdateConfig(),  # noqa: B008 - frozen dataclass
    progress: Callable[[Iterable], Iterable] | None = None,
    keep_maps: bool = False,
) -> tuple[TsdfModel, StepReport]:
    """Apply one surgical step (one sequence) to ``model``; returns (new model, report).

    ``model`` is not modified. All frames are validated (poses rigid and inside the
    model's volume, depth plausible) before anything is fused, so bad input raises
    without a half-updated result. Raises :class:`EmptyResultError` when no frame of the
    step could be used.
    """
    frames = list(frames)
    if not frames:
        raise InvalidInputError("frames", "a step needs at least one frame")
    metric = is_metric(depth_source)
    poses = [
        check_pose_in_model(model, f.T_world_from_cam, f"frame {f.index} pose") for f in frames
    ]
    step_cfg = cfg
    renders: list[np.ndarray | None] = [None] * len(frames)
    scales: list[float | None] = [None] * len(frames)
    F = None
    seq_reg = None
    renderer = None
    if cfg.register or wants_prior(depth_source):
        # M_t at every tracked pose: registration's reference, and the prior handed to a
        # depth source that wants one (the change-aware network).
        renderer = ModelRenderer(model)
        renders = list(renderer.raycaster.render_depths(camera, np.stack(poses)))
    estimates = [
        validate_estimate(estimate_depth(depth_source, f, R), f, camera, metric)
        for f, R in zip(frames, renders, strict=True)
    ]
    if cfg.register:
        scale_free = _scale_free(cfg, depth_source)
        if scale_free:
            # Solved once per frame; every stage below starts from the same scales.
            # Every render exists when registering (rendered above for the step).
            scales = [
                _try_scale(cast(np.ndarray, R), E, cfg)
                for R, E in zip(renders, estimates, strict=True)
            ]
        else:
            scales = [1.0] * len(frames)
        # The tracker first: ICP from the tracked poses. A global search (FPFH + RANSAC over
        # the whole step) only when that fails: on a monocular estimate, whose shape is not
        # quite the model's, it can lock onto a fit rotated by several degrees, which then
        # carves unchanged tissue (6-12 deg on the default experiment's network depth).
        args = (cast(ModelRenderer, renderer), camera, poses, estimates, scales)
        F, he = _hand_eye(*args, np.eye(4), cfg, scale_free)
        seq_reg = {"ok": True, "method": "tracker", "reason": "ICP from the tracked poses"}
        if cfg.sequence_ransac and (F is None or he["fitness_median"] < MIN_TRACKER_FITNESS):
            log.info("ICP from the tracked poses did not register (%s): global search", he)
            C, seq_reg = _sequence_registration(*args, cfg)
            F, he = _hand_eye(*args, C, cfg, scale_free)
        seq_reg = {**seq_reg, "hand_eye": he}
        excess = None if F is None else _tracking_excess(F, cfg.registration)
        if excess:
            # A monocular estimate whose shape differs from the model's pulls ICP to a
            # "correction" the tracker cannot need (6-12 deg on the default experiment's
            # network depth, true hand-eye error 0.5 deg); placed that way, the estimate
            # carves unchanged tissue. Trust the tracker for this step instead.
            reason = f"hand-eye {excess}: the step is placed with the tracked poses, scale only"
            log.warning("%s", reason)
            seq_reg = {**seq_reg, "rejected": reason}
            step_cfg = replace(cfg, register=False)
            F = None
    upd = ChiselUpdater(model, camera, depth_source, step_cfg)
    upd.begin_step(
        hand_eye=F, fixed=F is not None, sequence_registration=seq_reg, renderer=renderer
    )
    items = list(zip(frames, estimates, renders, scales, strict=True))
    reps = [
        upd.detect(f, estimate=E, render_mm=R, scale0=s)
        for f, E, R, s in (progress(items) if progress is not None else items)
    ]
    if cfg.change.min_views > 0:
        confirm_changes(reps, camera, cfg.change)
    for f, rep in zip(frames, reps, strict=True):
        upd.fuse(rep, f.rgb, keep_maps=keep_maps)
    report = upd.end_step()
    return upd.model, report


def _try_scale(render_mm: np.ndarray, estimate: np.ndarray, cfg: UpdateConfig) -> float | None:
    """The estimate's scale against the render, or None when too few pixels overlap."""
    try:
        return solve_scale(render_mm, estimate, cfg.change.threshold_mm)[0]
    except EmptyResultError:
        return None


def confirm_changes(reps: list[FrameReport], camera: Camera, cfg: ChangeConfig) -> None:
    """Multi-view check of a step's change masks, **in place** (batch mode).

    A changed pixel stays changed when at least ``cfg.min_views`` other frames that see
    its old surface point also see it removed, and they are at least ``cfg.min_agreement``
    of the frames that see it (:func:`chisel.change.multiview_support`). Depth errors of a
    monocular network differ from view to view, tissue removal does not: this is what
    keeps one frame's error from carving the model for good. The mask is cleaned again
    afterwards (components below the minimum area go).
    """
    used = np.array([r.used for r in reps], dtype=bool)
    if used.sum() < 2:
        return
    shape = camera.shape

    def stack(name: str, fill: float) -> np.ndarray:
        return np.stack(
            [getattr(r, name) if r.used else np.full(shape, fill, np.float32) for r in reps]
        )

    # A used report keeps its mask and pose until fused.
    masks = np.stack([cast(np.ndarray, r.mask) if r.used else np.zeros(shape, bool) for r in reps])
    poses = np.stack([cast(np.ndarray, r.T_world_from_cam) if r.used else np.eye(4) for r in reps])
    support, observed = multiview_support(
        masks, stack("m_t", np.nan), stack("m_raw", np.nan), camera, poses, used,
        np.array([r.threshold_mm if r.used else np.inf for r in reps]), cfg.visible_mm,
        cfg.contradict_fraction,
    )  # fmt: skip
    keep = (support >= cfg.min_views) & (support >= cfg.min_agreement * observed)
    for r, m, k in zip(reps, masks, keep, strict=True):
        if not r.used:
            continue
        new = clean_mask(m & k, cfg)
        r.unconfirmed_px = int(m.sum() - new.sum())
        r.mask = new


def _tracking_excess(F: np.ndarray, rcfg: RegistrationConfig) -> str:
    """Why the camera-side correction F is one the tracker cannot need ("" if it can)."""
    shift_mm, angle_deg = float(np.linalg.norm(F[:3, 3])), rotation_angle_deg(F[:3, :3])
    if shift_mm <= rcfg.tracking_accuracy_mm and angle_deg <= rcfg.tracking_accuracy_deg:
        return ""
    return (
        f"correction {shift_mm:.2f} mm / {angle_deg:.2f} deg exceeds the tracking accuracy "
        f"({rcfg.tracking_accuracy_mm} mm / {rcfg.tracking_accuracy_deg} deg)"
    )


def _hand_eye(
    renderer: ModelRenderer,
    camera: Camera,
    poses: list[np.ndarray],
    estimates: list[np.ndarray],
    scales: list[float | None],
    C_seq: np.ndarray,
    cfg: UpdateConfig,
    scale_free: bool,
) -> tuple[np.ndarray | None, dict]:
    """Camera-side correction F: robust mean of per-frame ICP corrections from ``C_seq``.

    A world-side correction cannot represent a constant hand-eye error for frames with
    different orientations; F can. Up to ``cfg.hand_eye_frames`` frames, evenly spaced
    over those with a scale, are registered without a prior (coarser point sampling),
    and the median of their camera-side corrections is F.
    """
    rcfg = cfg.registration
    usable = [i for i, s in enumerate(scales) if s is not None]
    if len(usable) > cfg.hand_eye_frames:
        pick = np.linspace(0, len(usable) - 1, cfg.hand_eye_frames).round().astype(int)
        usable = [usable[i] for i in pick]
    Fs, fits = [], []
    for i in usable:
        T, E, s0 = poses[i], estimates[i], float(cast(float, scales[i]))
        src = _points(camera, s0 * E, T, cfg.sequence_points)
        if len(src) < 10:
            continue
        sim = icp_similarity(src, T[:3, 3], renderer.index, C_seq, rcfg, estimate_scale=scale_free)
        res = check_result(
            sim.T_model_from_est, sim.fitness, sim.rmse_mm, "icp", src.mean(axis=0), rcfg, sim.scale
        )
        fits.append(sim.fitness if res.ok else 0.0)
        if res.ok:
            Fs.append(invert_rigid(T) @ res.T_model_from_est @ T)
    fitness = float(np.median(fits)) if fits else 0.0
    if not Fs:
        return None, {
            "ok": False, "frames": 0, "fitness_median": fitness,
            "reason": "no frame registered in the first pass",
        }  # fmt: skip
    F = robust_mean_transform(Fs)
    return F, {
        "ok": True, "frames": len(Fs), "fitness_median": fitness,
        "T_cam_from_corrected_cam": F.tolist(),
    }  # fmt: skip


def _sequence_registration(
    renderer: ModelRenderer,
    camera: Camera,
    poses: list[np.ndarray],
    estimates: list[np.ndarray],
    scales: list[float | None],
    cfg: UpdateConfig,
) -> tuple[np.ndarray, dict]:
    """RANSAC + ICP of the whole step's scaled estimates onto the model surface.

    scales : per frame, the estimate's scale (None = no overlap with the render: skipped).
    """
    pts = [
        _points(camera, s * E, T, cfg.sequence_points)
        for T, E, s in zip(poses, estimates, scales, strict=True)
        if s is not None
    ]
    src = np.concatenate(pts) if pts else np.empty((0, 3))
    if len(src) == 0:  # no frame, or every pixel masked out (tools, blood, a bad mask file)
        return np.eye(4), {"ok": False, "reason": "no valid pixel overlaps the model render"}
    lo, hi = src.min(axis=0) - 5.0, src.max(axis=0) + 5.0
    tv, tn = renderer.surface_points(lo, hi)
    if len(tv) < 10:
        return np.eye(4), {"ok": False, "reason": "no model surface near the estimate"}
    res = register_global(src, tv, tn, cfg.registration)
    out = res.to_dict()
    if not res.ok:
        log.warning(
            "sequence-level registration failed (%s); per-frame ICP from the tracker", res.reason
        )
        return np.eye(4), out
    return res.T_model_from_est, out
