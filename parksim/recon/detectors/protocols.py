"""Detection scoring protocols: ParkSim's own rules and DMPR-PS' published evaluation, selectable by name.

A protocol decides how detections are decoded (border margin, NMS, sweep threshold), when a detection matches a
label, and how AP is integrated. Both score the same ``Detections`` against the same ``SlotLabels``; the
differences are listed side by side in ``docs/detection_protocol.md``.

DMPR-PS (Huang et al. 2019, github Teoge/DMPR-PS: ``config.py``, ``data/struct.py``, ``data/process.py``,
``util/precision_recall.py``, ``evaluate.py``, ``ps_evaluate.py``) works in image fractions: a point's position
is ``(x + 0.5) / width`` for ParkSim's pixel coordinates with centres at integers, i.e. ``(x_matlab - 0.5) / 600``
for ps2.0's 1-based labels.
"""

from __future__ import annotations

import bisect
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np

from .decode import DecodeOptions, Detections
from .labels_ps2 import SlotLabels

__all__ = ["MatchOptions", "Scored", "Protocol", "ParkSimProtocol", "DMPRPSProtocol", "PROTOCOLS", "get_protocol",
           "match_points", "match_slots", "average_precision", "voc11_average_precision", "DMPR_M_PER_PX"]

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


@dataclass
class Scored:
    """What one image contributes to precision, recall and AP: a confidence per entry and whether it is a TP."""

    scores: list[float] = field(default_factory=list)
    flags: list[bool] = field(default_factory=list)


# --- ParkSim: metric thresholds, slot-angle check, detection-first matching, all-point AP -------------------------

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


# --- DMPR-PS: image-fraction thresholds, shape check, label-first matching, 11-point VOC AP -----------------------

DMPR_SQUARED_DISTANCE = 0.000277778
"""``config.SQUARED_DISTANCE_THRESH``: squared distance in image fractions, (10 px / 600 px)^2, compared with <."""
DMPR_DIRECTION_RAD = 0.5235987755982988
"""``config.DIRECTION_ANGLE_THRESH``: 30 deg, compared with <."""
DMPR_BOUNDARY = 0.05
"""``config.BOUNDARY_THRESH``: predictions outside [0.05, 0.95] of either side (in float32) are dropped before
NMS."""
DMPR_SWEEP_THRESHOLD = 0.01
"""``evaluate.py``: marking points for the AP sweep are decoded at confidence 0.01."""


def _fraction(x: float, y: float, labels: SlotLabels) -> tuple[float, float]:
    """ParkSim pixel coordinates (centres at integers) as DMPR-PS' image fractions."""
    return (x + 0.5) / labels.width, (y + 0.5) / labels.height


