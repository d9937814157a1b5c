"""Running a trained depth network: the updater's depth source, prediction, export.

A *depth source* is any callable ``(frame: chisel.io.sequence.Frame) -> (H, W) float32``
depth (NaN = invalid, possibly up to scale). :func:`load_depth_source` turns a checkpoint
(``.pt`` from ``chisel depth train``) or an exported TorchScript file into one.
"""

from __future__ import annotations

import logging
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from chisel.core.atomic import atomic_path
from chisel.core.errors import InvalidInputError
from chisel.depth.checkpoint import CheckpointError, load_checkpoint, nonfinite_tensors
from chisel.depth.metrics import DepthMetrics, MetricAccumulator
from chisel.depth.network import DepthPredictor
from chisel.depth.train import resolve_device
from chisel.io.sequence import Frame, Sequence, SequenceWriter

log = logging.getLogger(__name__)


class NetworkDepthSource:
    """A depth source backed by a :class:`DepthPredictor` (eager or TorchScript).

    ``source(frame)`` -> (H, W) float32 relative depth, NaN outside ``frame.mask``.
    ``source.predict(rgb)`` does the same on bare (H, W, 3) uint8 RGB without a mask.
    The depth is relative (``is_metric = False``): the updater solves its scale.
    """

    is_metric = False

    def __init__(
        self,
        module: torch.nn.Module | torch.jit.ScriptModule,
        device: str = "cpu",
        description: str = "",
        path: str | Path | None = None,
    ) -> None:
        self.device = resolve_device(device)
        self.module = module.to(self.device).eval()
        self.description = description
        self.path = path  # the model file, named when its output breaks the contract

    def predict_batch(self, rgb: np.ndarray) -> np.ndarray:
        """rgb : (B, H, W, 3) uint8 -> (B, H, W) float32 relative depth (> 0)."""
        arr = np.asarray(rgb)
        if arr.dtype != np.uint8 or arr.ndim != 4 or arr.shape[3] != 3:
            raise InvalidInputError(
                "rgb", f"expected (B, H, W, 3) uint8 RGB, got {arr.shape} {arr.dtype}"
            )
        with torch.inference_mode():
            out = self.module(torch.from_numpy(np.ascontiguousarray(arr)).to(self.device))
        self._check_output(out, arr.shape)
        return out.float().cpu().numpy()

    def _check_output(self, out: object, shape: tuple[int, ...]) -> None:
        """Refuse, naming the model file, an output that is not a (B, H, W) real tensor
        for ``shape`` = (B, H, W, 3) input (a tuple, a number, another batch or size)."""
        want = tuple(shape[:3])
        source = self.path if self.path is not None else (self.description or "depth model")
        if not isinstance(out, torch.Tensor):
            raise InvalidInputError(
                source,
                f"the depth model returned an object of type {type(out).__name__}, not a "
                f"tensor; expected a (B, H, W) float depth tensor of shape {want} for "
                f"(B, H, W, 3) input of shape {tuple(shape)}",
            )
        if out.is_complex() or out.dtype == torch.bool or tuple(out.shape) != want:
            raise InvalidInputError(
                source,
                f"the depth model returned a {out.dtype} tensor of shape {tuple(out.shape)}; "
                f"expected (B, H, W) float depth of shape {want} for (B, H, W, 3) input of "
                f"shape {tuple(shape)}",
            )

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        """rgb : (H, W, 3) uint8 -> (H, W) float32 relative depth (> 0)."""
        arr = np.asarray(rgb)
        if arr.ndim != 3:
            raise InvalidInputError("rgb", f"expected (H, W, 3) uint8 RGB, got shape {arr.shape}")
        return self.predict_batch(arr[None])[0]

    def __call__(self, frame: Frame) -> np.ndarray:
        if frame.rgb is None:
            raise InvalidInputError(
                f"frame {frame.index}", "the depth network needs the frame's RGB image"
            )
        depth = self.predict(frame.rgb)
        if frame.mask is not None:
            depth[~frame.mask] = np.nan
        return depth

    def __repr__(self) -> str:
        return (
            f"NetworkDepthSource({self.description or type(self.module).__name__}, {self.device})"
        )


def is_torchscript_file(path: str | Path) -> bool:
    """True if ``path`` is a TorchScript archive (it has a ``code/`` folder inside)."""
    try:
        with zipfile.ZipFile(path) as zf:
            return any("/code/" in name for name in zf.namelist())
    except (zipfile.BadZipFile, OSError):
        return False


def load_predictor(path: str | Path) -> tuple[DepthPredictor, dict[str, Any]]:
    """Eager :class:`DepthPredictor` (CPU, eval) and the info stored with a checkpoint."""
    net, info = load_checkpoint(path)
    return DepthPredictor(net).eval(), info


