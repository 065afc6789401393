"""DMPR-PS-style detector: backbone + point head on a 1/32 grid; slots from DMPR-PS' pairing rules."""

from __future__ import annotations

from typing import Any

from .base import Detector
from .decode import DecodeOptions, MarkingPoint, Slot, infer_slots

__all__ = ["DMPRDetector"]


class DMPRDetector(Detector):
    """Marking points from the shared point head; slots by DMPR-PS' geometric pairing rules (no learnt pairing)."""

    kind = "dmpr"

    def slots_of(self, points: list[MarkingPoint], b: int, extras: Any, size: tuple[int, int], m_per_px: float,
                 opts: DecodeOptions) -> list[Slot]:
        """Slots among the decoded points of image ``b`` of a ``size`` = (W, H) BEV: DMPR-PS' pairing rules."""
        return infer_slots(points, m_per_px, opts)
