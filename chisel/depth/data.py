"""Training data for the depth network: sequence folders -> in-memory frame tensors.

Inputs are sequence folders (``chisel.io.sequence``) with RGB and depth, named directly or
through a dataset index ``dataset.json`` (as written by ``python -m sim dataset``) that
lists sequence folders with the phantom seed each was rendered from. Splits are made by
phantom seed so that no phantom is seen in both training and validation; phantom seeds
0-99 are reserved for evaluation and refused by :func:`check_training_seeds`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import torch

from chisel.core.config import is_integer, show
from chisel.core.errors import EmptyResultError, InvalidInputError
from chisel.io.manifest import named_path, read_json_manifest
from chisel.io.sequence import Sequence

log = logging.getLogger(__name__)

DATASET_INDEX = "dataset.json"
RESERVED_EVAL_SEEDS = range(0, 100)
"""Phantom seeds of the evaluation set; the network must never train on them."""

MAX_PHANTOM_SEED = 2**63 - 1
"""Largest phantom seed: an int64, what numpy and torch hold a seed in."""

_SEED_KEYS = ("phantom_seed", "seed")
_PATH_KEYS = ("path", "sequence", "dir")
_Group = TypeVar("_Group", int, str)


@dataclass(frozen=True)
class SequenceRef:
    """A training sequence folder and the phantom it shows."""

    path: Path
    """Sequence folder."""
    seed: int | None
    """Phantom seed it was rendered from; None for real data or an unknown source."""

    @property
    def group(self) -> str:
        """Split key: the phantom seed, or the folder when the seed is unknown."""
        return f"seed:{self.seed}" if self.seed is not None else f"path:{self.path}"


def phantom_seed(value: Any, key: str, where: str | Path) -> int:
    """A phantom seed read from a JSON file: an integer in [0, ``MAX_PHANTOM_SEED``].

    Only a JSON integer is one: ``1000.9`` was read as phantom 1000 (``int()`` truncates),
    ``1e400`` (which JSON readers take for infinity) died of ``OverflowError``, and
    ``true`` or ``"1000"`` are not numbers. Raises :class:`InvalidInputError` naming
    ``where`` (the file and entry) and ``key``.
    """
    if is_integer(value) and 0 <= int(value) <= MAX_PHANTOM_SEED:
        return int(value)
    raise InvalidInputError(
        where, f"{key} must be an integer in [0, 2**63 - 1] (a JSON integer), got {show(value)}"
    )


def _seed_of(d: dict[str, Any], source: str) -> int | None:
    for key in _SEED_KEYS:
        if key in d and d[key] is not None:
            return phantom_seed(d[key], key, source)
    return None


def read_dataset_index(path: str | Path, allow_outside: bool = False) -> list[SequenceRef]:
    """Parse a ``dataset.json``: ``{"sequences": [{"path": ..., "phantom_seed": ...}, ...]}``.

    Relative paths are relative to the index's folder, and every path must lie inside it
    (links resolved) unless ``allow_outside`` (``--allow-outside-manifest``): the index is
    a manifest like any other. Also accepts entries that are plain path strings and
    ``seed`` for ``phantom_seed``.
    """
    path = Path(path)
    doc = read_json_manifest(path)
    entries = doc.get("sequences")
    if not isinstance(entries, list) or not entries:
        raise InvalidInputError(path, "expected a non-empty 'sequences' list")
    refs = []
    for i, entry in enumerate(entries):
        where = f"{path} sequences[{i}]"
        rel: object
        if isinstance(entry, str):
            rel, seed = entry, None
        elif isinstance(entry, dict):
            rel = next((entry[k] for k in _PATH_KEYS if k in entry), None)
            if not isinstance(rel, str):
                raise InvalidInputError(where, f"needs a path (one of {_PATH_KEYS}), got {entry}")
            seed = _seed_of(entry, where)
        else:
            raise InvalidInputError(where, f"expected a path or an object, got {entry!r}")
        seq_path = named_path(
            path, rel, f"sequences[{i}]", allow_outside=allow_outside, kind="folder"
        )
        refs.append(SequenceRef(seq_path, seed))
    return refs


def find_sequences(inputs: list[str | Path], allow_outside: bool = False) -> list[SequenceRef]:
    """Resolve dataset folders, ``dataset.json`` files and sequence folders to sequences
    (``allow_outside``: see :func:`read_dataset_index`).

    A sequence folder's phantom seed is read from its meta (``phantom_seed`` or ``seed``).
    """
    if not inputs:
        raise InvalidInputError("--data", "no dataset or sequence given")
    refs: list[SequenceRef] = []
    for item in inputs:
        p = Path(item)
        if p.is_file() and p.suffix == ".json":
            refs += read_dataset_index(p, allow_outside)
        elif (p / DATASET_INDEX).is_file():
            refs += read_dataset_index(p / DATASET_INDEX, allow_outside)
        elif (p / "sequence.json").is_file():
            refs.append(SequenceRef(p, _seed_of(Sequence(p).meta, f"{p / 'sequence.json'} meta")))
        else:
            raise InvalidInputError(
                p,
                f"neither a sequence folder (sequence.json) nor a dataset ({DATASET_INDEX})",
            )
    return refs


def check_training_seeds(refs: list[SequenceRef]) -> None:
    """Raise if any sequence shows a phantom reserved for evaluation (seeds 0-99)."""
    bad = sorted({r.seed for r in refs if r.seed is not None and r.seed in RESERVED_EVAL_SEEDS})
    if bad:
        raise InvalidInputError(
            "training data",
            f"phantom seeds {bad[:10]} are evaluation seeds ({RESERVED_EVAL_SEEDS.start}-"
            f"{RESERVED_EVAL_SEEDS.stop - 1}); train on seeds >= 1000",
        )


def held_out_groups(groups: list[_Group], val_fraction: float, seed: int) -> set[_Group]:
    """The groups (phantom seeds, folders) held out for validation, seeded.

    ``round(val_fraction * len(groups))`` of them, at least 1 when ``val_fraction > 0`` and
    there are >= 2, never all. ``groups`` must come in a fixed order (sorted): the draw
    depends on it.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise InvalidInputError("val_fraction", f"must be in [0, 1), got {val_fraction}")
    n_val = 0
    if val_fraction > 0 and len(groups) >= 2:
        n_val = min(len(groups) - 1, max(1, round(val_fraction * len(groups))))
    rng = np.random.default_rng(seed)
    return set(rng.choice(groups, size=n_val, replace=False).tolist()) if n_val else set()


