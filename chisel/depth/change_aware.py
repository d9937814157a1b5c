"""The change-aware depth network: the frame plus the model's render in, metric depth out.

A monocular network must guess shape and scale from one image. At update time we also
hold the model's depth render M_t at the frame's tracked pose: metric, and correct
wherever nothing changed. :class:`ChangeNet` sees both (RGB, the render's log-depth about
its median, the render's validity) and predicts a per-pixel **log-ratio correction** to
the render plus a **change logit**:

    p_change = sigmoid(c)
    depth_mm = prior_mm * exp(p_change * r)   where p_change >= CHANGE_DECISION_P (0.5),
                                              else prior_mm
                                              (NaN where the render is invalid)

The head starts at zero, so an untrained network returns the render itself; training only
has to learn where the render is no longer true and how much deeper the surface lies
there. The output is metric by construction (``is_metric = True`` as a depth source).

The network runs at ``input_scale`` of the frame (default 1/2: 160x128 for 320x256); its
correction is upsampled (bilinear) and applied to the full-resolution render, so
unchanged tissue keeps the render's full detail. :class:`ChangeAwarePredictor` wraps the
network with the normalisation and is what is scripted, exported and run.

Checkpoints share the monocular network's file format (``chisel.depth.checkpoint``) with
``"kind": "change-aware"``; a checkpoint of one kind given where the other is expected is
refused naming both kinds.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from chisel.core.config import config_from_dict
from chisel.core.errors import InvalidInputError
from chisel.depth.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    KIND_CHANGE_AWARE,
    CheckpointError,
    checkpoint_info,
    fill_weights,
    nonfinite_tensors,
    read_checkpoint,
    write_checkpoint_files,
)
from chisel.depth.network import check_rgb_normalisation, conv_bn_relu

KIND = KIND_CHANGE_AWARE
"""The ``kind`` recorded in change-aware checkpoints and TorchScript exports."""

DEFAULT_CHANGE_CHECKPOINT = Path(__file__).with_name("checkpoints") / "change_aware.pt"
"""The change-aware checkpoint shipped with the package (command in its ``.json``)."""


@dataclass(frozen=True)
class ChangeNetConfig:
    """Architecture of :class:`ChangeNet`; stored in every checkpoint (JSON-able)."""

    widths: tuple[int, ...] = (8, 16, 32, 48)
    """Channels per level; level k runs at 1/2**k of the network's input (level 0 = the
    network's own resolution, ``input_scale`` of the frame). The narrow first level keeps
    the full-resolution work small (85 k parameters in all)."""
    input_scale: float = 0.5
    """The network sees the frame and render resized by this factor (area filter); its
    correction is upsampled back. 0.5: 320x256 -> 160x128."""
    max_log_correction: float = 1.5
    """|r| is bounded by this (tanh): depth stays within exp(+-1.5) = 0.22x-4.5x of the
    render, so the output is finite and positive whatever the weights."""
    rgb_mean: tuple[float, float, float] = (0.5, 0.5, 0.5)
    """Per-channel mean subtracted from RGB scaled to [0, 1]."""
    rgb_std: tuple[float, float, float] = (0.25, 0.25, 0.25)
    """Per-channel divisor applied after the mean."""

    def __post_init__(self) -> None:
        widths = tuple(int(w) for w in self.widths)
        object.__setattr__(self, "widths", widths)
        object.__setattr__(self, "input_scale", float(self.input_scale))
        object.__setattr__(self, "max_log_correction", float(self.max_log_correction))
        object.__setattr__(self, "rgb_mean", tuple(float(m) for m in self.rgb_mean))
        object.__setattr__(self, "rgb_std", tuple(float(s) for s in self.rgb_std))
        if not 2 <= len(widths) <= 6 or any(w < 1 for w in widths):
            raise InvalidInputError(
                "ChangeNetConfig.widths", f"need 2-6 positive widths, got {widths}"
            )
        if not 0.1 <= self.input_scale <= 1.0:
            raise InvalidInputError(
                "ChangeNetConfig.input_scale", f"must be in [0.1, 1], got {self.input_scale}"
            )
        if not 0.0 < self.max_log_correction <= 5.0:
            raise InvalidInputError(
                "ChangeNetConfig.max_log_correction",
                f"must be in (0, 5], got {self.max_log_correction}",
            )
        check_rgb_normalisation(self.rgb_mean, self.rgb_std, "ChangeNetConfig")

    @property
    def stride(self) -> int:
        """The network's input is padded to a multiple of this."""
        return 2 ** (len(self.widths) - 1)

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "config") -> ChangeNetConfig:
        return config_from_dict(cls, d, source)


