"""The change-aware network as the updater's depth source, and its TorchScript export.

:class:`ChangeAwareDepthSource` declares ``wants_prior = True``: the updater calls it as
``source(frame, prior_mm=R)`` with ``R`` the model's render M_t at the frame's tracked pose
(the render it makes anyway; ``chisel.depth_source.estimate_depth`` is the one call site
rule). Its depth is metric (``is_metric = True``): no scale is solved.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from chisel.core.atomic import atomic_path
from chisel.core.errors import InvalidInputError
from chisel.depth.change_aware import KIND, ChangeAwarePredictor, load_change_checkpoint
from chisel.depth.checkpoint import KIND_MONOCULAR, CheckpointError, nonfinite_tensors
from chisel.depth.infer import is_torchscript_file
from chisel.depth.train import resolve_device
from chisel.io.sequence import Frame


@contextmanager
def fp32_convolutions(device: torch.device) -> Iterator[None]:
    """Full float32 convolutions on CUDA while the network runs.

    torch lets cuDNN round convolutions to TF32 by default. The network's change decision
    is a threshold (p >= 0.5), and on an H200 TF32 flipped it at 52 of 655 360 pixels of
    8 frames, up to 9 mm apart; in float32 the GPU gave the CPU's depths to 1e-4 mm with
    no flip (docs/depth.md, "On a GPU"). A network this small loses nothing by it.
    Anything that runs the exported module on CUDA itself (a batch) wraps it in this."""
    if device.type != "cuda":
        yield
        return
    previous = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32 = previous


class ChangeAwareDepthSource:
    """``source(frame, prior_mm=R)`` -> (H, W) float32 depth in mm, NaN = invalid.

    prior_mm : (H, W) float32 z-depth of the model's render at the frame's tracked pose,
    mm, NaN = no surface; it must have the frame's size. The output is NaN where the
    render is invalid or outside ``frame.mask``. After each call ``last_change_probability``
    holds the network's (H, W) change probability (the confidence head).
    """

    is_metric = True
    wants_prior = True
    needs_rgb = True
    is_estimate = True

    def __init__(
        self, module: torch.nn.Module | torch.jit.ScriptModule, device: str = "cpu",
        description: str = "",
    ) -> None:  # fmt: skip
        self.device = resolve_device(device)
        module = module.to(self.device).eval()
        if isinstance(module, torch.jit.ScriptModule):
            # Streaming runs the network once per frame: freezing folds batch norm into
            # the convolutions (and on CPU picks oneDNN kernels), ~10 % of a frame's
            # inference; outputs move by ~1e-5 mm.
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", "`torch.jit", DeprecationWarning)
                module = torch.jit.optimize_for_inference(torch.jit.freeze(module))
        self.module = module
        self.description = description
        self.last_change_probability: np.ndarray | None = None

    def predict(self, rgb: np.ndarray, prior_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rgb : (H, W, 3) uint8; prior_mm : (H, W) float mm, NaN = invalid ->
        ((H, W) float32 depth mm, (H, W) float32 change probability)."""
        rgb = np.asarray(rgb)
        prior = np.asarray(prior_mm, dtype=np.float32)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise InvalidInputError(
                "rgb", f"expected (H, W, 3) uint8 RGB, got {rgb.shape} {rgb.dtype}"
            )
        if prior.shape != rgb.shape[:2]:
            raise InvalidInputError(
                "prior_mm",
                f"the prior render is {prior.shape[1] if prior.ndim > 1 else '?'}x"
                f"{prior.shape[0] if prior.ndim else '?'} but the frame is "
                f"{rgb.shape[1]}x{rgb.shape[0]}: render the model at the frame's own size",
            )
        with torch.inference_mode(), fp32_convolutions(self.device):
            depth, p = self.module(
                torch.from_numpy(np.ascontiguousarray(rgb))[None].to(self.device),
                torch.from_numpy(np.ascontiguousarray(prior))[None].to(self.device),
            )
        return depth[0].float().cpu().numpy(), p[0].float().cpu().numpy()

    def __call__(self, frame: Frame, prior_mm: np.ndarray | None = None) -> np.ndarray:
        if prior_mm is None:
            raise InvalidInputError(
                f"frame {frame.index}",
                "the change-aware depth source needs the model's render at the frame's pose "
                "(prior_mm); use it through the updater (ChiselUpdater / update_step), which "
                "hands it the render",
            )
        if frame.rgb is None:
            raise InvalidInputError(
                f"frame {frame.index}", "the change-aware network needs the frame's RGB image"
            )
        depth, p = self.predict(frame.rgb, prior_mm)
        if frame.mask is not None:
            depth[~frame.mask] = np.nan
        self.last_change_probability = p
        return depth

    def __repr__(self) -> str:
        return f"ChangeAwareDepthSource({self.description}, {self.device})"


def _script(predictor: ChangeAwarePredictor) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "`torch.jit", DeprecationWarning)
        return torch.jit.script(predictor)


def load_change_aware_source(
    path: str | Path, device: str = "cpu", script: bool = True
) -> ChangeAwareDepthSource:
    """A change-aware depth source from a checkpoint or its TorchScript export.

    A monocular checkpoint or export is refused with :class:`CheckpointError` naming both
    kinds (an export's kind is its ``kind`` attribute; monocular exports have none).
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "change-aware depth model file does not exist")
    if is_torchscript_file(path):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "`torch.jit", DeprecationWarning)
            try:
                module = torch.jit.load(str(path), map_location="cpu")
            except RuntimeError as exc:
                raise CheckpointError(path, f"cannot load TorchScript model: {exc}") from None
        kind = getattr(module, "kind", KIND_MONOCULAR)
        if kind != KIND:
            raise CheckpointError(
                path,
                f"this is a {kind!r} TorchScript depth model, but a {KIND!r} model is expected "
                "here (export one with chisel depth export --kind change-aware)",
            )
        tensors = dict(module.named_parameters()) | dict(module.named_buffers())
        bad = nonfinite_tensors(tensors)
        if bad:
            raise CheckpointError(path, f"{len(bad)} weight tensor(s) hold NaN/inf, e.g. {bad[:3]}")
        return ChangeAwareDepthSource(module, device, f"torchscript {path}")
    net, _ = load_change_checkpoint(path)
    predictor = ChangeAwarePredictor(net).eval()
    if script:
        return ChangeAwareDepthSource(_script(predictor), device, f"checkpoint {path} (scripted)")
    return ChangeAwareDepthSource(predictor, device, f"checkpoint {path}")


def export_change_aware(predictor: ChangeAwarePredictor, out: str | Path) -> Path:
    """TorchScript export (``.pt``/``.ts``), atomically: uint8 (B, H, W, 3) RGB and
    (B, H, W) float32 prior mm -> (depth mm, change probability), each (B, H, W)."""
    out = Path(out)
    if out.suffix.lower() not in (".pt", ".ts"):
        raise InvalidInputError(
            out, f"change-aware export is TorchScript (.pt/.ts), got {out.suffix!r}"
        )
    scripted = _script(predictor.cpu().eval())
    with atomic_path(out) as tmp:
        scripted.save(str(tmp))
    return out