def _squared(a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2


def _direction_diff(a: float, b: float) -> float:
    """``data.struct.direction_diff`` on angles brought to [-pi, pi] (where DMPR-PS' atan2 angles already lie)."""
    diff = abs(math.remainder(a, 2 * math.pi) - math.remainder(b, 2 * math.pi))
    return diff if diff < math.pi else 2 * math.pi - diff


def _label_first(scores: list[float], n_labels: int, matches: Callable[[int, int], bool]) -> Scored:
    """``util.match_gt_with_preds`` per label in order: the most confident matching prediction (first on a tie,
    never one of confidence 0), which may serve several labels; predictions no label took are false positives."""
    out = Scored()
    taken = [False] * len(scores)
    for g in range(n_labels):
        best, idx = 0.0, -1
        for k, score in enumerate(scores):
            if matches(g, k) and best < score:
                best, idx = score, k
        if idx >= 0:
            taken[idx] = True
            out.scores.append(scores[idx])
            out.flags.append(True)
    for k, score in enumerate(scores):
        if not taken[k]:
            out.scores.append(score)
            out.flags.append(False)
    return out


def dmpr_match_points(det: Detections, labels: SlotLabels) -> Scored:
    """``data.struct.match_marking_points``: squared distance and direction below threshold, same T/L shape."""
    gts = [(_fraction(x, y, labels), d, s) for x, y, d, s in labels.marks]
    preds = [(_fraction(p.x, p.y, labels), p.direction, 1.0 if p.shape == "L" else 0.0) for p in det.points]

    def matches(g: int, k: int) -> bool:
        (gp, gd, gs), (pp, pd, ps) = gts[g], preds[k]
        if (gs > 0.5 and ps < 0.5) or (gs < 0.5 and ps > 0.5):
            return False
        return _squared(gp, pp) < DMPR_SQUARED_DISTANCE and _direction_diff(gd, pd) < DMPR_DIRECTION_RAD

    return _label_first([p.score for p in det.points], len(labels.marks), matches)


def dmpr_match_slots(det: Detections, labels: SlotLabels) -> Scored:
    """``data.struct.match_slots``: both ordered entrance points within the distance; a slot's confidence is its
    weaker point's (``ps_evaluate.py``)."""
    m = labels.marks
    gts = [(_fraction(m[i, 0], m[i, 1], labels), _fraction(m[j, 0], m[j, 1], labels)) for i, j in labels.slots]
    preds = [(_fraction(det.points[s.p1].x, det.points[s.p1].y, labels),
              _fraction(det.points[s.p2].x, det.points[s.p2].y, labels)) for s in det.slots]

    def matches(g: int, k: int) -> bool:
        return _squared(gts[g][0], preds[k][0]) < DMPR_SQUARED_DISTANCE and \
            _squared(gts[g][1], preds[k][1]) < DMPR_SQUARED_DISTANCE

    scores = [min(det.points[s.p1].score, det.points[s.p2].score) for s in det.slots]
    return _label_first(scores, len(labels.slots), matches)


def voc11_average_precision(scores: list[float], flags: list[bool], labelled: int) -> float:
    """``util.calc_precision_recall`` + ``calc_average_precision``: a label's entry is its match's confidence
    (0 when missed); the curve steps through the distinct label confidences, and AP is the mean over recall
    0, 0.1, ..., 1 of the highest precision at that recall or beyond (0 when nothing is labelled)."""
    if labelled == 0:
        return 0.0
    hits = [s for s, f in zip(scores, flags) if f]
    tp_conf = sorted(hits + [0.0] * (labelled - len(hits)))
    fp_conf = sorted(s for s, f in zip(scores, flags) if not f)
    recalls, precisions = [0.0], [0.0]
    for thresh in sorted(set(tp_conf), reverse=True):
        if thresh == 0.0:
            recalls.append(1.0)
            precisions.append(0.0)
            break
        tp = len(tp_conf) - bisect.bisect_left(tp_conf, thresh)
        fp = len(fp_conf) - bisect.bisect_left(fp_conf, thresh)
        recalls.append(tp / len(tp_conf))
        precisions.append(tp / (tp + fp))
    total = 0.0
    for i in range(11):
        index = next(k for k, r in enumerate(recalls) if r >= i / 10)
        total += max(precisions[index:])
    return total / 11


# --- the protocols ------------------------------------------------------------------------------------------------

class Protocol(ABC):
    """One evaluation protocol: decoding margins and sweep, matching rules, AP integration."""

    name: ClassVar[str]
    margin: ClassVar[float]            # drop predictions this close to the border (fraction of the side)
    dmpr_nms: ClassVar[bool]           # DMPR-PS' float32 positions and all-pairs NMS (``DecodeOptions.dmpr_ps``)
    sweep_threshold: ClassVar[float]   # confidence down to which detections enter the AP sweep
    slot_ap_at_operating: ClassVar[bool]  # slots' AP from the operating-point detections, not the sweep

    def decode_options(self, decode: DecodeOptions) -> DecodeOptions:
        """``decode`` (the operating point) with this protocol's border margin and NMS."""
        return replace(decode, margin=self.margin, dmpr_ps=self.dmpr_nms)

    def sweep_options(self, decode: DecodeOptions) -> DecodeOptions:
        """The decoding for the AP sweep: this protocol's margin, NMS and sweep threshold (or ``decode``'s if
        lower)."""
        return replace(decode, margin=self.margin, dmpr_ps=self.dmpr_nms,
                       threshold=min(self.sweep_threshold, decode.threshold))

    @abstractmethod
    def match_points(self, det: Detections, labels: SlotLabels) -> Scored:
        """Marking-point entries of one image."""

    @abstractmethod
    def match_slots(self, det: Detections, labels: SlotLabels) -> Scored:
        """Slot entries of one image."""

    @abstractmethod
    def average_precision(self, scores: list[float], flags: list[bool], labelled: int) -> float:
        """AP over all images' sweep entries."""

    def describe(self) -> dict[str, Any]:
        """The protocol's name and settings, for reports."""
        return {"name": self.name, "margin": self.margin, "nms": "all pairs" if self.dmpr_nms else "greedy",
                "sweep_threshold": self.sweep_threshold,
                "slot_ap_at_operating": self.slot_ap_at_operating}


@dataclass(frozen=True)
class ParkSimProtocol(Protocol):
    """ParkSim's rules: metric thresholds (``MatchOptions``), slot-angle check, no shape check, detection-first
    greedy matching (each label once), all-point AP, 1 % border margin, greedy NMS in float64."""

    match: MatchOptions = MatchOptions()
    name: ClassVar[str] = "parksim"
    margin: ClassVar[float] = 0.01
    dmpr_nms: ClassVar[bool] = False
    sweep_threshold: ClassVar[float] = 0.05
    slot_ap_at_operating: ClassVar[bool] = False

    def match_points(self, det: Detections, labels: SlotLabels) -> Scored:
        """Each detection once, flagged by ``match_points``."""
        return Scored([p.score for p in det.points], match_points(det, labels, self.match))

    def match_slots(self, det: Detections, labels: SlotLabels) -> Scored:
        """Each detected slot once, flagged by ``match_slots``."""
        return Scored([s.score for s in det.slots], match_slots(det, labels, self.match))

    def average_precision(self, scores: list[float], flags: list[bool], labelled: int) -> float:
        """All-point interpolated AP."""
        return average_precision(scores, flags, labelled)

    def describe(self) -> dict[str, Any]:
        """Name, settings and the matching thresholds."""
        return {**super().describe(), "distance_px_at_600": self.match.distance_px,
                "direction_deg": self.match.direction_deg, "slot_angle_deg": self.match.slot_angle_deg}


@dataclass(frozen=True)
class DMPRPSProtocol(Protocol):
    """DMPR-PS' published evaluation, rule for rule (thresholds fixed by their ``config.py``)."""

    name: ClassVar[str] = "dmpr-ps"
    margin: ClassVar[float] = DMPR_BOUNDARY
    dmpr_nms: ClassVar[bool] = True
    sweep_threshold: ClassVar[float] = DMPR_SWEEP_THRESHOLD
    slot_ap_at_operating: ClassVar[bool] = True

    def match_points(self, det: Detections, labels: SlotLabels) -> Scored:
        """Label-first entries by ``dmpr_match_points``."""
        return dmpr_match_points(det, labels)

    def match_slots(self, det: Detections, labels: SlotLabels) -> Scored:
        """Label-first entries by ``dmpr_match_slots``."""
        return dmpr_match_slots(det, labels)

    def average_precision(self, scores: list[float], flags: list[bool], labelled: int) -> float:
        """11-point VOC AP."""
        return voc11_average_precision(scores, flags, labelled)

    def describe(self) -> dict[str, Any]:
        """Name, settings and the fixed thresholds."""
        return {**super().describe(), "squared_distance_fraction": DMPR_SQUARED_DISTANCE,
                "direction_rad": DMPR_DIRECTION_RAD}


PROTOCOLS: dict[str, type[Protocol]] = {"parksim": ParkSimProtocol, "dmpr-ps": DMPRPSProtocol}
"""Protocols by the name ``--protocol`` takes; ``parksim`` is the default."""


def get_protocol(name: str, match: MatchOptions = MatchOptions()) -> Protocol:
    """The protocol called ``name``; ``match`` sets ParkSim's thresholds (DMPR-PS' are fixed, so a changed
    ``match`` with ``dmpr-ps`` is a ValueError)."""
    if name == "parksim":
        return ParkSimProtocol(match)
    if name == "dmpr-ps":
        if match != MatchOptions():
            raise ValueError("--protocol dmpr-ps uses DMPR-PS' fixed thresholds; the matching options apply to "
                             "--protocol parksim")
        return DMPRPSProtocol()
    raise ValueError(f"unknown protocol {name!r}; expected one of {', '.join(PROTOCOLS)}")
