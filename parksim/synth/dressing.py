"""Dressing of a laid-out garage: clutter (bins, cabinets, cones, ceiling pipes and ducts) and signage (pillar
and wall signs, slot numbers on the back walls and painted on the floor), as real garages have them.

Runs after ``layout.build_garage`` placed rows, cars, walls and lights, from its own random stream seeded by the
layout seed, so a garage without dressing (scene1-4) is unchanged. Only boxes and sign descriptions are made
here; ``signage`` draws the sign textures and ``shading`` puts them on the faces.
"""

from __future__ import annotations

import math

import numpy as np

from .garage import AISLE_WIDTH, CROSS_AISLE, Box, Decal, FloorText, Garage, LayoutParams

__all__ = ["dress"]

_WALL_SIGNS = (("EXIT", (0.95, 0.95, 0.95), (0.05, 0.42, 0.16)), ("P-2", (0.95, 0.95, 0.95), (0.1, 0.22, 0.55)),
               ("5 km/h", (0.7, 0.05, 0.05), (0.92, 0.92, 0.9)), ("NO SMOKING", (0.75, 0.05, 0.05), (0.9, 0.9, 0.88)),
               ("LIFT", (0.05, 0.05, 0.05), (0.9, 0.72, 0.1)), ("STAIRS", (0.95, 0.95, 0.95), (0.05, 0.42, 0.16)))
"""Wall signs: text, ink, panel."""
_BIN_COLOURS = ((0.12, 0.3, 0.14), (0.3, 0.31, 0.33), (0.1, 0.18, 0.4), (0.55, 0.45, 0.1))


def _face_u(box: Box, face: int, x: float, y: float) -> float:
    """Coordinate of world point (x, y) along face ``face`` of an unrotated box, rightwards as seen facing it."""
    return (y - box.cy, box.cy - y, box.cx - x, x - box.cx)[face]


def _clutter(g: Garage, p: LayoutParams, rng: np.random.Generator) -> None:
    """Bins and extinguishers at pillars, cabinets along the long walls, cones in the cross aisles, ceiling pipes
    over the entrance lines and ducts across the garage between the light rows (boxes of material "clutter" stand
    on the floor, "duct" hangs from the ceiling)."""
    H = g.height
    for pillar in [b for b in g.boxes if b.material == "pillar"]:
        lane = min(g.lanes, key=lambda y: abs(y - pillar.cy))
        towards_aisle = 1.0 if lane > pillar.cy else -1.0
        if rng.random() < p.clutter:
            colour = _BIN_COLOURS[int(rng.integers(len(_BIN_COLOURS)))]
            g.boxes.append(Box(pillar.cx, pillar.cy + towards_aisle * 0.68, 0.0, float(rng.uniform(0.8, 1.05)),
                               0.5, 0.5, float(rng.normal(0, 0.15)), "clutter", colour))
        if rng.random() < p.clutter:
            g.boxes.append(Box(pillar.cx + 0.15, pillar.cy + towards_aisle * 0.44, 0.35, 0.85, 0.18, 0.18, 0.0,
                               "clutter", (0.7, 0.04, 0.03)))
    for y_wall, inward in ((g.y_min, 1.0), (g.y_max, -1.0)):
        for x in np.arange(CROSS_AISLE + 2.0, g.length - CROSS_AISLE, 5.0):
            if rng.random() < p.clutter * 0.6:
                grey = float(rng.uniform(0.35, 0.6))
                g.boxes.append(Box(float(x + rng.uniform(-1.5, 1.5)), y_wall + inward * 0.14, 0.25,
                                   float(rng.uniform(1.2, 1.8)), float(rng.uniform(0.6, 1.1)), 0.26, 0.0, "clutter",
                                   (grey, grey, grey * 1.03)))
    for x_near in (0.6, g.length - 0.6):
        for _ in range(int(rng.poisson(3 * p.clutter))):
            cx, cy = x_near + float(rng.uniform(-0.3, 0.3)), float(rng.uniform(g.y_min + 0.5, g.y_max - 0.5))
            orange = (0.9, 0.28, 0.04)
            g.boxes += [Box(cx, cy, 0.0, 0.04, 0.38, 0.38, 0.0, "clutter", (0.08, 0.08, 0.08)),
                        Box(cx, cy, 0.04, 0.34, 0.24, 0.24, 0.0, "clutter", orange),
                        Box(cx, cy, 0.34, 0.44, 0.17, 0.17, 0.0, "clutter", (0.9, 0.9, 0.9)),
                        Box(cx, cy, 0.44, 0.62, 0.11, 0.11, 0.0, "clutter", orange)]
    half = AISLE_WIDTH / 2
    for lane in g.lanes:
        for side in (-1.0, 1.0):
            if rng.random() < p.clutter:
                colour = (0.6, 0.08, 0.06) if rng.random() < 0.5 else (0.45, 0.46, 0.47)
                g.boxes.append(Box(g.length / 2, lane + side * (half + 0.3), H - 0.5, H - 0.32, g.length - 0.6, 0.18,
                                   0.0, "duct", colour))
    spacing = p.light_spacing
    for x in np.arange(spacing, g.length - 1.0, spacing):
        if rng.random() < p.clutter * 0.5:
            g.boxes.append(Box(float(x), (g.y_min + g.y_max) / 2, H - 0.48, H - 0.06, 0.7, g.y_max - g.y_min - 0.2,
                               0.0, "duct", (0.62, 0.63, 0.62)))


