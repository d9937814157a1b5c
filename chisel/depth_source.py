"""Pluggable depth sources: where the updater gets the new depth M_{t+1} of a frame.

The protocol
------------
A depth source is **any callable** ``source(frame) -> depth``:

* ``frame`` is a :class:`chisel.io.sequence.Frame` (``rgb`` (H, W, 3) uint8 when the
  sequence has images, ``depth_mm`` when it has depth, ``T_world_from_cam`` the tracked
  pose, ``mask`` the usable pixels, ``index`` the frame number);
* it returns an (H, W) float32 z-depth map on the frame's raw pixel grid, NaN (or <= 0)
  = invalid. The depth may be **up to an unknown per-frame scale** (a monocular
  network); the updater solves the scale against the model's render.

An optional attribute ``is_metric: bool`` declares the depth to be in millimetres
(ground truth, a depth sensor). Metric depth is checked for plausible units
(:func:`chisel.io.sequence.check_depth_mm` refuses depth that looks like metres); the scale
is still solved robustly so small calibration errors are absorbed. Sources without the
attribute are treated as scale-free.

A source that declares ``is_estimate = True`` is carved like a noisy estimate whatever
its frames' measured noise (:func:`is_estimate`): the change-aware network returns the
render itself where it sees no change, so its noise measured against the render is ~0
and its frames would carve as exact depth does, while a region it gets wrong deletes
tissue that other views would not confirm (docs/updater.md).

A learnt estimate may also say where it is reliable: after each call, its attribute
``last_reliable_px`` holds an (H, W) bool map of the pixels whose depth it places to
within the change threshold (None: nowhere known). The updater reads it right after the
call, on the same thread (:func:`reliable_pixels`), and carves those pixels as precise
depth, the rest as a noisy estimate (``chisel.carve.carve_first_layer``).

A source that declares ``wants_prior = True`` is called as ``source(frame, prior_mm=R)``
instead, with ``R`` the (H, W) float32 render of the model M_t at the frame's tracked pose
(mm, NaN = no surface), the render the updater makes anyway (the change-aware network,
``change-aware:CHECKPOINT``). :func:`estimate_depth` is the one place that calls a source.

Built-ins: :class:`GroundTruthDepth` (the sequence's own depth), :class:`SequenceDepth`
(depth maps of another sequence folder with the same frames), :class:`CallableDepth`
(wrap any user callable), and ``network:CHECKPOINT`` through ``chisel.depth`` (loaded
lazily; provides ``chisel.depth.load_depth_source(checkpoint) -> DepthSource``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from chisel.core.errors import InvalidInputError
from chisel.io.sequence import Frame, Sequence


@runtime_checkable
class DepthSource(Protocol):
    """``(frame: Frame) -> (H, W) float32 depth, NaN = invalid, possibly up to scale``."""

    def __call__(self, frame: Frame) -> np.ndarray: ...


class GroundTruthDepth:
    """The frame's own depth (``frame.depth_mm``): ground truth for synthetic data, mm."""

    is_metric = True

    def __call__(self, frame: Frame) -> np.ndarray:
        if frame.depth_mm is None:
            raise InvalidInputError(
                f"frame {frame.index}", "depth source 'gt' needs depth in the sequence, it has none"
            )
        return frame.depth_mm


class SequenceDepth:
    """Depth maps from another sequence folder with the same frame count.

    The depth is metric (mm) unless the folder says it is relative: ``chisel depth
    predict`` writes ``meta.depth_prediction.relative_depth = true``, and then the updater
    solves the scale, exactly as when the network is the depth source.
    """

    def __init__(
        self, path: str | Path, expected_frames: int | None = None, of: Sequence | None = None
    ) -> None:
        """``of``: the sequence being updated; the depth's camera and poses must be its own
        (depth of other frames, or through another camera, was accepted unseen); links out
        of the depth folder are read only if ``of`` allows them in its own."""
        self.sequence = Sequence(path, allow_outside=of is not None and of.allow_outside)
        if of is not None:
            expected_frames = len(of)
            _check_same_frames(self.sequence, of)
        if not self.sequence.has_depth:
            raise InvalidInputError(path, "depth-source sequence has no depth maps")
        prediction = self.sequence.meta.get("depth_prediction") or {}
        self.is_metric = not bool(prediction.get("relative_depth", False))
        if expected_frames is not None and len(self.sequence) != expected_frames:
            raise InvalidInputError(
                path,
                f"depth-source sequence has {len(self.sequence)} frames, the updated "
                f"sequence has {expected_frames}",
            )

    def __call__(self, frame: Frame) -> np.ndarray:
        return self.sequence.depth_mm(frame.index)


def _check_same_frames(depth: Sequence, of: Sequence) -> None:
    """Raise unless ``depth`` was taken with ``of``'s camera at ``of``'s poses."""
    a, b = depth.camera, of.camera
    if (a.width, a.height) != (b.width, b.height) or not (
        np.allclose(a.K, b.K, rtol=1e-6, atol=1e-6) and np.allclose(a.dist, b.dist, atol=1e-9)
    ):
        raise InvalidInputError(
            depth.path / "sequence.json",
            f"depth-source camera ({a.width}x{a.height}, fx {a.fx:g}) is not the camera of "
            f"{of.path} ({b.width}x{b.height}, fx {b.fx:g}): depth of other frames",
        )
    if len(depth.poses) == len(of.poses):
        moved = np.abs(depth.poses - of.poses).reshape(len(of.poses), -1).max(axis=1)
        bad = np.flatnonzero(moved > 1e-4)
        if bad.size:
            raise InvalidInputError(
                depth.path / "poses.txt",
                f"{bad.size} pose(s) differ from {of.path / 'poses.txt'} (first: frame "
                f"{int(bad[0])}, by {moved[bad[0]]:.3g}): depth of other frames",
            )