def load_depth_source(
    path: str | Path, device: str = "cpu", script: bool = True
) -> NetworkDepthSource:
    """A depth source from a checkpoint (``chisel depth train``) or a TorchScript export.

    path : ``.pt`` checkpoint, or a TorchScript file from ``chisel depth export``
    (detected from its contents). device : "cpu" or "cuda[:N]".
    script : run a checkpoint through ``torch.jit.script`` (faster on CPU); False runs
    the eager module.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "depth model file does not exist")
    if is_torchscript_file(path):
        try:
            with warnings.catch_warnings():
                # torch >= 2.10 flags TorchScript as deprecated; it is still the format
                # that runs without Python-side model code, which is why we export it.
                warnings.filterwarnings("ignore", "`torch.jit", DeprecationWarning)
                module = torch.jit.load(str(path), map_location="cpu")
        except RuntimeError as exc:
            raise CheckpointError(path, f"cannot load TorchScript model: {exc}") from None
        tensors = dict(module.named_parameters()) | dict(module.named_buffers())
        bad = nonfinite_tensors(tensors)
        if bad:
            raise CheckpointError(
                path,
                f"{len(bad)} weight tensor(s) hold NaN/inf, e.g. {bad[:3]}: the network "
                "would predict no valid depth",
            )
        return NetworkDepthSource(module, device, f"torchscript {path}", path)
    predictor, _ = load_predictor(path)
    if script:
        # The scripted module gives the same numbers and ran ~1.7x faster than eager on
        # this 2-core CPU (benchmarks/bench_depth.py), mostly less Python overhead.
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "`torch.jit", DeprecationWarning)
            scripted: torch.nn.Module = torch.jit.script(predictor)
        return NetworkDepthSource(scripted, device, f"checkpoint {path} (scripted)", path)
    return NetworkDepthSource(predictor, device, f"checkpoint {path}", path)


def predict_sequence(
    source: Any,
    sequence: Sequence,
    out: str | Path,
    meta: dict[str, Any] | None = None,
    progress: bool = False,
) -> Path:
    """Write a NEW sequence folder: ``sequence``'s RGB, poses and masks, predicted depth.

    source : a depth source (callable ``Frame -> (H, W) float32``, NaN = invalid).
    meta : added to the new sequence's meta under ``"depth_prediction"``.
    The folder appears atomically; an existing ``out`` is replaced only on success.
    """
    out = Path(out)
    if out.resolve() == sequence.path.resolve():
        raise InvalidInputError(out, "output must be a new folder, not the input sequence")
    if not sequence.has_rgb:
        raise InvalidInputError(sequence.path, "sequence has no RGB to predict depth from")
    new_meta = dict(sequence.meta)
    new_meta["depth_prediction"] = {
        "source_sequence": str(sequence.path),
        "source_had_depth": bool(sequence.has_depth),
        **(meta or {}),
    }
    with SequenceWriter(
        out,
        sequence.camera,
        meta=new_meta,
        camera_mask=sequence.camera_mask,
        undistorted=sequence.undistorted,
    ) as w:
        for i in tqdm(range(len(sequence)), desc="depth predict", disable=not progress):
            f = sequence.frame(i, rgb=True, depth=False)
            depth = np.asarray(source(f), dtype=np.float32)
            sequence.camera.check_image(depth, f"predicted depth of frame {i}")
            w.add(
                Frame(
                    index=i,
                    T_world_from_cam=f.T_world_from_cam,
                    rgb=f.rgb,
                    depth_mm=depth,
                    mask=f.mask if sequence.has_mask else None,
                    T_world_from_cam_true=f.T_world_from_cam_true,
                )
            )
    return out


def evaluate_source(source: Any, sequences: list[Sequence]) -> DepthMetrics:
    """Median-scaled metrics of a depth source against the sequences' own depth.

    Pixels are scored where the true depth is valid and the frame mask allows them.
    """
    acc = MetricAccumulator()
    for seq in sequences:
        if not (seq.has_rgb and seq.has_depth):
            raise InvalidInputError(seq.path, "evaluation needs RGB and depth")
        for f in seq:
            assert f.depth_mm is not None  # seq.has_depth
            acc.add(source(f), f.depth_mm, f.mask)
    return acc.result()


def export_model(
    predictor: DepthPredictor, out: str | Path, example_hw: tuple[int, int] = (256, 320)
) -> Path:
    """Export ``predictor`` (uint8 (B, H, W, 3) -> (B, H, W) depth) to ``out``, atomically.

    ``.pt``/``.ts``: TorchScript (``torch.jit.script``; any input size).
    ``.onnx``: ONNX with dynamic batch/height/width; needs the ``onnx`` package.
    example_hw : (height, width) of the example input used to trace the ONNX graph.
    """
    out = Path(out)
    predictor = predictor.cpu().eval()
    suffix = out.suffix.lower()
    if suffix in (".pt", ".ts"):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "`torch.jit", DeprecationWarning)
            scripted = torch.jit.script(predictor)
        with atomic_path(out) as tmp:
            scripted.save(str(tmp))
        return out
    if suffix == ".onnx":
        try:
            import onnx  # noqa: F401  (torch's exporter needs it)
        except ImportError:
            raise InvalidInputError(
                out,
                "ONNX export needs the 'onnx' package (pip install onnx); TorchScript "
                "(.pt) export works without it",
            ) from None
        example = torch.zeros((1, *example_hw, 3), dtype=torch.uint8)
        with atomic_path(out) as tmp:
            torch.onnx.export(
                predictor,
                (example,),
                str(tmp),
                input_names=["rgb"],
                output_names=["depth"],
                dynamic_axes={
                    "rgb": {0: "batch", 1: "height", 2: "width"},
                    "depth": {0: "batch", 1: "height", 2: "width"},
                },
                dynamo=False,
            )
        return out
    raise InvalidInputError(
        out, f"export format from suffix {suffix!r}: expected .pt, .ts or .onnx"
    )