def split_by_group(
    refs: list[SequenceRef], val_fraction: float, seed: int
) -> tuple[list[SequenceRef], list[SequenceRef]]:
    """Split sequences into (train, val) by phantom seed (or folder when unknown), seeded.

    ``round(val_fraction * groups)`` groups (at least 1 when ``val_fraction > 0`` and there
    are >= 2 groups) go to validation.
    """
    val_groups = held_out_groups(sorted({r.group for r in refs}), val_fraction, seed)
    train = [r for r in refs if r.group not in val_groups]
    val = [r for r in refs if r.group in val_groups]
    return train, val


@dataclass
class FrameSet:
    """Frames held in memory for training or evaluation."""

    rgb: torch.Tensor
    """(N, H, W, 3) uint8 RGB."""
    depth_mm: torch.Tensor
    """(N, H, W) float32 true z-depth, mm; 1.0 where invalid (never read there)."""
    valid: torch.Tensor
    """(N, H, W) bool, True where the depth is valid and the frame mask allows it."""
    sources: list[str]
    """``"<sequence folder>#<frame>"`` per frame."""

    def __len__(self) -> int:
        return int(self.rgb.shape[0])


def load_frames(
    refs: list[SequenceRef],
    size: tuple[int, int] | None = None,
    frame_step: int = 1,
    min_valid_fraction: float = 0.05,
) -> FrameSet:
    """Read RGB, depth and masks of every ``frame_step``-th frame into memory.

    size : (width, height) to resize to (RGB: area, depth and validity: nearest), or None
    to keep the native size (then every sequence must share it). Frames with fewer than
    ``min_valid_fraction`` valid pixels are skipped.
    """
    if frame_step < 1:
        raise InvalidInputError("frame_step", f"must be >= 1, got {frame_step}")
    rgbs, depths, valids, sources = [], [], [], []
    shape: tuple[int, int] | None = None if size is None else (size[1], size[0])
    for ref in refs:
        seq = Sequence(ref.path)
        if not (seq.has_rgb and seq.has_depth):
            raise InvalidInputError(
                ref.path,
                f"training needs RGB and depth (has_rgb={seq.has_rgb}, has_depth={seq.has_depth})",
            )
        if shape is None:
            shape = seq.camera.shape
        for i in range(0, len(seq), frame_step):
            rgb = seq.rgb(i)
            depth = seq.depth_mm(i)
            valid = np.isfinite(depth)
            mask = seq.mask(i)
            if mask is not None:
                valid &= mask
            if rgb.shape[:2] != shape:
                if size is None:
                    raise InvalidInputError(
                        ref.path,
                        f"frames are {rgb.shape[1]}x{rgb.shape[0]} but earlier sequences are "
                        f"{shape[1]}x{shape[0]}; pass a common training size",
                    )
                rgb = cv2.resize(rgb, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
                depth = cv2.resize(depth, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
                valid = cv2.resize(
                    valid.astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST
                ).astype(bool)
            if valid.mean() < min_valid_fraction:
                continue
            rgbs.append(rgb)
            depths.append(np.where(valid, depth, np.float32(1.0)).astype(np.float32))
            valids.append(valid)
            sources.append(f"{ref.path}#{i}")
    if not rgbs:
        raise EmptyResultError(
            f"no usable frame (>= {min_valid_fraction:.0%} valid depth) in {len(refs)} sequence(s)"
        )
    log.info("loaded %d frames from %d sequences", len(rgbs), len(refs))
    return FrameSet(
        rgb=torch.from_numpy(np.stack(rgbs)),
        depth_mm=torch.from_numpy(np.stack(depths)),
        valid=torch.from_numpy(np.stack(valids)),
        sources=sources,
    )


def downsample_targets(
    depth_mm: torch.Tensor, valid: torch.Tensor, size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth and validity on a coarser grid (the network's), area-averaged.

    depth_mm : (N, H, W) float mm. valid : (N, H, W) bool. size : (height, width).
    A coarse pixel is valid only if every fine pixel it covers is (no averaging across a
    mask or depth edge into nothing); its depth is the mean of those pixels.
    Returns (N, h, w) float32 depth (1.0 where invalid) and (N, h, w) bool.
    """
    if tuple(depth_mm.shape[1:]) == tuple(size):
        return depth_mm, valid
    v = valid.float()[:, None]
    d = torch.where(valid, depth_mm, torch.zeros_like(depth_mm)).float()[:, None]
    v_low = torch.nn.functional.interpolate(v, size=size, mode="area")[:, 0]
    d_low = torch.nn.functional.interpolate(d, size=size, mode="area")[:, 0]
    ok = v_low > 1.0 - 1e-4
    return torch.where(ok, d_low / v_low.clamp(min=1e-6), torch.ones_like(d_low)), ok


@dataclass(frozen=True)
class AugmentConfig:
    """Seeded photometric and flip augmentation applied per training sample."""

    hflip: float = 0.5
    """Probability of a horizontal flip."""
    vflip: float = 0.5
    """Probability of a vertical flip (an endoscope has no preferred 'up')."""
    brightness: float = 0.3
    """Gain drawn from U(1 - b, 1 + b)."""
    contrast: float = 0.2
    """Contrast factor drawn from U(1 - c, 1 + c) about the image mean."""
    channel_gain: float = 0.1
    """Per-channel gain drawn from U(1 - g, 1 + g) (white balance)."""
    noise_std: float = 3.0
    """Gaussian noise sigma drawn from U(0, noise_std), in 8-bit levels."""

    def __post_init__(self) -> None:
        for name in ("hflip", "vflip"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InvalidInputError(f"AugmentConfig.{name}", f"must be in [0, 1], got {v}")
        for name in ("brightness", "contrast", "channel_gain"):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                raise InvalidInputError(f"AugmentConfig.{name}", f"must be in [0, 1), got {v}")
        if self.noise_std < 0:
            raise InvalidInputError(
                "AugmentConfig.noise_std", f"must be >= 0, got {self.noise_std}"
            )


def augment(
    rgb: torch.Tensor,
    depth_mm: torch.Tensor,
    valid: torch.Tensor,
    cfg: AugmentConfig,
    gen: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Augment a batch with draws from ``gen`` (so a seed fixes the result).

    rgb : (B, H, W, 3) uint8. depth_mm : (B, H, W) float mm. valid : (B, H, W) bool.
    Returns (rgb float32 in [0, 255] (B, H, W, 3), depth_mm, valid), flipped alike.
    """
    b = rgb.shape[0]
    u = torch.rand(b, 9, generator=gen)
    x = rgb.float()
    hf = u[:, 0] < cfg.hflip
    vf = u[:, 1] < cfg.vflip
    if bool(hf.any()):
        x[hf] = x[hf].flip(2)
        depth_mm = depth_mm.clone()
        valid = valid.clone()
        depth_mm[hf] = depth_mm[hf].flip(2)
        valid[hf] = valid[hf].flip(2)
    if bool(vf.any()):
        x[vf] = x[vf].flip(1)
        depth_mm = depth_mm.clone()
        valid = valid.clone()
        depth_mm[vf] = depth_mm[vf].flip(1)
        valid[vf] = valid[vf].flip(1)
    gain = 1.0 + cfg.brightness * (2.0 * u[:, 2] - 1.0)
    contrast = 1.0 + cfg.contrast * (2.0 * u[:, 3] - 1.0)
    chan = 1.0 + cfg.channel_gain * (2.0 * u[:, 4:7] - 1.0)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * contrast.view(b, 1, 1, 1) + mean
    x = x * (gain.view(b, 1, 1, 1) * chan.view(b, 1, 1, 3))
    if cfg.noise_std > 0:
        sigma = cfg.noise_std * u[:, 7].view(b, 1, 1, 1)
        x = x + sigma * torch.randn(x.shape, generator=gen)
    return x.clamp(0.0, 255.0), depth_mm, valid