class CallableDepth:
    """Wrap a user callable ``fn(frame) -> depth``; ``metric`` declares millimetres."""

    def __init__(self, fn: Callable[[Frame], np.ndarray], metric: bool = False) -> None:
        if not callable(fn):
            raise InvalidInputError("depth_source", f"expected a callable, got {type(fn).__name__}")
        self.fn = fn
        self.is_metric = bool(metric)

    def __call__(self, frame: Frame) -> np.ndarray:
        return self.fn(frame)


def is_metric(source: object) -> bool:
    """True if ``source`` declares millimetre depth (``is_metric`` attribute)."""
    return bool(getattr(source, "is_metric", False))


def is_estimate(source: object) -> bool:
    """True if ``source`` declares ``is_estimate``: a learnt estimate whose errors are
    spatially structured, so its frames are carved as noisy ones (deletion votes, one layer;
    ``UpdateConfig.noisy_votes``) even when its measured noise is below the threshold."""
    return bool(getattr(source, "is_estimate", False))


def wants_prior(source: object) -> bool:
    """True if ``source`` declares ``wants_prior``: it takes the model's render as ``prior_mm``."""
    return bool(getattr(source, "wants_prior", False))


def estimate_depth(
    source: Callable[..., np.ndarray], frame: Frame, prior_mm: np.ndarray | None
) -> np.ndarray:
    """Call a depth source on ``frame``, handing it ``prior_mm`` (the model's render at the
    frame's tracked pose) when it :func:`wants_prior`; raises if it wants one and gets None."""
    if not wants_prior(source):
        return source(frame)
    if prior_mm is None:
        raise InvalidInputError(
            f"frame {frame.index}",
            f"depth source {source!r} needs the model's render at the frame's pose (prior_mm)",
        )
    return source(frame, prior_mm=prior_mm)


def reliable_pixels(source: object, frame: Frame, shape: tuple[int, ...]) -> np.ndarray | None:
    """The (H, W) bool map of the pixels ``source`` declared reliable in its last call
    (``last_reliable_px``), copied; None when it declares none. Call it right after the
    source, on the same thread. Raises unless the map is bool of ``shape`` (the estimate's)."""
    m = getattr(source, "last_reliable_px", None)
    if m is None:
        return None
    m = np.asarray(m)
    if m.dtype != np.bool_ or m.shape != tuple(shape):
        raise InvalidInputError(
            f"frame {frame.index}",
            f"depth source {source!r} declared its reliable pixels as a {m.shape} {m.dtype} "
            f"map; a {tuple(shape)} bool map (the estimate's size) is expected",
        )
    return m.copy()


def load_network_source(checkpoint: str | Path) -> DepthSource:
    """Load the project's depth network (``chisel.depth``) as a depth source."""
    try:
        depth_mod = importlib.import_module("chisel.depth")
    except ModuleNotFoundError as exc:
        if exc.name not in ("chisel.depth", "chisel"):
            raise
        raise InvalidInputError(
            "--depth-source",
            "network depth needs the chisel.depth package, which is not available in "
            "this installation; use 'gt' or 'sequence:PATH', or pass a callable from Python",
        ) from None
    loader = getattr(depth_mod, "load_depth_source", None)
    if loader is None:
        raise InvalidInputError(
            "--depth-source",
            "chisel.depth provides no load_depth_source(checkpoint) -> DepthSource function",
        )
    return loader(Path(checkpoint))


def load_change_aware_source(checkpoint: str | Path) -> DepthSource:
    """Load the change-aware network (``chisel.depth.change_source``) as a depth source."""
    try:
        module = importlib.import_module("chisel.depth.change_source")
    except ModuleNotFoundError as exc:
        if exc.name not in ("chisel.depth", "chisel.depth.change_source", "chisel"):
            raise
        raise InvalidInputError(
            "--depth-source",
            "change-aware depth needs the chisel.depth package, not installed here",
        ) from None
    return module.load_change_aware_source(Path(checkpoint))


def depth_source_from_spec(spec: str, sequence: Sequence | None = None) -> DepthSource:
    """Parse ``gt`` | ``sequence:PATH`` | ``network:CHECKPOINT`` |
    ``change-aware:CHECKPOINT`` into a depth source."""
    if spec == "gt":
        if sequence is not None and not sequence.has_depth:
            raise InvalidInputError(
                sequence.path, "--depth-source gt needs depth maps in the sequence, it has none"
            )
        return GroundTruthDepth()
    kind, sep, arg = spec.partition(":")
    if sep and arg and kind == "sequence":
        return SequenceDepth(arg, of=sequence)
    if sep and arg and kind == "network":
        return load_network_source(arg)
    if sep and arg and kind == "change-aware":
        return load_change_aware_source(arg)
    raise InvalidInputError(
        "--depth-source",
        "expected 'gt', 'sequence:PATH', 'network:CHECKPOINT' or 'change-aware:CHECKPOINT', "
        f"got {spec!r}",
    )
