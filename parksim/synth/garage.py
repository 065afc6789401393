"""The garage scene's types: boxes standing on the floor, paint, marking points and slots, lights, signs, and the
layout parameters, with the dimensions every part of the generator agrees on.

``layout`` fills a :class:`Garage`; ``cars`` and ``dressing`` add to it; ``raycast``, ``shading``, ``labels`` and
the rest read it. Keeping the types here, below all of them, lets ``layout`` call ``cars`` and ``dressing`` without
an import cycle. World frame: z up, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Box", "Paint", "MarkingPoint", "Slot", "Light", "Garage", "LayoutParams", "Decal", "FloorText",
           "AISLE_WIDTH", "CROSS_AISLE", "PARALLEL_SLOT", "MIN_LENGTH"]

AISLE_WIDTH = 6.0
"""Driving aisle width between the entrance lines of two facing rows (m)."""
CROSS_AISLE = 8.0
"""Free floor at both x ends of the garage, where cars turn between aisles (m)."""
PARALLEL_SLOT = (6.0, 2.5)
"""A parallel slot's length along the row and depth (m): the widest bay."""
MIN_LENGTH = 2 * CROSS_AISLE + PARALLEL_SLOT[0]
"""Shortest garage (m): both cross aisles and the widest bay, so every row holds a slot."""


@dataclass(frozen=True)
class Box:
    """Oriented box standing on the floor: centre (cx, cy), z range, size along/across ``yaw``."""

    cx: float
    cy: float
    z0: float
    z1: float
    length: float
    width: float
    yaw: float
    material: str
    color: tuple[float, float, float] = (0.5, 0.5, 0.5)

    def corners_xy(self) -> np.ndarray:
        """The four floor-plan corners, counter-clockwise, shape (4, 2)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        hl, hw = self.length / 2, self.width / 2
        local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
        return local @ np.array([[c, s], [-s, c]]) + np.array([self.cx, self.cy])


@dataclass(frozen=True)
class Paint:
    """A painted floor polygon (line segment rectangle or arrow) in world xy, with its colour name."""

    polygon: tuple[tuple[float, float], ...]
    color: str


@dataclass(frozen=True)
class MarkingPoint:
    """DMPR-PS marking point in the world: where a separator meets the entrance line.

    ``direction`` (rad, world) points along the separator into the slot; ``shape`` is "T"
    when the entrance line continues on both sides of the separator, "L" at a row end.
    """

    x: float
    y: float
    direction: float
    shape: str


@dataclass(frozen=True)
class Slot:
    """A parking slot: entrance marking points ``p1, p2`` (indices into ``Garage.marks``; the slot lies right of
    p1 -> p2), kind, ``angle_deg`` from the entrance p1 -> p2 to the separators (0..180), depth, occupancy."""

    p1: int
    p2: int
    kind: str
    angle_deg: float
    depth: float
    occupied: bool


@dataclass(frozen=True)
class Light:
    """Ceiling fixture at (x, y) with relative intensity (0 = broken)."""

    x: float
    y: float
    intensity: float


@dataclass
class Garage:
    """The whole static scene; ``lanes`` are the aisle centre lines' y; ``cars`` the parked cars' outer boxes."""

    length: float
    y_min: float
    y_max: float
    height: float
    boxes: list[Box] = field(default_factory=list)
    paint: list[Paint] = field(default_factory=list)
    marks: list[MarkingPoint] = field(default_factory=list)
    slots: list[Slot] = field(default_factory=list)
    lights: list[Light] = field(default_factory=list)
    lanes: list[float] = field(default_factory=list)
    cars: list[Box] = field(default_factory=list)
    line_width: float = 0.15
    ambient: float = 0.12
    params: LayoutParams = field(default_factory=lambda: LayoutParams())
    decals: list[Decal] = field(default_factory=list)
    floor_text: list[FloorText] = field(default_factory=list)

    def slot_entrance(self, s: Slot) -> tuple[np.ndarray, np.ndarray]:
        """Midpoint of slot ``s``'s entrance and the unit direction into the slot (world xy)."""
        a, b = self.marks[s.p1], self.marks[s.p2]
        return np.array([(a.x + b.x) / 2, (a.y + b.y) / 2]), np.array([math.cos(a.direction), math.sin(a.direction)])


@dataclass(frozen=True)
class Decal:
    """A sign or painted text on a box face: box index, face (0..3: +x, -x, +y, -y), centre ``u`` (m, to the right
    as seen facing the face, from the box centre) and ``z``, size, text, ink and panel colours (no panel: None)."""

    box: int
    face: int
    u: float
    z: float
    width: float
    height: float
    text: str
    ink: tuple[float, float, float]
    panel: tuple[float, float, float] | None


@dataclass(frozen=True)
class FloorText:
    """Text painted on the floor: centre (x, y), ``heading`` (rad) its reading direction, letter height (m)."""

    x: float
    y: float
    heading: float
    height: float
    text: str
    color: str


@dataclass(frozen=True)
class LayoutParams:
    """Knobs of one garage: size, slot mix, paint, occupancy, lighting, and the real-garage dressing (varied cars,
    clutter, signage, worn paint, stains, wet and glossy floor) whose defaults (all off) keep scene1-4 as they were.
    docs/synth.md gives each knob's range and the property of real garages it imitates."""

    seed: int = 0
    length: float = 48.0
    aisles: int = 1
    height: float = 2.9
    kinds: tuple[str, ...] = ("perpendicular", "perpendicular", "slanted", "parallel")
    slant_deg: float = 60.0
    yellow_fraction: float = 0.3
    occupancy: float = 0.55
    light_spacing: float = 6.0
    light_intensity: float = 1.0
    broken_lights: float = 0.1
    ambient: float = 0.12
    line_width: float = 0.16
    light_falloff: float = 4.0
    car_variety: float = 0.0
    clutter: float = 0.0
    signage: bool = False
    paint_fade: float = 0.0
    paint_scuff: float = 0.0
    tyre_marks: float = 0.0
    stains: float = 0.0
    wet_patches: float = 0.0
    floor_gloss: float = 0.0
    grime: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.length) and self.length >= MIN_LENGTH):
            raise ValueError(f"garage length must be at least {MIN_LENGTH:g} m (two {CROSS_AISLE:g} m cross aisles "
                             f"and a bay), got {self.length:g}")
        if self.aisles < 1:
            raise ValueError(f"a garage needs at least one aisle, got {self.aisles}")
        shares = {k: getattr(self, k) for k in ("car_variety", "clutter", "paint_fade", "paint_scuff", "tyre_marks",
                                                 "floor_gloss", "grime")}
        bad = [f"{k} {v:g}" for k, v in shares.items() if not 0.0 <= v <= 1.0]
        bad += [f"{k} {v:g}" for k, v in (("stains", self.stains), ("wet_patches", self.wet_patches),
                                           ("light_falloff", self.light_falloff)) if not 0.0 <= v <= 20.0]
        if bad:
            raise ValueError(f"layout parameters out of range: {', '.join(bad)} (shares lie in [0, 1]; stains, "
                             "wet_patches and light_falloff in [0, 20])")
