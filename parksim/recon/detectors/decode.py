"""DMPR-PS decoding: grid cells -> marking points (threshold, boundary margin, NMS), point pairs -> slots."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .backbone import PointMaps
from .labels_ps2 import slot_angle_deg

__all__ = ["MarkingPoint", "Slot", "Detections", "DecodeOptions", "decode_points", "infer_slots", "select_slots"]


@dataclass(frozen=True)
class MarkingPoint:
    """A detected marking point in BEV pixels (centres at integers); direction in rad, ``atan2(dv, du)``."""

    x: float
    y: float
    direction: float
    shape: str
    score: float


@dataclass(frozen=True)
class Slot:
    """A detected slot: indices of its ordered entrance points (slot on the right of p1 -> p2), score, angle (deg)."""

    p1: int
    p2: int
    score: float
    angle: float


@dataclass
class Detections:
    """Marking points and slots detected in one BEV."""

    points: list[MarkingPoint] = field(default_factory=list)
    slots: list[Slot] = field(default_factory=list)


@dataclass(frozen=True)
class DecodeOptions:
    """Decoding thresholds (DMPR-PS' rules); distances in metres so they hold at any BEV scale."""

    threshold: float = 0.5          # marking-point confidence
    margin: float = 0.01            # drop points this close to the border (fraction of the BEV side)
    nms: float = 1.0 / 16           # suppress weaker points within this box half-size (fraction of the side)
    dmpr_ps: bool = False           # DMPR-PS' float32 positions and all-pairs NMS instead of ParkSim's (decode_points)
    # Slot width across the separators (entrance length x sin of the slot angle), so that a slanted slot and the
    # longer floor gap between two slanted bays differ: ParkSim's (ps2.0-like) slots are 2.5-2.6 m wide, parallel 6 m.
    short_width_m: tuple[float, float] = (2.0, 2.9)      # perpendicular and slanted slots
    long_width_m: tuple[float, float] = (5.5, 7.0)       # parallel slots
    through_cos: float = 0.8        # a third point k with cos(i->k, k->j) above this lies on the entrance i-j
    separator_deg: float = 60.0     # max angle between a point's direction and the entrance's right normal
    parallel_deg: float = 20.0      # max angle between the two points' directions
    edge_threshold: float = 0.5     # GCN: edge score for a slot


def decode_points(maps: PointMaps, index: int, width: int, height: int, opts: DecodeOptions) -> list[MarkingPoint]:
    """Marking points of image ``index`` of a batch, in the pixels of a ``width`` x ``height`` BEV.

    Cells above ``opts.threshold`` give positions ``u = (col + offset) / grid``, kept when ``margin <= u <= 1 -
    margin`` on both axes; then two points closer than ``opts.nms`` on both axes are resolved for the stronger.
    ParkSim's rules: positions in float64, greedy NMS (the points by falling confidence, each suppressed only by a
    kept one), output by falling confidence. ``opts.dmpr_ps``: DMPR-PS' ``get_predicted_points`` under NumPy 2,
    positions, border test and NMS distances in float32, NMS over every pair (the weaker of two close points is
    dropped even when the stronger was dropped itself, the later in grid order on a tie), output in grid order.
    """
    conf = maps.confidence[index, 0].detach()
    grid_h, grid_w = conf.shape
    off, direc, shape = maps.offset[index].detach(), maps.direction[index].detach(), maps.shape_l[index, 0].detach()
    real = np.float32 if opts.dmpr_ps else np.float64
    lo, hi = real(opts.margin), real(1 - opts.margin)
    candidates = []
    for r, c in (conf > opts.threshold).nonzero().tolist():   # row-major: DMPR-PS' grid order
        u = (real(c) + real(float(off[0, r, c]))) / real(grid_w)
        v = (real(r) + real(float(off[1, r, c]))) / real(grid_h)
        if not (lo <= u <= hi and lo <= v <= hi):
            continue
        candidates.append((float(conf[r, c]), u, v, math.atan2(float(direc[1, r, c]), float(direc[0, r, c])),
                           "L" if float(shape[r, c]) > 0.5 else "T"))
    nms = real(opts.nms)

    def close(a: tuple, b: tuple) -> bool:
        return bool(abs(a[1] - b[1]) < nms and abs(a[2] - b[2]) < nms)

    if opts.dmpr_ps:
        suppressed = [False] * len(candidates)
        for i, a in enumerate(candidates):
            for j in range(i + 1, len(candidates)):
                if close(a, candidates[j]):
                    suppressed[i if a[0] < candidates[j][0] else j] = True
        kept = [cand for cand, out in zip(candidates, suppressed) if not out]
    else:
        kept = []
        for cand in sorted(candidates, key=lambda t: -t[0]):
            if not any(close(cand, k) for k in kept):
                kept.append(cand)
    return [MarkingPoint(float(u) * width - 0.5, float(v) * height - 0.5, d, s, score) for score, u, v, d, s in kept]


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _pair_ok(points: list[MarkingPoint], i: int, j: int, m_per_px: float, opts: DecodeOptions) -> bool:
    """DMPR-PS pairing rules for the ordered pair i -> j: slot width, no point between, separator geometry."""
    a, b = points[i], points[j]
    vec = np.array([b.x - a.x, b.y - a.y])
    length = float(np.linalg.norm(vec))
    width = length * m_per_px * math.sin(math.radians(slot_angle_deg(a.x, a.y, a.direction, b.x, b.y, b.direction)))
    lo, hi = opts.short_width_m
    lo2, hi2 = opts.long_width_m
    if not (lo <= width <= hi or lo2 <= width <= hi2):
        return False
    for k, p in enumerate(points):
        if k in (i, j):
            continue
        ak, kb = np.array([p.x - a.x, p.y - a.y]), np.array([b.x - p.x, b.y - p.y])
        norms = np.linalg.norm(ak) * np.linalg.norm(kb)
        if norms > 0 and float(ak @ kb) / norms > opts.through_cos:
            return False
    right = np.array([-vec[1], vec[0]]) / length  # the slot side as the image is viewed (v down)
    da, db = _unit(a.direction), _unit(b.direction)
    cos_sep = math.cos(math.radians(opts.separator_deg))
    return bool(da @ right >= cos_sep and db @ right >= cos_sep
                and da @ db >= math.cos(math.radians(opts.parallel_deg)))


def select_slots(points: list[MarkingPoint], candidates: list[tuple[float, int, int]]) -> list[Slot]:
    """Greedy by score: each point opens at most one slot and closes at most one; an L point bounds only one."""
    used_as: dict[int, set[int]] = {1: set(), 2: set()}
    used_l: set[int] = set()
    slots = []
    for score, i, j in sorted(candidates, key=lambda t: -t[0]):
        if i in used_as[1] or j in used_as[2] or i in used_l or j in used_l:
            continue
        used_as[1].add(i)
        used_as[2].add(j)
        used_l.update(k for k in (i, j) if points[k].shape == "L")
        a, b = points[i], points[j]
        slots.append(Slot(i, j, score, slot_angle_deg(a.x, a.y, a.direction, b.x, b.y, b.direction)))
    return slots


def infer_slots(points: list[MarkingPoint], m_per_px: float, opts: DecodeOptions) -> list[Slot]:
    """DMPR-PS slot inference over all ordered point pairs; a slot's score is its weaker point's confidence."""
    candidates = [(min(points[i].score, points[j].score), i, j)
                  for i in range(len(points)) for j in range(len(points))
                  if i != j and _pair_ok(points, i, j, m_per_px, opts)]
    return select_slots(points, candidates)
