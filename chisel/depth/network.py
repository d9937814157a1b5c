"""The monocular depth network: a small residual U-Net that runs on a CPU.

``DepthNet`` maps a normalised RGB batch to log-depth at half resolution; the
:class:`DepthPredictor` wrapper takes uint8 RGB at any size, normalises it, pads it to the
network's stride, and returns positive relative depth at full resolution. The wrapper is
what is exported (TorchScript) and what :func:`chisel.depth.load_depth_source` runs, so
an exported model needs no config to be used.

The output is *relative* depth: trained with a scale-invariant loss that weakly anchors
the scale (Eigen's lambda < 1), it comes out near millimetres on data like the training
renders, but the updater solves the scale of every estimate against its own render.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from chisel.core.config import config_from_dict
from chisel.core.errors import InvalidInputError

LOG_DEPTH_CLAMP = 12.0
"""Predicted log-depth is clamped to +-this before ``exp`` so depth stays finite (e^12 ~ 1.6e5)."""


def check_rgb_normalisation(
    rgb_mean: tuple[float, ...], rgb_std: tuple[float, ...], owner: str
) -> None:
    """The input normalisation of a network's config: 3 means, 3 positive deviations."""
    if len(rgb_mean) != 3 or len(rgb_std) != 3 or min(rgb_std) <= 0:
        raise InvalidInputError(
            f"{owner}.rgb_mean/rgb_std",
            f"need 3 values each and positive std, got {rgb_mean}, {rgb_std}",
        )


@dataclass(frozen=True)
class DepthNetConfig:
    """Architecture of :class:`DepthNet`; stored in every checkpoint (JSON-able)."""

    widths: tuple[int, ...] = (16, 24, 32, 48, 64)
    """Channels of the encoder stages; stage ``k`` runs at 1/2**(k+1) of the input size."""
    blocks: tuple[int, ...] = (1, 1, 1, 2, 2)
    """Residual blocks after the strided convolution of each encoder stage."""
    input_scale: float = 0.5
    """The network sees the image resized by this factor (area filter); its depth is
    upsampled back to the input size. 0.5 makes training and inference 4x cheaper; the
    endoscopic surfaces are smooth enough that the lost detail costs little."""
    rgb_mean: tuple[float, float, float] = (0.5, 0.5, 0.5)
    """Per-channel mean subtracted from RGB scaled to [0, 1]."""
    rgb_std: tuple[float, float, float] = (0.25, 0.25, 0.25)
    """Per-channel divisor applied after the mean."""

    def __post_init__(self) -> None:
        widths = tuple(int(w) for w in self.widths)
        blocks = tuple(int(b) for b in self.blocks)
        object.__setattr__(self, "widths", widths)
        object.__setattr__(self, "blocks", blocks)
        object.__setattr__(self, "input_scale", float(self.input_scale))
        object.__setattr__(self, "rgb_mean", tuple(float(m) for m in self.rgb_mean))
        object.__setattr__(self, "rgb_std", tuple(float(s) for s in self.rgb_std))
        if not 2 <= len(widths) <= 7:
            raise InvalidInputError("DepthNetConfig.widths", f"need 2-7 stages, got {len(widths)}")
        if any(w < 1 for w in widths):
            raise InvalidInputError("DepthNetConfig.widths", f"must be positive, got {widths}")
        if len(blocks) != len(widths) or any(b < 0 for b in blocks):
            raise InvalidInputError(
                "DepthNetConfig.blocks",
                f"need one non-negative count per stage ({len(widths)}), got {blocks}",
            )
        if not 0.1 <= self.input_scale <= 1.0:
            raise InvalidInputError(
                "DepthNetConfig.input_scale", f"must be in [0.1, 1], got {self.input_scale}"
            )
        check_rgb_normalisation(self.rgb_mean, self.rgb_std, "DepthNetConfig")

    @property
    def stride(self) -> int:
        """Input height and width are padded to a multiple of this."""
        return 2 ** len(self.widths)

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "config") -> DepthNetConfig:
        return config_from_dict(cls, d, source)


def conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class _ResBlock(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.conv1 = conv_bn_relu(c, c)
        self.conv2 = nn.Conv2d(c, c, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.bn2(self.conv2(self.conv1(x))))


class DepthNet(nn.Module):
    """Residual U-Net encoder-decoder from scratch (no pretrained backbone exists here).

    forward: (B, 3, H, W) float normalised RGB, H and W multiples of ``config.stride``
    -> (B, 1, H, W) float log-depth (relative; ``exp`` gives depth).
    Encoder stage k runs at 1/2**(k+1) resolution; the decoder climbs back to 1/2 and a
    light full-resolution level (a stem on the input) restores the image's own grid.
    """

    def __init__(self, config: DepthNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or DepthNetConfig()
        w = self.config.widths
        stages = []
        c_in = 3
        for width, n_blocks in zip(w, self.config.blocks, strict=True):
            layers: list[nn.Module] = [conv_bn_relu(c_in, width, stride=2)]
            layers += [_ResBlock(width) for _ in range(n_blocks)]
            stages.append(nn.Sequential(*layers))
            c_in = width
        self.encoder = nn.ModuleList(stages)
        # Decoder level k fuses the upsampled level k+1 with the encoder skip of level k.
        self.decoder = nn.ModuleList(
            [
                nn.Sequential(conv_bn_relu(w[k + 1] + w[k], w[k]), conv_bn_relu(w[k], w[k]))
                for k in range(len(w) - 2, -1, -1)
            ]
        )
        top = max(4, w[0] // 2)
        self.stem = conv_bn_relu(3, top)
        self.top = conv_bn_relu(w[0] + top, top)
        self.head = nn.Conv2d(top, 1, 3, 1, 1)
        # Start near depth = e^2.5 ~ 12 mm, a typical endoscopic working distance.
        nn.init.zeros_(self.head.weight)
        assert self.head.bias is not None  # Conv2d has a bias by default
        nn.init.constant_(self.head.bias, 2.5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        full = self.stem(x)
        skips: list[torch.Tensor] = []
        for stage in self.encoder:
            x = stage(x)
            skips.append(x)
        y = skips[-1]
        n = len(skips)
        for i, block in enumerate(self.decoder):
            skip = skips[n - 2 - i]
            y = F.interpolate(
                y, size=(skip.shape[2], skip.shape[3]), mode="bilinear", align_corners=False
            )
            y = block(torch.cat([y, skip], dim=1))
        y = F.interpolate(
            y, size=(full.shape[2], full.shape[3]), mode="bilinear", align_corners=False
        )
        return self.head(self.top(torch.cat([y, full], dim=1)))


class DepthPredictor(nn.Module):
    """uint8 RGB in, positive relative depth out, at the input's own size.

    forward: rgb (B, H, W, 3) uint8 -> (B, H, W) float32 relative depth (> 0, finite).
    Any H, W >= 2 work: the input is resized by ``input_scale``, replicate-padded to the
    network stride, and the depth is cropped and upsampled back to (H, W).
    This is the module that is exported (TorchScript) and run by the depth source.
    """

    def __init__(self, net: DepthNet) -> None:
        super().__init__()
        self.net = net
        cfg = net.config
        self.stride = int(cfg.stride)
        self.input_scale = float(cfg.input_scale)
        self.log_depth_clamp = float(LOG_DEPTH_CLAMP)
        self.register_buffer("mean", torch.tensor(cfg.rgb_mean).view(1, 3, 1, 1) * 255.0)
        self.register_buffer("std", torch.tensor(cfg.rgb_std).view(1, 3, 1, 1) * 255.0)

    def net_size(self, h: int, w: int) -> tuple[int, int]:
        """(height, width) the network works at for an (h, w) input."""
        if self.input_scale == 1.0:
            return h, w
        return max(1, int(round(h * self.input_scale))), max(1, int(round(w * self.input_scale)))

    def log_depth(self, rgb: torch.Tensor, full_res: bool = True) -> torch.Tensor:
        """rgb (B, H, W, 3) uint8, or float in [0, 255] (augmented training input)
        -> (B, 1, H, W) float32 log relative depth; with ``full_res=False`` at the
        network's own size :meth:`net_size` (training computes its loss there)."""
        if rgb.dim() != 4 or rgb.shape[3] != 3:
            raise ValueError("DepthPredictor expects (B, H, W, 3) RGB")
        h = rgb.shape[1]
        w = rgb.shape[2]
        x = rgb.permute(0, 3, 1, 2).float()
        x = (x - torch.jit.annotate(torch.Tensor, self.mean)) / torch.jit.annotate(
            torch.Tensor, self.std
        )
        sh, sw = self.net_size(h, w)
        if sh != h or sw != w:
            x = F.interpolate(x, size=(sh, sw), mode="area")
        pad_h = (self.stride - sh % self.stride) % self.stride
        pad_w = (self.stride - sw % self.stride) % self.stride
        if pad_h > 0 or pad_w > 0:
            x = F.pad(x, [0, pad_w, 0, pad_h], mode="replicate")
        x = x.contiguous(memory_format=torch.channels_last)
        y = self.net(x)[:, :, :sh, :sw]
        if full_res and (sh != h or sw != w):
            y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
        return y.clamp(-self.log_depth_clamp, self.log_depth_clamp)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return torch.exp(self.log_depth(rgb))[:, 0].contiguous()
