"""Precision, recall and AP of marking points and slots under a scoring protocol (ParkSim's or DMPR-PS'),
and a runner over a data folder."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from .base import Detector
from .dataset import iter_items
from .decode import DecodeOptions, Detections
from .labels_ps2 import SlotLabels
from .protocols import MatchOptions, ParkSimProtocol, Protocol, Scored, average_precision, match_points, match_slots

__all__ = ["MatchOptions", "match_points", "match_slots", "average_precision", "Metrics", "summarize", "Evaluator",
           "evaluate_folder"]


@dataclass
class Metrics:
    """Precision and recall at the operating threshold, AP over the score sweep, and the counts behind them."""

    precision: float
    recall: float
    ap: float
    tp: int
    fp: int
    labelled: int


def summarize(flags: list[bool], sweep_scores: list[float], sweep_flags: list[bool], labelled: int,
              ap: Callable[[list[float], list[bool], int], float] = average_precision) -> Metrics:
    """Metrics from the operating-point entries and the low-threshold sweep; ``ap`` integrates the sweep."""
    tp = int(sum(flags))
    fp = len(flags) - tp
    return Metrics(tp / max(len(flags), 1) if flags else (1.0 if labelled == 0 else 0.0), tp / max(labelled, 1),
                   ap(sweep_scores, sweep_flags, labelled), tp, fp, labelled)


@dataclass
class _Tally:
    flags: list[bool] = field(default_factory=list)
    sweep_scores: list[float] = field(default_factory=list)
    sweep_flags: list[bool] = field(default_factory=list)
    labelled: int = 0

    def add(self, operating: Scored, sweep: Scored, labelled: int) -> None:
        self.flags += operating.flags
        self.sweep_scores += sweep.scores
        self.sweep_flags += sweep.flags
        self.labelled += labelled


class Evaluator:
    """Accumulates matches over images under ``protocol``; ``add`` takes detections at the operating and at the
    sweep threshold (decoded with ``protocol.decode_options`` / ``sweep_options``)."""

    def __init__(self, protocol: Protocol = ParkSimProtocol()) -> None:
        self.protocol = protocol
        self.points, self.slots = _Tally(), _Tally()

    def add(self, det: Detections, sweep: Detections, labels: SlotLabels) -> None:
        """Score one image; marking points only where the labels give directions (ps2.0's originals do not)."""
        p = self.protocol
        if labels.directional:
            self.points.add(p.match_points(det, labels), p.match_points(sweep, labels), len(labels.marks))
        slot_sweep = det if p.slot_ap_at_operating else sweep
        self.slots.add(p.match_slots(det, labels), p.match_slots(slot_sweep, labels), len(labels.slots))

    def result(self) -> dict[str, Metrics]:
        """``{"points": Metrics, "slots": Metrics}``."""
        return {name: summarize(t.flags, t.sweep_scores, t.sweep_flags, t.labelled, self.protocol.average_precision)
                for name, t in (("points", self.points), ("slots", self.slots))}


def evaluate_folder(model: Detector, folder: str | Path, split: str = "test",
                    decode: DecodeOptions = DecodeOptions(), protocol: Protocol = ParkSimProtocol()) -> dict:
    """Detect on every BEV of ``folder``'s ``split``; metrics, images, the protocol and the mean inference time per
    BEV (ms)."""
    evaluator = Evaluator(protocol)
    decode = protocol.decode_options(decode)
    sweep_opts = protocol.sweep_options(decode)
    seconds, images = 0.0, 0
    model.eval()
    for item in iter_items(folder, split):
        bev = torch.from_numpy(item.image).permute(2, 0, 1).float()[None] / 255.0
        size = (bev.shape[-1], bev.shape[-2])
        start = time.perf_counter()
        with torch.no_grad():
            maps, extras = model.run(bev)
            det = model.decode(maps, extras, size, item.labels.m_per_px, decode)[0]
        seconds += time.perf_counter() - start
        with torch.no_grad():
            sweep = model.decode(maps, extras, size, item.labels.m_per_px, sweep_opts)[0]
        evaluator.add(det, sweep, item.labels)
        images += 1
    if images == 0:
        raise ValueError(f"{folder}: no BEVs in split {split!r}")
    return {"folder": str(folder), "split": split, "images": images, "ms_per_bev": 1000.0 * seconds / images,
            "protocol": protocol.describe(), **{k: asdict(v) for k, v in evaluator.result().items()}}
