"""The paper's (DMPR-PS') precision, recall and AP for marking points and slots, and a runner over a data folder."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from .dataset import iter_items
from .decode import DecodeOptions, Detections
from .dmpr import DMPRDetector
from .labels_ps2 import SlotLabels

__all__ = ["MatchOptions", "match_points", "match_slots", "Metrics", "summarize", "Evaluator", "evaluate_folder"]

DMPR_M_PER_PX = 10.0 / 600
"""DMPR-PS' image scale: 600 px = 10 m."""


@dataclass(frozen=True)
class MatchOptions:
    """When a detection counts as true: distances in DMPR-PS pixels (600 px = 10 m), converted to each BEV's scale."""

    distance_px: float = 10.0      # marking point / slot entrance point to its label
    direction_deg: float = 30.0    # marking point direction
    slot_angle_deg: float = 10.0   # slot angle (entrance to separators)

    def distance(self, m_per_px: float) -> float:
        """The distance threshold in pixels of a BEV with ``m_per_px``."""
        return self.distance_px * DMPR_M_PER_PX / m_per_px


def _angle_diff_deg(a: float, b: float) -> float:
    return abs(math.degrees(math.remainder(a - b, 2 * math.pi)))


def _greedy_match(scores: list[float], n_labels: int, matches: Callable[[int, int], bool]) -> list[bool]:
    """True-positive flag per detection: the best-scored detections claim labels first, each label once."""
    free = np.ones(n_labels, dtype=bool)
    flags = [False] * len(scores)
    for k in sorted(range(len(scores)), key=lambda k: -scores[k]):
        for g in np.flatnonzero(free):
            if matches(k, int(g)):
                free[g], flags[k] = False, True
                break
    return flags


def match_points(det: Detections, labels: SlotLabels, opts: MatchOptions) -> list[bool]:
    """Per detected point: within the distance threshold of a labelled point and its direction within limit."""
    thr = opts.distance(labels.m_per_px)

    def matches(k: int, g: int) -> bool:
        p, (x, y, d, _) = det.points[k], labels.marks[g]
        return math.hypot(p.x - x, p.y - y) <= thr and _angle_diff_deg(p.direction, d) <= opts.direction_deg

    return _greedy_match([p.score for p in det.points], len(labels.marks), matches)


def match_slots(det: Detections, labels: SlotLabels, opts: MatchOptions) -> list[bool]:
    """Per detected slot: both ordered entrance points match, the angle within its limit."""
    thr = opts.distance(labels.m_per_px)

    def matches(k: int, g: int) -> bool:
        s = det.slots[k]
        a, b = det.points[s.p1], det.points[s.p2]
        ga, gb = labels.marks[labels.slots[g, 0]], labels.marks[labels.slots[g, 1]]
        return (math.hypot(a.x - ga[0], a.y - ga[1]) <= thr and math.hypot(b.x - gb[0], b.y - gb[1]) <= thr
                and abs(s.angle - labels.slot_angles[g]) <= opts.slot_angle_deg)

    return _greedy_match([s.score for s in det.slots], len(labels.slots), matches)


@dataclass
class Metrics:
    """Precision and recall at the operating threshold, AP over the score sweep, and the counts behind them."""

    precision: float
    recall: float
    ap: float
    tp: int
    fp: int
    labelled: int


def average_precision(scores: list[float], flags: list[bool], labelled: int) -> float:
    """Area under the precision-recall curve with precision made monotone (VOC all-point interpolation)."""
    if labelled == 0 or not scores:
        return 0.0
    order = np.argsort(-np.asarray(scores), kind="stable")
    tp = np.cumsum(np.asarray(flags, dtype=float)[order])
    precision = tp / np.arange(1, len(order) + 1)
    recall = np.concatenate([[0.0], tp / labelled])
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    return float(np.sum(np.diff(recall) * precision))


def summarize(flags: list[bool], sweep_scores: list[float], sweep_flags: list[bool], labelled: int) -> Metrics:
    """Metrics from the operating-point flags and the low-threshold sweep."""
    tp = int(sum(flags))
    fp = len(flags) - tp
    return Metrics(tp / max(len(flags), 1) if flags else (1.0 if labelled == 0 else 0.0), tp / max(labelled, 1),
                   average_precision(sweep_scores, sweep_flags, labelled), tp, fp, labelled)


@dataclass
class _Tally:
    flags: list[bool] = field(default_factory=list)
    sweep_scores: list[float] = field(default_factory=list)
    sweep_flags: list[bool] = field(default_factory=list)
    labelled: int = 0


class Evaluator:
    """Accumulates matches over images; ``add`` takes detections at the operating and at the sweep threshold."""

    def __init__(self, opts: MatchOptions = MatchOptions()) -> None:
        self.opts = opts
        self.points, self.slots = _Tally(), _Tally()

    def add(self, det: Detections, sweep: Detections, labels: SlotLabels) -> None:
        """Score one image."""
        self.points.flags += match_points(det, labels, self.opts)
        self.points.sweep_flags += match_points(sweep, labels, self.opts)
        self.points.sweep_scores += [p.score for p in sweep.points]
        self.points.labelled += len(labels.marks)
        self.slots.flags += match_slots(det, labels, self.opts)
        self.slots.sweep_flags += match_slots(sweep, labels, self.opts)
        self.slots.sweep_scores += [s.score for s in sweep.slots]
        self.slots.labelled += len(labels.slots)

    def result(self) -> dict[str, Metrics]:
        """``{"points": Metrics, "slots": Metrics}``."""
        return {name: summarize(t.flags, t.sweep_scores, t.sweep_flags, t.labelled)
                for name, t in (("points", self.points), ("slots", self.slots))}


def evaluate_folder(model: DMPRDetector, folder: str | Path, split: str = "test",
                    decode: DecodeOptions = DecodeOptions(), match: MatchOptions = MatchOptions(),
                    sweep_threshold: float = 0.05) -> dict:
    """Detect on every BEV of ``folder``'s ``split``; metrics, images and the mean inference time per BEV (ms)."""
    from dataclasses import replace

    evaluator = Evaluator(match)
    sweep_opts = replace(decode, threshold=min(sweep_threshold, decode.threshold))
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
            **{k: asdict(v) for k, v in evaluator.result().items()}}
