"""A small optical-flow network of PWC-Net's design (Sun et al., CVPR 2018), in plain torch.

PWC-Net's parts, scaled down to train in hours on a 2-core CPU:

* **Pyramid**: both images go through one shared feature pyramid, each level a stride-2 and a
  stride-1 3 × 3 convolution (levels 1 … L at 1/2 … 1/2^L of the input).
* **Warping**: from the coarsest level to level 2 (1/4 of the input), the second image's
  features are warped towards the first by the flow of the level above, upsampled.
* **Cost volume**: the correlation of the first image's features with the warped second ones
  over every displacement within ``radius`` pixels of the level (``(2r + 1)²`` channels),
  written with shifted slices, so no CUDA correlation package is needed (the authors' PWC code
  needs one). Unlike PWC-Net's raw feature products, the features are normalised to unit
  length first (a cosine similarity): with raw products this small network, trained from
  scratch on a CPU budget, shrank its features until the cost volume carried nothing and
  predicted one mean flow for every pair.
* **Flow decoder per level**: convolutions on ``[cost volume, first features, upsampled flow]``
  predicting the level's flow as a residual over the upsampled flow of the level above.
* **Context network**: dilated convolutions (1, 2, 4, 8, 1) refining the finest flow.

The output is the flow at 1/4 of the input (the finest decoder level, PWC-Net's own output
size: 48 × 128 for a 192 × 512 input, the MFG input size); :meth:`PWCFlowNet.forward` gives every
level's flow for the multi-scale loss. Flow is in pixels of the input image throughout, stored
inside the network divided by :data:`FLOW_SCALE` (PWC-Net's 20) so that the decoders regress
numbers of order one. Convention: ``image0(x) ≈ image1(x + flow(x))``, as every estimator of
:mod:`mfg_lightning.flow.estimators`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["FLOW_SCALE", "PWCConfig", "PWCFlowNet", "config_from", "correlation", "warp"]

#: Flow inside the network is (input pixels) / FLOW_SCALE (PWC-Net's scaling of its targets).
FLOW_SCALE = 20.0


@dataclass(frozen=True)
class PWCConfig:
    """The network's shape (what a checkpoint must match).

    Attributes:
        pyramid: feature channels of pyramid levels 1, 2, … (level ``l`` at 1/2^l of the
            input); the coarsest level is ``len(pyramid)``.
        decoder: channels of each flow decoder's hidden convolutions.
        context: channels of the context network's dilated convolutions.
        dilations: their dilations (one per entry of ``context``).
        radius: the cost volume's search radius at every level, pixels of the level.
        output_level: the finest level with a decoder (2: 1/4 of the input, PWC-Net's).
    """

    pyramid: tuple[int, ...] = (16, 32, 48, 64, 96)
    decoder: tuple[int, ...] = (64, 48, 32)
    context: tuple[int, ...] = (32, 32, 32, 32)
    dilations: tuple[int, ...] = (1, 2, 4, 8)
    radius: int = 4
    output_level: int = 2

    def __post_init__(self) -> None:
        for name in ("pyramid", "decoder", "context", "dilations"):
            value = tuple(int(v) for v in getattr(self, name))
            if not value or min(value) < 1:
                raise ValueError(f"flow net {name} must be positive integers, got {value}")
            object.__setattr__(self, name, value)
        if len(self.context) != len(self.dilations):
            raise ValueError("flow net context and dilations must have the same length")
        if not 1 <= self.output_level < len(self.pyramid):
            raise ValueError(
                f"flow net output_level must be in [1, {len(self.pyramid) - 1}], "
                f"got {self.output_level}"
            )
        if self.radius < 1:
            raise ValueError(f"flow net radius must be ≥ 1, got {self.radius}")

    @property
    def divisor(self) -> int:
        """Input height and width must be multiples of this (the coarsest level's stride)."""
        return 2 ** len(self.pyramid)

    def to_dict(self) -> dict[str, list[int] | int]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def _conv(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation),
        nn.LeakyReLU(0.1),
    )


def warp(features: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """``features`` sampled at ``x + flow(x)``, bilinearly, zero outside.

    Args:
        features: ``(B, C, h, w)``.
        flow: ``(B, 2, h, w)`` displacements in pixels of this ``h × w`` grid.

    Returns:
        ``(B, C, h, w)``.
    """
    h, w = features.shape[-2:]
    ys = torch.arange(h, device=flow.device, dtype=flow.dtype)
    xs = torch.arange(w, device=flow.device, dtype=flow.dtype)
    x = xs.view(1, 1, w) + flow[:, 0]
    y = ys.view(1, h, 1) + flow[:, 1]
    # align_corners=True: -1 and 1 are the centres of the first and last pixels
    grid = torch.stack((2 * x / max(w - 1, 1) - 1, 2 * y / max(h - 1, 1) - 1), dim=-1)
    return F.grid_sample(
        features, grid.to(features.dtype), mode="bilinear", padding_mode="zeros", align_corners=True
    )


def correlation(f0: torch.Tensor, f1: torch.Tensor, radius: int) -> torch.Tensor:
    """PWC-Net's cost volume: ``out[:, k, y, x] = mean_c f0[:, c, y, x] · f1[:, c, y + dy, x + dx]``
    for the ``(2r + 1)²`` displacements ``(dy, dx)`` in ``[-r, r]²`` (row-major, ``dy`` outer),
    zero where ``f1`` is read outside the image.

    Args:
        f0, f1: ``(B, C, h, w)`` features.
        radius: ``r``, pixels.

    Returns:
        ``(B, (2r + 1)², h, w)``.
    """
    _, c, h, w = f0.shape
    padded = F.pad(f1, (radius, radius, radius, radius))
    span = 2 * radius + 1
    costs = [
        (f0 * padded[:, :, dy : dy + h, dx : dx + w]).sum(1)
        for dy in range(span)
        for dx in range(span)
    ]
    return torch.stack(costs, dim=1) / c


class _Decoder(nn.Module):
    """One level's flow decoder: convolutions on ``[cost, features, flow]`` → a flow residual
    (and its last hidden features, which the context network reads at the finest level)."""

    def __init__(self, c_in: int, hidden: Sequence[int]) -> None:
        super().__init__()
        layers, c = [], c_in
        for c_out in hidden:
            layers.append(_conv(c, c_out))
            c = c_out
        self.body = nn.Sequential(*layers)
        self.flow = nn.Conv2d(c, 2, 3, padding=1)
        self.out_channels = c

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        hidden = self.body(x)
        return self.flow(hidden), hidden


class PWCFlowNet(nn.Module):
    """PWC-Net's design, small (:class:`PWCConfig`).

    Input: two ``(B, 3, H, W)`` images in ``[0, 1]`` (RGB), ``H`` and ``W`` multiples of
    :attr:`PWCConfig.divisor` (:meth:`estimate` pads others). Output: the flow at 1/4 of the
    input (level :attr:`PWCConfig.output_level`), in input pixels.
    """

    def __init__(self, config: PWCConfig | None = None, **kwargs: object) -> None:
        super().__init__()
        self.config = config or PWCConfig(**kwargs)  # type: ignore[arg-type]
        cfg = self.config
        self.pyramid = nn.ModuleList()
        c = 3
        for c_out in cfg.pyramid:
            self.pyramid.append(nn.Sequential(_conv(c, c_out, stride=2), _conv(c_out, c_out)))
            c = c_out
        cost = (2 * cfg.radius + 1) ** 2
        # decoders of levels coarsest … output_level, indexed by level
        self.decoders = nn.ModuleDict(
            {
                str(level): _Decoder(cost + cfg.pyramid[level - 1] + 2, cfg.decoder)
                for level in range(len(cfg.pyramid), cfg.output_level - 1, -1)
            }
        )
        layers, c = [], self.decoders[str(cfg.output_level)].out_channels + 2
        for c_out, d in zip(cfg.context, cfg.dilations, strict=True):
            layers.append(_conv(c, c_out, dilation=d))
            c = c_out
        layers.append(nn.Conv2d(c, 2, 3, padding=1))
        self.context = nn.Sequential(*layers)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """He initialisation for the leaky-ReLU convolutions, zero biases, and flow heads 10×
        smaller. Why: with PyTorch's default initialisation every layer shrinks its input's
        scale, so that after the pyramid's ten layers the features are ~0.01 and the cost
        volume (a mean of their products) ~1e-4, below what the decoders can tell from noise:
        measured, the network then learns to ignore the second image and predicts one mean
        flow for every pair. Small flow heads start the cascade near zero flow, so the first
        warps read the features where they are."""
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, a=0.1, nonlinearity="leaky_relu")
                nn.init.zeros_(module.bias)
        heads = [d.flow for d in self.decoders.values()] + [self.context[-1]]
        with torch.no_grad():
            for head in heads:
                head.weight.mul_(0.1)

    @staticmethod
    def normalize(image0: torch.Tensor, image1: torch.Tensor) -> torch.Tensor:
        """Both images standardised per pair and channel (their joint mean and standard
        deviation: brightness constancy between the two is kept), stacked ``(2B, 3, H, W)``."""
        pair = torch.stack((image0, image1), dim=1).float()  # (B, 2, 3, H, W)
        mean = pair.mean(dim=(1, 3, 4), keepdim=True)
        std = pair.std(dim=(1, 3, 4), keepdim=True).clamp_min(1e-3)
        pair = (pair - mean) / std
        return torch.cat((pair[:, 0], pair[:, 1]), dim=0)

    def features(self, image: torch.Tensor) -> list[torch.Tensor]:
        """The pyramid of ``(B, 3, H, W)`` standardised images: levels 1 … L."""
        x = image
        out = []
        for level in self.pyramid:
            x = level(x)
            out.append(x)
        return out

    def forward(self, image0: torch.Tensor, image1: torch.Tensor) -> list[torch.Tensor]:
        """Every decoder level's flow, coarsest first, the last one refined by the context
        network: ``(B, 2, H / 2^l, W / 2^l)`` in input pixels, for ``l`` = L … output_level."""
        cfg = self.config
        b = image0.shape[0]
        pyramids = self.features(self.normalize(image0, image1))
        flows: list[torch.Tensor] = []
        flow: torch.Tensor | None = None
        hidden: torch.Tensor | None = None
        for level in range(len(cfg.pyramid), cfg.output_level - 1, -1):
            f0, f1 = pyramids[level - 1][:b], pyramids[level - 1][b:]
            if flow is None:
                flow = f0.new_zeros(b, 2, *f0.shape[-2:])
                warped = f1
            else:
                # network units (input px / FLOW_SCALE): the same numbers at every level
                flow = F.interpolate(flow, size=f0.shape[-2:], mode="bilinear", align_corners=False)
                warped = warp(f1, flow * (FLOW_SCALE / 2**level))
            # the correlation of unit feature vectors (cosine similarity, in [-1, 1]): the
            # decoders read the same range at every level and step, which the pyramid cannot
            # shrink away (measured: with raw features it does, and the flow stops using them)
            cost = correlation(F.normalize(f0, dim=1), F.normalize(warped, dim=1), cfg.radius)
            cost = F.leaky_relu(cost * f0.shape[1], 0.1)
            residual, hidden = self.decoders[str(level)](torch.cat((cost, f0, flow), dim=1))
            flow = flow + residual
            if level == cfg.output_level:
                flow = flow + self.context(torch.cat((hidden, flow), dim=1))
            flows.append(flow * FLOW_SCALE)
        return flows

    @torch.no_grad()
    def estimate(self, image0: torch.Tensor, image1: torch.Tensor) -> torch.Tensor:
        """The flow at the input size: ``(B, 2, H, W)`` input pixels, for any ``H × W`` (padded
        at the bottom and right to the divisor by edge replication, then cropped; the finest
        level's flow upsampled bilinearly)."""
        return self.levels_and_estimate(image0, image1)[1]

    def levels_and_estimate(
        self, image0: torch.Tensor, image1: torch.Tensor
    ) -> tuple[list[torch.Tensor], torch.Tensor]:
        """:meth:`forward`'s levels and :meth:`estimate`'s flow of one pass, with gradients
        (end-to-end training: :mod:`mfg_lightning.models.end_to_end`)."""
        h, w = image0.shape[-2:]
        d = self.config.divisor
        ph, pw = (-h) % d, (-w) % d
        if ph or pw:
            image0 = F.pad(image0, (0, pw, 0, ph), mode="replicate")
            image1 = F.pad(image1, (0, pw, 0, ph), mode="replicate")
        flows = self.forward(image0, image1)
        full = F.interpolate(
            flows[-1].float(), size=(h + ph, w + pw), mode="bilinear", align_corners=False
        )
        return flows, full[..., :h, :w]


def config_from(values: dict | PWCConfig | None) -> PWCConfig:
    """A :class:`PWCConfig` from a checkpoint's or config's dict (lists as tuples)."""
    if isinstance(values, PWCConfig):
        return values
    values = dict(values or {})
    known = set(PWCConfig.__dataclass_fields__)
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown flow net setting(s) {unknown}; known: {sorted(known)}")
    return PWCConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
