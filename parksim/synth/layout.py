"""Procedural underground garage: aisles, slot rows, painted lines, pillars, parked cars, walls, lights.

Everything is analytic: oriented boxes standing on the floor, paint as 2D polygons on the
floor (z = 0), point-like light fixtures under the ceiling. World frame: z up, metres; the
garage floor spans ``x in [0, length]``, ``y in [y_min, y_max]``. Slot rows run along x on
both sides of each aisle, each row made of bays (perpendicular, slanted or parallel slots)
with pillars between bays at the back of the row, as in real garages.
"""

from __future__ import annotations

import math

import numpy as np

from . import cars
from .dressing import dress
from .garage import (
    AISLE_WIDTH,
    CROSS_AISLE,
    PARALLEL_SLOT,
    Box,
    Decal,
    FloorText,
    Garage,
    LayoutParams,
    Light,
    MarkingPoint,
    Paint,
    Slot,
)

__all__ = ["build_garage",
           "Box", "Paint", "MarkingPoint", "Slot", "Light", "Garage", "LayoutParams", "Decal", "FloorText",
           "AISLE_WIDTH", "CROSS_AISLE"]
"""``build_garage``; the scene types and dimensions are ``garage``'s, named here too for callers that read them
from the layout."""

_PERP = (2.5, 5.3)        # slot width along the row, depth (ps2.0-like)
_SLANT_WIDTH = 2.6        # perpendicular distance between slanted separators
_SLANT_LENGTH = 5.0       # length of a slanted separator line
_BAY_GAP = 1.2            # floor between bays, where a pillar stands at the back
_PILLAR = 0.7             # pillar side (m)
_CAR = (4.5, 1.8, 1.45)   # length, width, height of a parked car


def _segment(p0: np.ndarray, p1: np.ndarray, width: float, color: str) -> Paint:
    """Rectangle of ``width`` centred on the segment p0-p1 (square ends flush with the end points + half width)."""
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([-d[1], d[0]]) * width / 2
    a, b = p0 - d * width / 2, p1 + d * width / 2
    return Paint(tuple(map(tuple, (a + n, b + n, b - n, a - n))), color)


def _arrow(x: float, y: float, heading: float) -> Paint:
    """Straight lane arrow (shaft + head), 3 m long, pointing along ``heading``."""
    local = np.array([[-1.5, 0.12], [0.6, 0.12], [0.6, 0.4], [1.5, 0.0], [0.6, -0.4], [0.6, -0.12], [-1.5, -0.12]])
    c, s = math.cos(heading), math.sin(heading)
    pts = local @ np.array([[c, s], [-s, c]]) + np.array([x, y])
    return Paint(tuple(map(tuple, pts)), "white")


def _car_boxes(cx: float, cy: float, yaw: float, color: tuple[float, float, float]) -> list[Box]:
    """A parked car as boxes: lower body, glass cabin, roof, four wheels."""
    length, width, height = _CAR
    c, s = math.cos(yaw), math.sin(yaw)
    at = lambda fwd, left: (cx + c * fwd - s * left, cy + s * fwd + c * left)  # noqa: E731
    boxes = [Box(cx, cy, 0.28, 0.95, length, width, yaw, "car_body", color),
             Box(*at(-0.25, 0.0), 0.95, height - 0.06, 2.5, width - 0.16, yaw, "car_window"),
             Box(*at(-0.25, 0.0), height - 0.06, height, 2.3, width - 0.22, yaw, "car_body", color)]
    for fwd in (1.35, -1.35):
        for left in (width / 2 - 0.12, -width / 2 + 0.12):
            boxes.append(Box(*at(fwd, left), 0.0, 0.64, 0.64, 0.26, yaw, "wheel"))
    return boxes


