"""DMPR-PS-style detector: backbone + point head on a 1/32 grid; slots from DMPR-PS' pairing rules."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from .backbone import Backbone, PointHead, PointMaps, prepare_input
from .decode import DecodeOptions, Detections, MarkingPoint, Slot, decode_points, infer_slots

__all__ = ["DMPRDetector"]


class DMPRDetector(nn.Module):
    """Marking points (confidence, L/T shape, offset, direction per 1/32 cell) from a BEV of any size."""

    kind = "dmpr"

    def __init__(self, width: float = 0.25, input_size: int = 256) -> None:
        super().__init__()
        if input_size % 32 or input_size < 64:
            raise ValueError(f"input_size must be a multiple of 32 and at least 64, got {input_size}")
        if not width > 0:
            raise ValueError(f"width multiplier must be positive, got {width}")
        self.width, self.input_size = width, input_size
        self.backbone = Backbone(width)
        self.point_head = PointHead(self.backbone.channels[-1])

    def features(self, bev: Tensor) -> list[Tensor]:
        """Backbone features (strides 8, 16, 32) of a ``[B, 3, H, W]`` BEV in [0, 1], resized here."""
        return self.backbone(prepare_input(bev, self.input_size))

    def forward(self, bev: Tensor) -> PointMaps:
        """Point maps of a ``[B, 3, H, W]`` (or ``[3, H, W]``) BEV in [0, 1]; differentiable w.r.t. the BEV."""
        return self.point_head(self.features(bev)[-1])

    def confidence(self, bev: Tensor) -> Tensor:
        """Corner-confidence map ``[B, 1, G, G]`` in [0, 1] (G = input_size / 32), differentiable w.r.t. ``bev``."""
        return self(bev).confidence

    def slots_of(self, points: list[MarkingPoint], b: int, extras: Any, size: tuple[int, int], m_per_px: float,
                 opts: DecodeOptions) -> list[Slot]:
        """Slots among the decoded points of image ``b`` of a ``size`` = (W, H) BEV: DMPR-PS' pairing rules."""
        return infer_slots(points, m_per_px, opts)

    def run(self, bev: Tensor) -> tuple[PointMaps, Any]:
        """Network outputs needed by ``detect``: the point maps and model-specific extras (none for DMPR)."""
        return self(bev), None

    def decode(self, maps: PointMaps, extras: Any, size: tuple[int, int], m_per_px: float,
               opts: DecodeOptions) -> list[Detections]:
        """Marking points and slots per image from the outputs of ``run``, in pixels of a ``size`` = (W, H) BEV."""
        out = []
        for b in range(maps.logits.shape[0]):
            points = decode_points(maps, b, size[0], size[1], opts)
            out.append(Detections(points, self.slots_of(points, b, extras, size, m_per_px, opts)))
        return out

    @torch.no_grad()
    def detect(self, bev: Tensor, m_per_px: float, opts: DecodeOptions = DecodeOptions()) -> list[Detections]:
        """Decoded marking points and slots per image, in the input BEV's pixels; ``m_per_px`` is its scale."""
        maps, extras = self.run(bev)
        return self.decode(maps, extras, (bev.shape[-1], bev.shape[-2]), m_per_px, opts)

    def config(self) -> dict[str, Any]:
        """Constructor arguments (stored in checkpoints)."""
        return {"width": self.width, "input_size": self.input_size}

