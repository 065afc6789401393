"""Shared network parts: input resizing, a fully convolutional backbone to a 1/32 grid, the point head."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["Backbone", "PointHead", "PointMaps", "prepare_input", "POINT_CHANNELS"]

POINT_CHANNELS = 6
"""Point-head channels per cell: confidence, shape (L), x/y offset in the cell, cos/sin of the direction."""


def prepare_input(bev: Tensor, size: int) -> Tensor:
    """Batch ``[B, 3, H, W]`` (or ``[3, H, W]``) RGB in [0, 1], resized to ``size`` x ``size`` and centred at 0."""
    if bev.dim() == 3:
        bev = bev[None]
    if bev.dim() != 4 or bev.shape[1] != 3:
        raise ValueError(f"expected a BEV as [3, H, W] or [B, 3, H, W] RGB, got shape {list(bev.shape)}")
    if bev.shape[-2:] != (size, size):
        bev = F.interpolate(bev, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    return bev - 0.5


def _conv(cin: int, cout: int, k: int = 3, stride: int = 1) -> nn.Sequential:
    """Conv + batch norm + leaky ReLU (DMPR-PS' YOLO-style block)."""
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout),
                         nn.LeakyReLU(0.1, inplace=True))


class _Stage(nn.Module):
    """Stride-2 conv, then (``block``) a residual 1x1-3x3 bottleneck."""

    def __init__(self, cin: int, cout: int, block: bool) -> None:
        super().__init__()
        self.down = _conv(cin, cout, 3, 2)
        self.block = nn.Sequential(_conv(cout, cout // 2, 1), _conv(cout // 2, cout, 3)) if block else None

    def forward(self, x: Tensor) -> Tensor:
        x = self.down(x)
        return x if self.block is None else x + self.block(x)


class Backbone(nn.Module):
    """Five stride-2 stages (32..512 channels times ``width``); returns the features at strides 8, 16 and 32.

    The two full-resolution stages are plain strided convs (they dominate the CPU cost); the
    bottlenecks sit at strides 8 to 32.
    """

    def __init__(self, width: float = 0.5) -> None:
        super().__init__()
        chans = [max(8, int(round(c * width))) for c in (32, 64, 128, 256, 512)]
        self.channels = chans
        self.stages = nn.ModuleList(_Stage(cin, cout, block=k >= 2)
                                    for k, (cin, cout) in enumerate(zip([3] + chans[:-1], chans)))

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        return feats[2:]


@dataclass
class PointMaps:
    """Per-cell predictions on the 1/32 grid, each ``[B, C, G, G]``; ``logits`` keeps the raw head output."""

    logits: Tensor

    @property
    def confidence(self) -> Tensor:
        """Marking-point confidence in [0, 1], ``[B, 1, G, G]`` (what the slot-aware corner masks use)."""
        return torch.sigmoid(self.logits[:, 0:1])

    @property
    def shape_l(self) -> Tensor:
        """Probability that the point is L-shaped (else T)."""
        return torch.sigmoid(self.logits[:, 1:2])

    @property
    def offset(self) -> Tensor:
        """Point position inside its cell, x then y, in [0, 1]."""
        return torch.sigmoid(self.logits[:, 2:4])

    @property
    def direction(self) -> Tensor:
        """Unit (cos, sin) of the point's direction in image coordinates."""
        return F.normalize(torch.tanh(self.logits[:, 4:6]), dim=1, eps=1e-6)


class PointHead(nn.Module):
    """DMPR-PS head on the 1/32 features: two 3x3 convs, then a 1x1 conv to the point channels."""

    def __init__(self, cin: int) -> None:
        super().__init__()
        self.body = nn.Sequential(_conv(cin, cin, 3), _conv(cin, cin, 3))
        self.out = nn.Conv2d(cin, POINT_CHANNELS, 1)

    def forward(self, x: Tensor) -> PointMaps:
        return PointMaps(self.out(self.body(x)))