class _RowBuilder:
    """Lays out one slot row along x: entrance line at ``y = edge``, slots extend towards ``side``."""

    def __init__(self, garage: Garage, params: LayoutParams, rng: np.random.Generator, edge: float, side: int):
        self.g, self.p, self.rng, self.edge, self.side = garage, params, rng, edge, side
        self.color = "yellow" if rng.random() < params.yellow_fraction else "white"
        # the varied cars draw from their own stream, so the classic layouts' draws stay as they were
        self.car_rng = np.random.default_rng([params.seed, 101, int(round(edge * 100)) + 10_000])

    def bay(self, x0: float, kind: str, n: int) -> float:
        """Paint ``n`` slots of ``kind`` starting at ``x0``; return the x where the bay's paint ends."""
        side, e, w = self.side, self.edge, self.p.line_width
        if kind == "perpendicular":
            step, depth, angle = _PERP[0], _PERP[1], 90.0
        elif kind == "parallel":
            step, depth, angle = PARALLEL_SLOT[0], PARALLEL_SLOT[1], 90.0
        else:
            angle = self.p.slant_deg
            step, depth = _SLANT_WIDTH / math.sin(math.radians(angle)), _SLANT_LENGTH
        # Separator direction: perpendicular to the row, or leaning forward (+x) for slanted slots.
        a = math.radians(angle)
        sep = np.array([math.cos(a), side * math.sin(a)])
        direction = math.atan2(sep[1], sep[0])
        x1 = x0 + n * step
        self.g.paint.append(_segment(np.array([x0, e]), np.array([x1, e]), w, self.color))
        first = len(self.g.marks)
        for i in range(n + 1):
            p = np.array([x0 + i * step, e])
            self.g.paint.append(_segment(p, p + sep * depth, w, self.color))
            self.g.marks.append(MarkingPoint(float(p[0]), float(p[1]), direction, "L" if i in (0, n) else "T"))
        # Back line for perpendicular and parallel rows, as ps2.0 garages paint them.
        back = depth * math.sin(a) * side
        if kind != "slanted":
            self.g.paint.append(_segment(np.array([x0, e + back]), np.array([x1, e + back]), w, self.color))
        tip = max(0.0, sep[0] * depth)  # slanted separators lean past the bay's last entrance point
        # p1 -> p2 keeps the slot on the right-hand side when looking from p1 to p2 in the world, so the entrance
        # runs along +x (side -1) or -x (side +1); the slot angle is measured from it to the separators.
        slot_angle = angle if side < 0 else 180.0 - angle
        for i in range(n):
            occupied = bool(self.rng.random() < self.p.occupancy)
            p1, p2 = (first + i, first + i + 1) if side < 0 else (first + i + 1, first + i)
            self.g.slots.append(Slot(p1, p2, kind, slot_angle, depth, occupied))
            if occupied:
                self._park(np.array([x0 + (i + 0.5) * step, e]), sep, depth, kind)
        return x1 + tip

    def _park(self, entrance_mid: np.ndarray, sep: np.ndarray, depth: float, kind: str) -> None:
        """Put a car in the slot, slightly off-centre and yawed as people park."""
        centre = entrance_mid + sep * depth / 2 + self.rng.normal(0, 0.08, 2)
        yaw = math.atan2(sep[1], sep[0]) if kind != "parallel" else 0.0
        if kind != "parallel" and self.rng.random() < 0.5:
            yaw += math.pi  # parked nose-in or reversed in
        if kind == "parallel":
            centre = entrance_mid + np.array([0.0, sep[1] * depth / 2])
        yaw += float(self.rng.normal(0, 0.025))
        hue = self.rng.choice(np.array([[0.8, 0.8, 0.82], [0.12, 0.12, 0.13], [0.55, 0.1, 0.08], [0.15, 0.25, 0.5],
                                        [0.45, 0.46, 0.48], [0.7, 0.68, 0.6], [0.85, 0.85, 0.85]]))
        color = (float(hue[0]), float(hue[1]), float(hue[2]))
        if self.car_rng.random() < self.p.car_variety:
            shape = cars.random_shape(self.car_rng)
            if kind == "parallel" or shape.length <= depth - 0.1:  # a long pickup or van only where it fits
                jitter = self.car_rng.normal(0.0, 0.04, 3)
                color = tuple(float(v) for v in np.clip(cars.PALETTE[self.car_rng.integers(len(cars.PALETTE))]
                                                        * (1.0 + jitter), 0.02, 0.95))  # type: ignore[assignment]
                self.g.boxes.extend(cars.car_boxes(shape, float(centre[0]), float(centre[1]), yaw, color))
                self.g.cars.append(Box(float(centre[0]), float(centre[1]), 0.0, shape.height, shape.length,
                                       shape.width, yaw, "car", color))
                return
        self.g.boxes.extend(_car_boxes(float(centre[0]), float(centre[1]), yaw, color))
        self.g.cars.append(Box(float(centre[0]), float(centre[1]), 0.0, _CAR[2], _CAR[0], _CAR[1], yaw, "car", color))

    def fill(self, x_start: float, x_end: float) -> None:
        """Fill the row with bays of random kinds, a pillar at the back after each bay."""
        x = x_start
        while True:
            kind = str(self.rng.choice(self.p.kinds))
            n = int(self.rng.integers(2, 4)) if kind != "parallel" else int(self.rng.integers(1, 3))
            step = {"perpendicular": _PERP[0], "parallel": PARALLEL_SLOT[0]}.get(
                kind, _SLANT_WIDTH / math.sin(math.radians(self.p.slant_deg)))
            if x + n * step > x_end:
                n = int((x_end - x) // step)
                if n < 1:
                    return
            x = self.bay(x, kind, n)
            self.g.boxes.append(Box(x + _BAY_GAP / 2, self.edge + self.side * (_PERP[1] - _PILLAR / 2),
                                    0.0, self.p.height, _PILLAR, _PILLAR, 0.0, "pillar"))
            x += _BAY_GAP


def build_garage(params: LayoutParams) -> Garage:
    """Lay out a garage with ``params.aisles`` parallel aisles, walls, pillars, cars and lights (seeded)."""
    rng = np.random.default_rng(params.seed)
    depth = _PERP[1]
    half = AISLE_WIDTH / 2
    # y layout: wall | row | aisle 0 | row | row (back to back) | aisle 1 | row | wall
    lanes = [i * (AISLE_WIDTH + 2 * depth) for i in range(params.aisles)]
    y_min, y_max = lanes[0] - half - depth - 0.4, lanes[-1] + half + depth + 0.4
    g = Garage(params.length, y_min, y_max, params.height, lanes=lanes, line_width=params.line_width,
               ambient=params.ambient, params=params)
    x0, x1 = CROSS_AISLE, params.length - CROSS_AISLE
    for lane in lanes:
        for side in (-1, 1):
            _RowBuilder(g, params, rng, lane + side * half, side).fill(x0, x1)
        for x in np.arange(x0 + 2.0, x1, 12.0):
            heading = 0.0 if lane == lanes[0] else math.pi
            g.paint.append(_arrow(float(x), lane, heading))
    # Dashed yellow centre line along the cross aisles' turning zone.
    for lane in lanes:
        for xs in np.arange(1.0, CROSS_AISLE - 2.0, 2.0):
            g.paint.append(_segment(np.array([xs, lane]), np.array([xs + 1.0, lane]), 0.12, "yellow"))
    t = 0.3
    L, H = params.length, params.height
    g.boxes += [Box(L / 2, y_min - t / 2, 0.0, H, L + 2 * t, t, 0.0, "wall"),
                Box(L / 2, y_max + t / 2, 0.0, H, L + 2 * t, t, 0.0, "wall"),
                Box(-t / 2, (y_min + y_max) / 2, 0.0, H, t, y_max - y_min, 0.0, "wall"),
                Box(L + t / 2, (y_min + y_max) / 2, 0.0, H, t, y_max - y_min, 0.0, "wall")]
    light_ys = sorted({*lanes, *(lane + s * (half + depth / 2) for lane in lanes for s in (-1, 1))})
    for y in light_ys:
        for x in np.arange(params.light_spacing / 2, L, params.light_spacing):
            on = rng.random() >= params.broken_lights
            intensity = params.light_intensity * float(rng.uniform(0.85, 1.15)) if on else 0.0
            g.lights.append(Light(float(x), float(y), intensity))
            g.boxes.append(Box(float(x), float(y), H - 0.08, H, 1.25, 0.16, 0.0,
                               "fixture" if on else "fixture_off"))
    dress(g, params)
    return g
