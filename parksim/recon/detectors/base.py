"""What every slot detector is: a backbone and point head finding marking points on a BEV, and a rule that pairs
them into slots (each subclass's own), with decoding, detection and the checkpoint format they share."""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from .backbone import Backbone, PointHead, PointMaps, prepare_input
from .decode import DecodeOptions, Detections, MarkingPoint, Slot, decode_points

__all__ = ["Detector"]


class Detector(nn.Module, ABC):
    """Marking points (confidence, L/T shape, offset, direction per 1/32 cell) from a BEV of any size, and slots
    from them by the subclass's :meth:`slots_of`.

    Subclasses set ``kind`` (the checkpoint's name for them), implement :meth:`slots_of`, and override :meth:`run`
    and :meth:`config` when they need more network outputs or constructor arguments.
    """

    kind: ClassVar[str]

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

    def run(self, bev: Tensor) -> tuple[PointMaps, Any]:
        """Network outputs ``detect`` needs: the point maps and the subclass's extras for :meth:`slots_of` (none
        here)."""
        return self(bev), None

    @abstractmethod
    def slots_of(self, points: list[MarkingPoint], b: int, extras: Any, size: tuple[int, int], m_per_px: float,
                 opts: DecodeOptions) -> list[Slot]:
        """Slots among the decoded ``points`` of image ``b`` of a ``size`` = (W, H) BEV at ``m_per_px``.

        Args:
            points: the image's decoded marking points, in BEV pixels.
            b: the image's index in the batch ``extras`` came from.
            extras: the second output of :meth:`run` for the whole batch.
            size: (W, H) of the BEV, pixels.
            m_per_px: the BEV's scale.
            opts: decoding thresholds.

        Returns:
            The slots, each naming its two entrance points by index into ``points``.
        """

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
        """Decoded marking points and slots per image.

        Args:
            bev: ``[B, 3, H, W]`` (or ``[3, H, W]``) RGB in [0, 1].
            m_per_px: the BEV's scale (the slot rules measure in metres).
            opts: decoding thresholds.

        Returns:
            One :class:`Detections` per image, in the input BEV's pixels.
        """
        maps, extras = self.run(bev)
        return self.decode(maps, extras, (bev.shape[-1], bev.shape[-2]), m_per_px, opts)

    def config(self) -> dict[str, Any]:
        """Constructor arguments (stored in checkpoints)."""
        return {"width": self.width, "input_size": self.input_size}

    def save(self, path: Path, extra: dict[str, Any] | None = None) -> None:
        """Write the checkpoint ``parksim.recon.detectors.load_detector`` reads, atomically: ``kind``, constructor
        ``config``, CPU weights (loadable without the training device), and ``extra`` entries (e.g. ``meta``)."""
        tmp = path.with_suffix(".tmp")
        weights = {k: v.cpu() for k, v in self.state_dict().items()}
        torch.save({"kind": self.kind, "config": self.config(), "state_dict": weights, **(extra or {})}, tmp)
        tmp.replace(path)

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> Detector:
        """The model a checkpoint written by :meth:`save` holds, in eval mode (its ``kind`` is the caller's to
        check: the registry picks ``cls`` by it)."""
        model = cls(**checkpoint["config"])
        model.load_state_dict(checkpoint["state_dict"])
        return model.eval()
