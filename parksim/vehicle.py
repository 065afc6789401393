"""Ego vehicle for closed-loop parking: kinematic bicycle model, body footprint and collision tests.

Vehicle frame as everywhere in ParkSim: origin on the ground under the rear-axle centre, x
forward, y left. Obstacles are the scene map's oriented boxes (``{"center": [x, y], "size":
[length, width], "yaw": rad}``: pillars, parked cars, walls); collision is a separating-axis
test between the footprint rectangle and every box, vectorised over boxes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["VehicleParams", "VehicleState", "step", "footprint", "car_centre", "Obstacles", "wrap_angle"]


@dataclass(frozen=True)
class VehicleParams:
    """A mid-size car: body 4.7 m x 1.8 m (as the synthetic ego), 2.8 m wheelbase, ~4.1 m minimum turning radius.

    Attributes:
        wheelbase: rear to front axle (m).
        rear_overhang: rear bumper behind the rear axle (m).
        length: body length (m).
        width: body width (m).
        max_steer: front-wheel steering limit (rad).
        max_steer_rate: steering rate limit (rad/s).
        max_accel: acceleration limit (m/s^2).
        max_decel: braking limit (m/s^2).
        max_speed: forward speed limit (m/s, garage speed).
        max_reverse: backward speed limit (m/s).
        dt: seconds per ``step``.
    """

    wheelbase: float = 2.8
    rear_overhang: float = 0.95
    length: float = 4.7
    width: float = 1.8
    max_steer: float = 0.6
    max_steer_rate: float = 0.8
    max_accel: float = 2.0
    max_decel: float = 4.0
    max_speed: float = 4.0
    max_reverse: float = 2.0
    dt: float = 0.1

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """Footprint in the vehicle frame: (x_min, x_max, y_min, y_max)."""
        return (-self.rear_overhang, self.length - self.rear_overhang, -self.width / 2, self.width / 2)

    @property
    def min_turn_radius(self) -> float:
        """Rear-axle turning radius at full lock."""
        return self.wheelbase / math.tan(self.max_steer)


@dataclass(frozen=True)
class VehicleState:
    """Rear-axle pose (x, y, yaw), speed (m/s, negative when reversing) and front-wheel steering angle (rad).

    Attributes:
        x: rear-axle centre, world metres.
        y: rear-axle centre, world metres.
        yaw: heading, radians.
        v: speed along the heading (m/s, negative when reversing).
        steer: front-wheel steering angle (rad, positive left).
    """

    x: float
    y: float
    yaw: float
    v: float = 0.0
    steer: float = 0.0

    @property
    def pose(self) -> tuple[float, float, float]:
        """``(x, y, yaw)``."""
        return (self.x, self.y, self.yaw)


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Angle wrapped to [-pi, pi).

    Args:
        a: angle(s) in radians.

    Returns:
        The same angle(s) in [-pi, pi), a float or an array like ``a``.
    """
    return (a + math.pi) % (2 * math.pi) - math.pi


def step(state: VehicleState, accel: float, steer_cmd: float, p: VehicleParams = VehicleParams()) -> VehicleState:
    """One ``p.dt`` step: the steering moves towards ``steer_cmd`` at its rate limit, speed follows ``accel``.

    Kinematic bicycle about the rear axle, integrated at the step's mid heading.

    Args:
        state: the state before the step.
        accel: acceleration in m/s^2 (clipped to ``[-max_decel, max_accel]``).
        steer_cmd: steering target in radians (clipped to ``max_steer``).
        p: the vehicle.

    Returns:
        The state after ``p.dt`` seconds; speed clipped to ``[-max_reverse, max_speed]``.
    """
    accel = float(np.clip(accel, -p.max_decel, p.max_accel))
    target = float(np.clip(steer_cmd, -p.max_steer, p.max_steer))
    max_delta = p.max_steer_rate * p.dt
    steer = state.steer + float(np.clip(target - state.steer, -max_delta, max_delta))
    v = float(np.clip(state.v + accel * p.dt, -p.max_reverse, p.max_speed))
    yaw_rate = v * math.tan(steer) / p.wheelbase
    mid_yaw = state.yaw + 0.5 * yaw_rate * p.dt
    x = state.x + v * math.cos(mid_yaw) * p.dt
    y = state.y + v * math.sin(mid_yaw) * p.dt
    return VehicleState(x, y, float(wrap_angle(state.yaw + yaw_rate * p.dt)), v, steer)


