"""Parked cars of varied body types (sedan, hatchback, SUV, van, pickup), each built from several boxes.

A body type fixes the silhouette (where the cabin sits, how tall the body is); its proportions are drawn per car
within ranges around real European/US models, so no two cars are alike. The classic single-shape car of the
benchmark presets scene1-4 is ``layout._car_boxes``; these cars are used where ``LayoutParams.car_variety > 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .garage import Box

__all__ = ["BODY_TYPES", "PALETTE", "CarShape", "random_shape", "car_boxes"]


@dataclass(frozen=True)
class CarShape:
    """One car's silhouette in its own frame (x forward, m): overall size, the body (sill to belt line), the cabin
    (glass) and roof span along x (centre, length), wheel radius; ``bed`` marks a pickup's open load bed."""

    kind: str
    length: float
    width: float
    height: float
    sill: float
    belt: float
    cabin_x: float
    cabin_length: float
    wheel_radius: float
    bed: bool = False


# kind: ranges of (length, width, height, belt height, cabin length share, cabin centre share (of length, + = fwd))
BODY_TYPES: dict[str, tuple[tuple[float, float], ...]] = {
    "sedan": ((4.4, 4.95), (1.74, 1.86), (1.38, 1.48), (0.86, 0.95), (0.46, 0.52), (-0.06, -0.02)),
    "hatchback": ((3.75, 4.25), (1.66, 1.78), (1.42, 1.52), (0.86, 0.95), (0.55, 0.62), (-0.14, -0.09)),
    "suv": ((4.4, 4.95), (1.82, 1.96), (1.62, 1.80), (1.00, 1.10), (0.58, 0.64), (-0.10, -0.06)),
    "van": ((4.8, 5.25), (1.90, 2.02), (1.90, 2.10), (1.05, 1.15), (0.80, 0.86), (-0.06, -0.03)),
    "pickup": ((5.1, 5.45), (1.86, 2.00), (1.75, 1.88), (1.05, 1.15), (0.28, 0.34), (0.10, 0.16)),
}
"""Proportion ranges per body type (drawn uniformly)."""
PALETTE = np.array([[0.82, 0.82, 0.84], [0.10, 0.10, 0.11], [0.55, 0.56, 0.58], [0.34, 0.35, 0.37],
                    [0.55, 0.08, 0.07], [0.12, 0.22, 0.48], [0.14, 0.28, 0.18], [0.72, 0.66, 0.54],
                    [0.88, 0.86, 0.80], [0.80, 0.55, 0.10], [0.30, 0.16, 0.10], [0.45, 0.52, 0.60]])
"""Body colours (linear albedo): white, black, silver, graphite, red, blue, green, beige, cream, orange, brown,
steel blue; each car jitters its colour a little."""


def random_shape(rng: np.random.Generator, kind: str | None = None) -> CarShape:
    """A car of ``kind`` (random body type when None) with proportions drawn from ``BODY_TYPES``."""
    if kind is None:
        kind = str(rng.choice(list(BODY_TYPES)))
    (length, width, height, belt, cabin, shift) = (float(rng.uniform(*r)) for r in BODY_TYPES[kind])
    return CarShape(kind, length, width, height, sill=float(rng.uniform(0.22, 0.34)), belt=belt,
                    cabin_x=shift * length, cabin_length=cabin * length,
                    wheel_radius=float(rng.uniform(0.30, 0.33) if kind in ("sedan", "hatchback") else
                                       rng.uniform(0.34, 0.40)), bed=kind == "pickup")


def car_boxes(shape: CarShape, cx: float, cy: float, yaw: float, color: tuple[float, float, float]) -> list[Box]:
    """The car's boxes in the world: body, cabin glass, roof, bumpers, lamps, wheels (and a pickup's bed walls)."""
    c, s = math.cos(yaw), math.sin(yaw)

    def box(fwd: float, left: float, z0: float, z1: float, length: float, width: float, material: str,
            rgb: tuple[float, float, float] = (0.5, 0.5, 0.5)) -> Box:
        return Box(cx + c * fwd - s * left, cy + s * fwd + c * left, z0, z1, length, width, yaw, material, rgb)

    L, W, H = shape.length, shape.width, shape.height
    roof_t = 0.06
    dark = (0.05, 0.05, 0.055)
    boxes = []
    if shape.bed:  # cab body in front, a lower bed floor behind with side and tail walls
        cab_end = shape.cabin_x - shape.cabin_length / 2 - 0.1
        front = L / 2 - cab_end
        boxes.append(box(cab_end + front / 2, 0.0, shape.sill, shape.belt, front, W, "car_body", color))
        bed = cab_end + L / 2
        boxes.append(box(-L / 2 + bed / 2, 0.0, shape.sill, shape.sill + 0.25, bed, W, "car_body", color))
        for left in (W / 2 - 0.04, -W / 2 + 0.04):
            boxes.append(box(-L / 2 + bed / 2, left, shape.sill + 0.25, shape.belt, bed, 0.08, "car_body", color))
        boxes.append(box(-L / 2 + 0.04, 0.0, shape.sill + 0.25, shape.belt, 0.08, W - 0.16, "car_body", color))
    else:
        boxes.append(box(0.0, 0.0, shape.sill, shape.belt, L, W, "car_body", color))
    boxes.append(box(shape.cabin_x, 0.0, shape.belt, H - roof_t, shape.cabin_length, W - 0.14, "car_window",
                     (0.08, 0.09, 0.1)))
    boxes.append(box(shape.cabin_x, 0.0, H - roof_t, H, shape.cabin_length - 0.1, W - 0.2, "car_body", color))
    for end in (1.0, -1.0):  # bumpers, slightly proud of the body, and the lamps above them
        boxes.append(box(end * (L / 2 + 0.02), 0.0, shape.sill + 0.02, shape.sill + 0.22, 0.08, W - 0.06,
                         "car_body", dark))
        lamp = (0.85, 0.85, 0.8) if end > 0 else (0.6, 0.04, 0.03)
        for left in (W / 2 - 0.2, -W / 2 + 0.2):
            boxes.append(box(end * (L / 2 + 0.005), left, shape.belt - 0.2, shape.belt - 0.06, 0.03, 0.28,
                             "car_body", lamp))
    r = shape.wheel_radius
    axle = L / 2 - max(0.75, 0.2 * L)
    for fwd in (axle, -axle):
        for left in (W / 2 - 0.12, -W / 2 + 0.12):
            boxes.append(box(fwd, left, 0.0, 2 * r, 2 * r, 0.24, "wheel"))
    return boxes
