"""The update: the streaming updater, and the fusion of a frame's detected change.

Per frame of a surgical step (paper, section 2; deviations in ``docs/updater.md``):

1. render M_t: the model's surface at step start (marching cubes, cached per step) ray
   cast at the frame's tracked pose (:mod:`chisel.render`);
2. the depth source gives an estimate of the new depth (possibly up to scale);
3. registration (unless switched off): a sequence-level RANSAC (FPFH) + robust ICP of all
   frames' scaled estimates to the model surface, then a camera-side hand-eye
   correction F (robust mean of per-frame ICP results), then per frame a robust 7-DoF
   ICP (pose and depth scale) from ``T_tracked @ F`` with a weak prior near it; frames
   whose fitness is too low are skipped and reported, never fused;
4. the registered estimate is re-projected into the frame at its tracked pose -> M',
   pixels lost in projection take M_t ("imputation");
5. change mask m = (M' - M_t) > threshold, cleaned (steps 3-5: :mod:`chisel.detect`);
6. masked integration of M' with ``w = 0 * W_t + m`` (:func:`fuse`, :mod:`chisel.fusion`).

Registration off (the paper's ablation): the estimate is only scaled to the render
(robust median of ratios) and used as M' directly. A whole step at once (the batch
prelude, multi-view confirmation): :mod:`chisel.batch`. File I/O lives in
``chisel.cli.cmd_model``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import cv2
import numba
import numpy as np

from chisel.carve import CARVE_DELETED, CARVE_FUSE, CARVE_NONE, carve_first_layer
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.core.geometry import Camera, check_rigid
from chisel.depth_source import estimate_depth, is_estimate, is_metric, reliable_pixels
from chisel.detect import (
    Context,
    Detection,
    FrameInput,
    HandEye,
    detect,
    scale_free,
    validate_estimate,
)
from chisel.fusion import check_pose_in_model, integrate
from chisel.io.sequence import Frame
from chisel.model import TsdfModel
from chisel.render import ModelRenderer
from chisel.reports import FrameReport, StepReport, shading_report
from chisel.shading import shading_translation, step_correction
from chisel.update_config import UpdateConfig

log = logging.getLogger(__name__)


def shading_translation_of(
    frame: Frame, render_mm: np.ndarray, camera: Camera, cfg: UpdateConfig
) -> np.ndarray | None:
    """The frame's shading translation under ``cfg`` (:func:`chisel.shading.
    shading_translation`), or None (no RGB, or no shift passed the gate)."""
    if frame.rgb is None:
        return None
    t = shading_translation(np.asarray(frame.rgb), render_mm, camera, frame.mask, cfg.shading)
    log.debug("frame %d: shading translation %s", frame.index, t)
    return t


def is_precise(threshold_mm: float, cfg: UpdateConfig, estimate: bool = False) -> bool:
    """Whether a frame's estimate can place a surface to within the change threshold: its
    noise did not raise its threshold (:func:`chisel.change.frame_threshold`) above
    ``cfg.change.threshold_mm`` and its source is not a learnt estimate
    (:func:`chisel.depth_source.is_estimate`), or ``cfg.noisy_carve`` is off."""
    if not cfg.noisy_carve:
        return True
    return not estimate and threshold_mm <= cfg.change.threshold_mm * (1.0 + 1e-6)


def carve_precise(
    threshold_mm: float, cfg: UpdateConfig, estimate: bool, reliable: np.ndarray | None
) -> bool | np.ndarray:
    """What :func:`chisel.carve.carve_first_layer` carves as precise: the whole frame
    (:func:`is_precise`), or a learnt estimate's ``reliable`` pixels when its frame's
    noise did not raise the threshold."""
    if is_precise(threshold_mm, cfg, estimate):
        return True
    if reliable is not None and is_precise(threshold_mm, cfg, False):
        return reliable
    return False


def fuse(
    model: TsdfModel,
    camera: Camera,
    det: Detection,
    cfg: UpdateConfig,
    reset: np.ndarray,
    rgb: np.ndarray | None = None,
    keep_mask: bool = False,
    votes: np.ndarray | None = None,
    estimate: bool = False,
    reliable: np.ndarray | None = None,
) -> FrameReport:
    """Carve a detected frame's change mask into ``model`` (in place): the frame's report.

    reset : (X, Y, Z) uint8, the step's voxels already reset (updated in place); rgb :
    (H, W, 3) uint8 colour of the frame (used when the model has colour); votes : (X, Y, Z)
    uint8, the step's deletion votes of noisy frames (``cfg.noisy_votes``; updated in
    place; None = a noisy frame deletes alone); estimate : the frame's depth source is a
    learnt estimate (:func:`chisel.depth_source.is_estimate`), carved as a noisy frame;
    reliable : (H, W) bool, the pixels where such an estimate declared itself reliable
    (:func:`chisel.depth_source.reliable_pixels`), carved as precise unless the frame's
    noise raised its threshold. With ``cfg.fill_unseen`` the estimate is also fused where
    the model shows no surface, and at the detection's confirmed ``fill`` pixels that
    carving did not fuse, into voxels it never observed. A frame not used (its scale could
    not be solved) only gets its report.
    """
    if not det.used:
        return FrameReport(
            det.index, False, det.reason, det.scale, det.registration,
            unconfirmed_px=det.unconfirmed_px, threshold_mm=det.typical_threshold_mm,
            threshold_per_mm=det.threshold_per_mm,
        )  # fmt: skip
    if det.mask is None or det.m_prime is None or det.m_t is None or det.T_world_from_cam is None:
        raise InvalidInputError("detection", f"frame {det.index}: a used detection has no maps")
    mask = fuse_mask = det.mask
    tol_mm = det.typical_threshold_mm
    deleted_px = voxels_deleted = uncarved_px = 0
    if cfg.carve == "deletion" and mask.any():
        # Deletion first: where the model already holds the surface behind the
        # removed layer, delete the layer and keep that surface; fuse the new
        # depth only where the model holds nothing behind.
        status, voxels_deleted = carve_first_layer(
            model, camera, det.T_world_from_cam, det.m_t, det.m_prime, mask, tol_mm,
            reset=reset, precise=carve_precise(tol_mm, cfg, estimate, reliable),
            votes=votes,
            noisy_votes=cfg.noisy_votes, noisy_layer_mm=cfg.noisy_layer_mm,
            noisy_max_depth_mm=cfg.noisy_max_depth_mm, rim_px=cfg.rim_px,
        )  # fmt: skip
        deleted_px = int((status == CARVE_DELETED).sum())
        fuse_mask = mask & (status == CARVE_FUSE)
        # The frame's change is what it carved: a pixel that carving left alone (a noisy
        # estimate ending inside held tissue, say) was judged unchanged after all.
        uncarved_px = int((mask & (status == CARVE_NONE)).sum())
        mask = mask & (status != CARVE_NONE)
    lateral = cv2.distanceTransform(fuse_mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    voxels_updated = voxels_deleted + integrate(
        model, camera, det.T_world_from_cam, det.m_prime, pixel_weight=fuse_mask, rgb=rgb,
        reset=reset, lateral_px=lateral,
    )  # fmt: skip
    if cfg.fill_unseen:
        # Where the model shows no surface the estimate fills its holes; it never
        # overwrites what the model observed (a hole in its surface mesh can lie in front
        # of observed tissue whose faces were dropped at the edge of the unobserved).
        with np.errstate(invalid="ignore"):
            unseen = ~np.isfinite(det.m_t) & (det.m_prime > 0) & ~fuse_mask
        if det.fill is not None:  # where other views confirm the estimate's surface
            unseen |= det.fill & ~fuse_mask
        if unseen.any():
            voxels_updated += integrate(
                model, camera, det.T_world_from_cam, det.m_prime, pixel_weight=unseen, rgb=rgb,
                reset=reset, unobserved_only=True,
            )  # fmt: skip
    valid = np.isfinite(det.m_t)
    return FrameReport(
        index=det.index,
        used=True,
        scale=det.scale,
        shift_mm=det.shift_mm,
        registration=det.registration,
        changed_fraction=float(mask.sum() / max(int(valid.sum()), 1)),
        voxels_updated=voxels_updated,
        unconfirmed_px=det.unconfirmed_px,
        threshold_mm=tol_mm,
        threshold_per_mm=det.threshold_per_mm,
        deleted_px=deleted_px,
        uncarved_px=uncarved_px,
        voxels_deleted=voxels_deleted,
        mask=mask if keep_mask else None,
        mask_T_world_from_cam=det.T_world_from_cam if keep_mask else None,
    )


def finish_step(
    model: TsdfModel, frames: list[FrameReport], sequence_registration: dict | None,
    cfg: UpdateConfig, pose_correction: dict | None = None,
) -> tuple[TsdfModel, StepReport]:  # fmt: skip
    """The step's end: its counter advances; raises :class:`EmptyResultError` when no
    frame could be used, unless ``cfg.allow_unused_step`` (the model is then kept)."""
    if not any(f.used for f in frames):
        reasons = sorted({f.reason for f in frames})[:5]
        message = f"no frame of the step could be used ({len(frames)} frames; reasons: {reasons})"
        if not cfg.allow_unused_step:
            raise EmptyResultError(message)
        log.warning("%s: the model is kept as it was", message)
    model = replace(model, step=model.step + 1)
    return model, StepReport.of(model.step, frames, sequence_registration, cfg, pose_correction)


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
    T_tracked @ F``, plus per-frame jitter (:class:`chisel.detect.HandEye`, kept across
    steps). A frame whose ICP fails is retried with RANSAC + ICP on its own points while
    F has no prior, less often while the retries keep failing (``UpdateConfig.frame_ransac``).
    """

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
        self._votes: np.ndarray | None = None
        self._frames: list[FrameReport] = []
        self._hand_eye = HandEye()
        # Per frame of the step, in order: its shading translation (the correction it was
        # rendered with plus its own shift), or None where it gave none.
        self._shading: list[np.ndarray | None] = []

    def begin_step(self, hand_eye: np.ndarray | None = None, fixed: bool = False) -> None:
        """Start a surgical step: M_t is the model as it is now.

        hand_eye : (4, 4) camera-side correction F (``T_corrected = T_tracked @ F``) to
        start from, e.g. from a sequence-level registration; fixed : use F as is for
        every frame instead of re-estimating it from the frames.
        """
        self._renderer = ModelRenderer(self.model)
        self._reset = np.zeros(self.model.shape, dtype=np.uint8)
        self._votes = np.zeros(self.model.shape, dtype=np.uint8)
        self._frames = []
        self._shading = []
        if hand_eye is not None:
            self._hand_eye.F = check_rigid(hand_eye, "hand_eye")
        self._hand_eye.fixed = fixed

    @property
    def hand_eye(self) -> np.ndarray:
        """(4, 4) current camera-side correction F (``T_corrected = T_tracked @ F``)."""
        return self._hand_eye.current()

    @property
    def renderer(self) -> ModelRenderer:
        if self._renderer is None:
            raise RuntimeError("call begin_step() before processing frames")
        return self._renderer

    def end_step(self) -> StepReport:
        """Finish the step: the model's step counter advances; returns the report."""
        if self._renderer is None:
            raise RuntimeError("end_step() without begin_step()")
        found = [t for t in self._shading if t is not None]
        correction = (
            shading_report(step_correction(found), len(found), len(self._frames)) if found else None
        )
        self.model, report = finish_step(self.model, self._frames, None, self.cfg, correction)
        self._renderer = None
        self._reset = self._votes = None
        return report

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
            self.cfg.occluder_margin_px,
        )

    def process(self, frame: Frame, keep_maps: bool = False) -> FrameReport:
        """Detect the change in one frame and carve it into the model: the frame's report.

        frame : tracked pose plus image and/or depth. A frame whose depth has no overlap
        with M_t is skipped (``used = False``) and leaves the model untouched; keep_maps :
        the report keeps the carved change mask.
        """
        F = self._shading_correction(len(self._shading))
        inp = self._prepare(frame, F)
        if F is None:
            return self._carve(inp, keep_maps)
        # The frame's own shading shift (for the frames after the next one) is measured
        # on a thread beside its carving, and both end before the call returns.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="chisel-shading") as pool:
            shift = pool.submit(self._shading_translation, inp, F)
            report = self._carve_beside_workers(inp, keep_maps)
            self._shading.append(shift.result())
        return report

    def process_stream(
        self, frames: Iterable[Frame], keep_maps: bool = False
    ) -> Iterator[FrameReport]:
        """:meth:`process` over ``frames`` in order, each frame's render of M_t and depth
        estimate running on a worker thread while the frame before it is detected and
        carved, and its shading shift (``UpdateConfig.shading``) on a second one.

        All three depend only on the frame, on M_t (the model's surface at step start,
        never on what earlier frames of the step carved) and on the shading shifts of the
        frames two or more before it: reports and model are those of :meth:`process`
        frame by frame. A frame's report is yielded once the next frame has arrived (or
        the frames have ended): one frame of latency, for a rate near the slowest of the
        three instead of their sum (a network's inference, the ray cast, the FFTs and
        numba's kernels release the GIL). Meanwhile numba's kernels run on the calling
        thread alone. ``frames`` may be a live source. The depth source is called from one
        worker thread, one frame at a time, so it must not depend on the caller's thread
        (TorchScript modules and Mitsuba ray casts do not). An error of frame i is raised
        after the reports of the frames before it.
        """

        def carve(prepared: Future[FrameInput]) -> FrameReport:
            return self._carve_beside_workers(prepared.result(), keep_maps)

        def shade(prepared: Future[FrameInput], F: np.ndarray) -> np.ndarray | None:
            return self._shading_translation(prepared.result(), F)

        first = len(self._shading)
        shifts: list[Future[np.ndarray | None]] = []

        def collect(upto: int) -> None:
            """Wait for the shifts of the stream's frames before ``upto``, in order."""
            while len(self._shading) < first + min(upto, len(shifts)):
                self._shading.append(shifts[len(self._shading) - first].result())

        with (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="chisel-depth") as pool,
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="chisel-shading") as shading,
        ):
            pending = None
            for k, frame in enumerate(frames):
                collect(max(k - 1, 0))
                F = self._shading_correction(first + k)
                job = pool.submit(self._prepare, frame, F)
                if F is not None:
                    shifts.append(shading.submit(shade, job, F))
                if pending is not None:
                    yield carve(pending)
                pending = job
            if pending is not None:
                yield carve(pending)
            collect(len(shifts))

    def _shading_correction(self, position: int) -> np.ndarray | None:
        """The camera-side correction F for the step's frame at ``position`` with
        ``UpdateConfig.shading`` on (None when off): the median of the shading
        translations of the frames two or more before it (:func:`chisel.shading.
        step_correction`; the batch takes all the step's frames). Not the frame just
        before, so that its shift can be measured while this frame is rendered
        (:meth:`process_stream`); a frame's own shift, which holds its jitter too, is
        never applied to it, as in the batch."""
        if not self.cfg.shading.align_by_shading:
            return None
        earlier = self._shading[: max(position - 1, 0)]
        return step_correction([t for t in earlier if t is not None])

    def _shading_translation(self, inp: FrameInput, F: np.ndarray) -> np.ndarray | None:
        """The frame's shading translation in the tracked camera's frame: the correction
        F it was rendered with plus its own shift from there; None where it gave none."""
        if inp.render_mm is None:  # _prepare always renders; kept for the type
            return None
        t = shading_translation_of(inp.frame, inp.render_mm, self.camera, self.cfg)
        return None if t is None else F[:3, 3] + t

    def _prepare(self, frame: Frame, F: np.ndarray | None = None) -> FrameInput:
        """The frame's checked tracked pose (moved by the shading correction F when given),
        M_t rendered there, the validated estimate and the pixels its source declared
        reliable (read on the thread that called it)."""
        T = check_pose_in_model(self.model, frame.T_world_from_cam, f"frame {frame.index} pose")
        if F is not None:
            T = T @ F
        R = self.renderer.render(self.camera, T)
        E = self.estimate(frame, R)
        return FrameInput(
            frame, T, E, R, reliable=reliable_pixels(self.depth_source, frame, E.shape)
        )

    def _carve_beside_workers(self, inp: FrameInput, keep_maps: bool) -> FrameReport:
        """:meth:`_carve` with numba's kernels on this thread alone (the setting is per
        thread): its OpenMP workers spin-wait between kernels and would take the core
        that a worker thread's inference or shading needs (the overlap then gained
        nothing)."""
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            return self._carve(inp, keep_maps)
        finally:
            numba.set_num_threads(threads)

    def _carve(self, inp: FrameInput, keep_maps: bool) -> FrameReport:
        """Detect a frame's change from its estimate and carve it into the model."""
        ctx = Context(
            self.camera, self.renderer, self.cfg, scale_free(self.cfg, self.depth_source),
            self.hand_eye, self._hand_eye.prior, self._hand_eye.may_retry(self.cfg.frame_ransac),
        )  # fmt: skip
        det = detect(inp, ctx)
        self._hand_eye.learn(det)
        rep = fuse(
            self.model, self.camera, det, self.cfg, self._reset_grid(), inp.frame.rgb, keep_maps,
            votes=self._votes, estimate=is_estimate(self.depth_source), reliable=inp.reliable,
        )  # fmt: skip
        self._frames.append(rep)
        return rep

    def _reset_grid(self) -> np.ndarray:
        if self._reset is None:
            raise RuntimeError("call begin_step() before processing frames")
        return self._reset