IN_CHANNELS = 5
"""RGB (3, normalised), the render's log-depth about its median (0 where invalid), and
the render's validity (fraction of valid pixels per network pixel)."""


class ChangeNet(nn.Module):
    """A small U-Net: (B, 5, h, w) -> (B, 2, h, w) = (log-ratio correction, change logit).

    h and w must be multiples of ``config.stride``. The head is zero-initialised: an
    untrained network's correction is 0 (output = the render) and its change logit 0.
    """

    def __init__(self, config: ChangeNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or ChangeNetConfig()
        w = self.config.widths
        self.stem = nn.Sequential(conv_bn_relu(IN_CHANNELS, w[0]), conv_bn_relu(w[0], w[0]))
        self.down = nn.ModuleList(
            [nn.Sequential(conv_bn_relu(w[k], w[k + 1], stride=2), conv_bn_relu(w[k + 1], w[k + 1]))
             for k in range(len(w) - 1)]
        )  # fmt: skip
        self.up = nn.ModuleList(
            [conv_bn_relu(w[k + 1] + w[k], w[k]) for k in range(len(w) - 2, -1, -1)]
        )
        self.head = nn.Conv2d(w[0], 2, 3, 1, 1)
        nn.init.zeros_(self.head.weight)
        assert self.head.bias is not None  # Conv2d has a bias by default
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.stem(x)
        skips: list[torch.Tensor] = [y]
        for stage in self.down:
            y = stage(y)
            skips.append(y)
        n = len(skips)
        for i, block in enumerate(self.up):
            skip = skips[n - 2 - i]
            y = F.interpolate(
                y, size=(skip.shape[2], skip.shape[3]), mode="bilinear", align_corners=False
            )
            y = block(torch.cat([y, skip], dim=1))
        return self.head(y)


CHANGE_DECISION_P = 0.5
"""Change probability from which the network's correction is applied (below it the
render comes out unchanged): the boundary its cross-entropy was trained on. A higher one
(0.7, for the asymmetry that a deletion is never undone while a missed removal stays open
to other frames) was measured on the `table` run: on phantom seeds 0-4 the row's error
fell (0.282 -> 0.244 of no update), on held-out seeds 5-7 it rose (0.226 -> 0.236), and
the removed-tissue Dice fell on both (docs/results.md, thirteenth session). Not taken."""


class ChangeAwarePredictor(nn.Module):
    """uint8 RGB and the render in, metric depth and change probability out.

    forward(rgb, prior_mm):
      rgb : (B, H, W, 3) uint8 (or float in [0, 255]); prior_mm : (B, H, W) float32 z-depth
      of the model's render at the tracked pose, mm, NaN (or <= 0) = invalid.
      Returns ``(depth_mm, p_change)``, both (B, H, W) float32: depth = prior *
      exp(p_change * r) where p_change >= ``decision_p``, else the prior; NaN where the
      render is invalid; p_change in [0, 1].
    decision_p : :data:`CHANGE_DECISION_P` by default; kept in the scripted module, so an
      export carries the decision it was made with.
    This is the module that is scripted, exported (TorchScript) and run.
    """

    def __init__(self, net: ChangeNet, decision_p: float = CHANGE_DECISION_P) -> None:
        super().__init__()
        if not 0.0 < decision_p < 1.0:
            raise InvalidInputError("decision_p", f"must be in (0, 1), got {decision_p}")
        self.net = net
        self.decision_p = float(decision_p)
        cfg = net.config
        self.kind = KIND
        self.stride = int(cfg.stride)
        self.input_scale = float(cfg.input_scale)
        self.max_log_correction = float(cfg.max_log_correction)
        self.register_buffer("mean", torch.tensor(cfg.rgb_mean).view(1, 3, 1, 1) * 255.0)
        self.register_buffer("std", torch.tensor(cfg.rgb_std).view(1, 3, 1, 1) * 255.0)

    def net_size(self, h: int, w: int) -> tuple[int, int]:
        """(height, width) the network works at for an (h, w) frame."""
        if self.input_scale == 1.0:
            return h, w
        return max(1, int(round(h * self.input_scale))), max(1, int(round(w * self.input_scale)))

    def raw(self, rgb: torch.Tensor, prior_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(r, c): log-ratio correction and change logit, (B, 1, H, W) each, at full size."""
        if rgb.dim() != 4 or rgb.shape[3] != 3:
            raise ValueError("ChangeAwarePredictor expects (B, H, W, 3) RGB")
        if (
            prior_mm.dim() != 3
            or prior_mm.shape[0] != rgb.shape[0]
            or (prior_mm.shape[1] != rgb.shape[1] or prior_mm.shape[2] != rgb.shape[2])
        ):
            raise ValueError("ChangeAwarePredictor expects a (B, H, W) prior of the frame's size")
        b = rgb.shape[0]
        h = rgb.shape[1]
        w = rgb.shape[2]
        mean = torch.jit.annotate(torch.Tensor, self.mean)  # a buffer: typed for mypy
        std = torch.jit.annotate(torch.Tensor, self.std)
        x = (rgb.permute(0, 3, 1, 2).float() - mean) / std
        prior = prior_mm.float()
        valid = torch.isfinite(prior) & (prior > 0)
        safe = torch.where(valid, prior, torch.ones_like(prior))
        log_p = torch.log(safe)
        # The render's log-depth about its own median: the network sees shape, not scale.
        ref = torch.nanmedian(torch.where(valid, log_p, torch.full_like(log_p, float("nan")))
                              .reshape(b, -1), dim=1).values  # fmt: skip
        ref = torch.where(torch.isfinite(ref), ref, torch.zeros_like(ref))
        vf = valid.float()
        rel = (log_p - ref.view(b, 1, 1)) * vf
        inp = torch.cat([x, rel[:, None], vf[:, None]], dim=1)
        sh, sw = self.net_size(h, w)
        if sh != h or sw != w:
            small = F.interpolate(inp, size=(sh, sw), mode="area")
            v_small = small[:, 4:5]
            rel_small = small[:, 3:4] / v_small.clamp(min=1e-6)
            inp = torch.cat([small[:, :3], rel_small, v_small], dim=1)
        pad_h = (self.stride - sh % self.stride) % self.stride
        pad_w = (self.stride - sw % self.stride) % self.stride
        if pad_h > 0 or pad_w > 0:
            inp = F.pad(inp, [0, pad_w, 0, pad_h], mode="replicate")
        y = self.net(inp)[:, :, :sh, :sw]
        if sh != h or sw != w:
            y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
        r = self.max_log_correction * torch.tanh(y[:, 0:1] / self.max_log_correction)
        return r, y[:, 1:2]

    def forward(
        self, rgb: torch.Tensor, prior_mm: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        r, c = self.raw(rgb, prior_mm)
        p = torch.sigmoid(c[:, 0])
        prior = prior_mm.float()
        valid = torch.isfinite(prior) & (prior > 0)
        # The correction is applied in proportion to the change probability: where the
        # network is sure nothing changed, the render comes out as it is (held-out
        # phantoms: unchanged abs-rel 0.011 -> 0.004, mask precision 0.36 -> 0.83). Where
        # its change head decides "unchanged" (p < decision_p) the render comes out
        # unchanged: a soft gate alone let large corrections through at p 0.2-0.5, which
        # flagged unchanged tissue (docs/depth.md).
        corrected = torch.where(p >= self.decision_p, prior * torch.exp(r[:, 0] * p), prior)
        depth = torch.where(valid, corrected, torch.full_like(prior, float("nan")))
        return depth, p


def num_parameters(net: nn.Module) -> int:
    return int(sum(p.numel() for p in net.parameters()))


def save_change_checkpoint(
    path: str | Path, net: ChangeNet, info: dict[str, Any] | None = None
) -> Path:
    """Write a change-aware checkpoint (``kind: change-aware``) and its ``.json`` sidecar."""
    path = Path(path)
    if path.suffix != ".pt":
        raise InvalidInputError(path, f"checkpoint file must end in .pt, got {path.suffix!r}")
    try:
        info = json.loads(json.dumps(dict(info or {})))
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(path, f"checkpoint info must be JSON-able: {exc}") from None
    bad = nonfinite_tensors(dict(net.state_dict()))
    if bad:
        raise CheckpointError(
            path, f"refusing to save a network with NaN/inf in {len(bad)} tensor(s), e.g. {bad[:3]}"
        )
    head = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "kind": KIND}
    payload = {
        **head,
        "config": net.config.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
        "info": info,
    }
    sidecar = {
        **head,
        "weights": path.name,
        "num_parameters": num_parameters(net),
        "config": net.config.to_dict(),
        "info": info,
    }
    write_checkpoint_files(path, payload, sidecar)
    return path


def load_change_checkpoint(path: str | Path) -> tuple[ChangeNet, dict[str, Any]]:
    """Load a change-aware checkpoint into a fresh :class:`ChangeNet` (eval, CPU).

    A monocular checkpoint (kind ``monocular``, or no kind: the older files) is refused
    with a :class:`CheckpointError` naming both kinds. Returns ``(net, info)``.
    """
    payload = read_checkpoint(path, KIND)
    config = ChangeNetConfig.from_dict(payload.get("config", {}), f"{path} config")
    net = ChangeNet(config)
    fill_weights(path, net, payload, config.to_dict())
    return net, checkpoint_info(path, payload)