def _signs(g: Garage, rng: np.random.Generator) -> None:
    """Zone and column signs on the aisle faces of pillars, slot numbers on the back walls and on the floor just
    inside each slot's entrance, and large signs (exit, level, speed limit) along every wall."""
    walls = [i for i, b in enumerate(g.boxes) if b.material == "wall"]
    zone = {lane: chr(ord("A") + k) for k, lane in enumerate(g.lanes)}
    nearest = lambda y: min(g.lanes, key=lambda lane: abs(lane - y))  # noqa: E731
    column = 0
    for i, b in enumerate(g.boxes):
        if b.material != "pillar":
            continue
        column += 1
        text = f"{zone[nearest(b.cy)]}{column:02d}"
        for face in (2, 3):
            g.decals.append(Decal(i, face, 0.0, 1.6, 0.62, 0.36, text, (0.05, 0.05, 0.05), (0.92, 0.92, 0.9)))
    for j, s in enumerate(g.slots):
        mid, into = g.slot_entrance(s)
        number = f"{101 + j}"
        if s.kind != "parallel":
            right = np.array([into[1], -into[0]])
            at = mid + into * 0.95
            paint = "yellow" if _row_is_yellow(g, mid) else "white"
            g.floor_text.append(FloorText(float(at[0]), float(at[1]), math.atan2(right[1], right[0]), 0.42,
                                          number, paint))
        back = mid + into * s.depth
        for w in walls:
            wall = g.boxes[w]
            face = _inner_face(g, wall)
            if face in (2, 3) and abs(back[1] - (g.y_min if face == 2 else g.y_max)) < 1.2:
                g.decals.append(Decal(w, face, _face_u(wall, face, float(back[0]), float(back[1])), 1.55, 0.62,
                                      0.34, number, (0.95, 0.95, 0.95), (0.1, 0.22, 0.55)))
    for w in walls:
        wall = g.boxes[w]
        span = max(wall.length, wall.width) - 4.0
        for k, off in enumerate(np.arange(-span / 2, span / 2, 9.0) + float(rng.uniform(0, 9.0))):
            text, ink, panel = _WALL_SIGNS[int(rng.integers(len(_WALL_SIGNS)))]
            width = 0.28 * len(text) + 0.3
            g.decals.append(Decal(w, _inner_face(g, wall), float(off), 2.05 + 0.1 * (k % 2), width, 0.42, text, ink,
                                  panel))


def _inner_face(g: Garage, wall: Box) -> int:
    """The face of an outer wall that looks into the garage."""
    if wall.length > wall.width:
        return 2 if wall.cy < g.y_min else 3
    return 0 if wall.cx < 0 else 1


def _row_is_yellow(g: Garage, point: np.ndarray) -> bool:
    """Whether the paint nearest ``point`` (a slot's entrance) is yellow: floor numbers take the row's colour."""
    best, yellow = np.inf, False
    for p in g.paint:
        d = float(np.min(np.hypot(*(np.asarray(p.polygon) - point).T)))
        if d < best:
            best, yellow = d, p.color == "yellow"
    return yellow


def dress(g: Garage, p: LayoutParams) -> None:
    """Add the clutter and signage ``p`` asks for (nothing when ``clutter`` is 0 and ``signage`` off)."""
    rng = np.random.default_rng([p.seed, 202])
    if p.clutter > 0:
        _clutter(g, p, rng)
    if p.signage:
        _signs(g, rng)