def car_centre(pose: Iterable[float], p: VehicleParams = VehicleParams()) -> np.ndarray:
    """World xy of the body centre for a rear-axle pose (x, y, yaw).

    Args:
        pose: rear-axle ``(x, y, yaw)`` (metres, radians).
        p: the vehicle.

    Returns:
        ``[2]`` float64 world metres.
    """
    x, y, yaw = pose
    x0, x1, _, _ = p.extent
    d = (x0 + x1) / 2
    return np.array([x + d * math.cos(yaw), y + d * math.sin(yaw)])


def footprint(pose: Iterable[float], p: VehicleParams = VehicleParams(), margin: float = 0.0) -> np.ndarray:
    """World corners (4, 2), counter-clockwise, of the body at rear-axle pose (x, y, yaw), grown by ``margin``.

    Args:
        pose: rear-axle ``(x, y, yaw)`` (metres, radians).
        p: the vehicle.
        margin: metres added on every side.

    Returns:
        ``[4, 2]`` float64 corners, front-left first.
    """
    x, y, yaw = pose
    x0, x1, y0, y1 = p.extent
    local = np.array([[x1 + margin, y1 + margin], [x0 - margin, y1 + margin],
                      [x0 - margin, y0 - margin], [x1 + margin, y0 - margin]])
    c, s = math.cos(yaw), math.sin(yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.array([x, y])


class Obstacles:
    """The scene map's oriented boxes as arrays, for fast footprint collision tests.

    Example:
        >>> walls = Obstacles([{"center": [3.0, 0.0], "size": [1.0, 1.0], "kind": "pillar"}])
        >>> walls.collides((0.0, 0.0, 0.0)), walls.collides((0.0, 3.0, 0.0))
        (True, False)
    """

    def __init__(self, boxes: Iterable[Mapping[str, Any]]) -> None:
        """Boxes as arrays.

        Args:
            boxes: ``{"center": [x, y], "size": [length, width], "yaw": rad, "kind": str}`` (metres; ``yaw``
                default 0, ``kind`` default "obstacle").
        """
        boxes = list(boxes)
        self.kinds = [str(b.get("kind", "obstacle")) for b in boxes]
        self.centres = np.array([b["center"] for b in boxes], np.float64).reshape(-1, 2)
        self.halves = np.array([b["size"] for b in boxes], np.float64).reshape(-1, 2) / 2
        yaw = np.array([b.get("yaw", 0.0) for b in boxes], np.float64)
        self.axes = np.stack([np.stack([np.cos(yaw), np.sin(yaw)], 1),
                              np.stack([-np.sin(yaw), np.cos(yaw)], 1)], 1)   # (n, 2 axes, 2)

    def __len__(self) -> int:
        """The number of boxes."""
        return len(self.kinds)

    def corners(self) -> np.ndarray:
        """(n, 4, 2) world corners of every box, counter-clockwise.

        Returns:
            ``[n, 4, 2]`` float64 metres.
        """
        signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)
        local = signs[None] * self.halves[:, None, :]
        return (self.centres[:, None, :] + local[..., 0:1] * self.axes[:, None, 0]
                + local[..., 1:2] * self.axes[:, None, 1])

    def hits(self, polygon: np.ndarray) -> np.ndarray:
        """Boolean per box: does the convex rectangle ``polygon`` (4, 2) overlap it (separating-axis test).

        Args:
            polygon: ``[4, 2]`` corners of a rectangle in order (as ``footprint`` gives them).

        Returns:
            ``[n]`` bool, True where it overlaps (touching counts).
        """
        if not len(self):
            return np.zeros(0, bool)
        edges = np.roll(polygon, -1, axis=0) - polygon
        poly_axes = np.stack([edges[0], edges[1]]) / np.linalg.norm(edges[:2], axis=1, keepdims=True)
        axes = np.concatenate([self.axes, np.broadcast_to(poly_axes, (len(self), 2, 2))], axis=1)  # (n, 4, 2)
        box_c = self.corners()                                                # (n, 4, 2)
        proj_box = np.einsum("nkd,ncd->nkc", axes, box_c)                     # (n, 4 axes, 4 corners)
        proj_poly = np.einsum("nkd,cd->nkc", axes, polygon)
        separated = (proj_box.max(2) < proj_poly.min(2)) | (proj_poly.max(2) < proj_box.min(2))
        return ~separated.any(axis=1)

    def collides(self, pose: Iterable[float], p: VehicleParams = VehicleParams(), margin: float = 0.0) -> bool:
        """True when the body at rear-axle ``pose`` (grown by ``margin``) overlaps any box.

        Args:
            pose: rear-axle ``(x, y, yaw)`` (metres, radians).
            p: the vehicle.
            margin: metres added on every side of the body.

        Returns:
            Whether any box overlaps the footprint.
        """
        return bool(self.hits(footprint(pose, p, margin)).any())
