"""The parking task's rules, shared by ``ParkingEnv`` and the scenario ``Episode``: one definition of each.

Slot geometry (``slot_pose``, ``free_slots``, ``heading_error``), the normalised action (``to_controls``,
``to_action``, ``drive``), when the car counts as parked (``parking_errors``, ``is_parked``), the reward and the
observation. They live here, below both users, so that the env can delegate to ``Episode`` while ``Episode`` and
the scorecard use the env's rules without importing the env (docs/env.md states the contract they implement).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..frames import Frame
from ..vehicle import VehicleParams, VehicleState, car_centre, step, wrap_angle

__all__ = ["slot_pose", "free_slots", "heading_error", "to_controls", "to_action", "drive", "parking_errors",
           "is_parked", "progress_cost", "reward", "slot_in_ego_frame", "step_info", "observation",
           "STOPPED_SPEED", "SUCCESS_BONUS", "COLLISION_PENALTY", "STEP_COST", "YAW_WEIGHT"]

SUCCESS_BONUS, COLLISION_PENALTY, STEP_COST, YAW_WEIGHT = 10.0, 10.0, 0.01, 0.5
"""The reward's terms: a bonus once parked, a penalty on touching anything, a cost per step, and the weight of the
heading error (rad) beside the distance (m) in the progress cost."""
STOPPED_SPEED = 0.1
"""Parked needs the speed below this (m/s)."""


def slot_pose(slot: dict[str, Any]) -> tuple[np.ndarray, float]:
    """Slot centre (world xy) and its parking heading: into the slot, or along it for parallel slots.

    Args:
        slot: a map slot with ``corners`` ``[4, 2]`` (world metres; the first two on the entrance side).

    Returns:
        ``(centre [2], yaw)``: the centre in metres and the heading in radians along the slot's longer side.
    """
    c = np.asarray(slot["corners"], np.float64)
    centre = c.mean(axis=0)
    into = c[2:].mean(axis=0) - c[:2].mean(axis=0)
    along = c[1] - c[0]
    axis = along if np.linalg.norm(along) > np.linalg.norm(into) else into
    return centre, math.atan2(axis[1], axis[0])


def free_slots(world_map: dict[str, Any]) -> list[dict[str, Any]]:
    """The map's slots that no parked car occupies.

    Args:
        world_map: a scene's ``map.json`` content.

    Returns:
        The slots whose ``occupied`` is false or absent, in map order.
    """
    return [s for s in world_map.get("slots", []) if not s.get("occupied", False)]


def heading_error(yaw: float, slot_yaw: float) -> float:
    """Heading error to the slot axis in [0, pi/2]: forward or backward parking both count.

    Args:
        yaw: the car's heading in radians.
        slot_yaw: the slot's heading in radians (``slot_pose``).

    Returns:
        The smaller angle between the car and the slot axis, radians.

    Example:
        >>> round(heading_error(math.pi - 0.1, 0.0), 6)
        0.1
    """
    e = abs(float(wrap_angle(yaw - slot_yaw)))
    return min(e, math.pi - e)


def to_controls(action: Sequence[float] | np.ndarray, p: VehicleParams) -> tuple[float, float]:
    """(acceleration m/s^2, steering rad) for a normalised action, clipped to [-1, 1] first.

    ``action[0]`` = +1 is ``p.max_accel``, -1 is ``-p.max_decel`` (linear on each side of 0: the car
    brakes harder than it accelerates); ``action[1]`` = +-1 is +-``p.max_steer`` (positive steers left).

    Args:
        action: ``[2]`` normalised ``(acceleration, steering)``.
        p: the vehicle's limits.

    Returns:
        ``(acceleration, steering)`` in m/s^2 and radians.
    """
    a = np.clip(np.asarray(action, np.float64).reshape(2), -1.0, 1.0)
    accel = a[0] * (p.max_accel if a[0] >= 0 else p.max_decel)
    return float(accel), float(a[1] * p.max_steer)


def to_action(accel: float, steer: float, p: VehicleParams) -> np.ndarray:
    """Inverse of ``to_controls``: the float32 normalised action for physical controls (clipped to the limits).

    Args:
        accel: acceleration in m/s^2 (negative brakes).
        steer: steering angle in radians (positive left).
        p: the vehicle's limits.

    Returns:
        ``[2]`` float32 action in [-1, 1].
    """
    a = accel / (p.max_accel if accel >= 0 else p.max_decel)
    return np.clip(np.array([a, steer / p.max_steer], np.float32), -1.0, 1.0)


def drive(state: VehicleState, action: Sequence[float] | np.ndarray, p: VehicleParams
          ) -> tuple[VehicleState, tuple[float, float]]:
    """The ego one ``p.dt`` later under a normalised action (``to_controls``, then ``parksim.vehicle.step``).

    Args:
        state: the ego now.
        action: ``[2]`` normalised ``(acceleration, steering)``.
        p: the vehicle.

    Returns:
        ``(next state, (acceleration m/s^2, steering command rad))``.

    Raises:
        ValueError: ``action`` holds a NaN or an infinity (refused: nothing was stepped).
    """
    if not np.isfinite(np.asarray(action, np.float64)).all():
        raise ValueError(f"action {np.asarray(action).tolist()} has a non-finite value (NaN or inf): refused, "
                         "the vehicle state is unchanged")
    accel, steer = to_controls(action, p)
    return step(state, accel, steer, p), (accel, steer)


def parking_errors(pose: Sequence[float], slot: dict[str, Any], p: VehicleParams) -> tuple[float, float]:
    """How far the car is from parked in ``slot``.

    Args:
        pose: the rear-axle ``(x, y, yaw)``.
        slot: the target slot (``corners``).
        p: the vehicle (where its body centre is).

    Returns:
        ``(distance of the body centre to the slot centre in m, heading error to the slot axis in rad)``.
    """
    centre, slot_yaw = slot_pose(slot)
    dist = float(np.linalg.norm(car_centre(pose, p) - centre))
    return dist, heading_error(pose[2], slot_yaw)


def is_parked(distance: float, heading: float, speed: float, pos_tol: float, yaw_tol: float) -> bool:
    """Parked: the body centre within ``pos_tol``, the heading within ``yaw_tol`` of the slot axis, stopped.

    Args:
        distance: body centre to slot centre (m).
        heading: heading error to the slot axis (rad).
        speed: the car's speed (m/s).
        pos_tol: the distance tolerance (m).
        yaw_tol: the heading tolerance (rad).

    Returns:
        Whether the car is parked.
    """
    return distance < pos_tol and heading < yaw_tol and abs(speed) < STOPPED_SPEED


def progress_cost(distance: float, heading: float) -> float:
    """What the reward decreases: the distance (m) plus ``YAW_WEIGHT`` times the heading error (rad).

    Args:
        distance: body centre to slot centre (m).
        heading: heading error to the slot axis (rad).

    Returns:
        The cost.
    """
    return distance + YAW_WEIGHT * heading


def reward(cost_before: float, cost_after: float, success: bool, collided: bool) -> float:
    """One step's reward: the progress made, less the step cost, plus the bonus when parked, less the penalty.

    Args:
        cost_before: ``progress_cost`` before the step.
        cost_after: ``progress_cost`` after it.
        success: parked (and untouched) after the step.
        collided: touched something during the step.

    Returns:
        The reward.
    """
    return float(cost_before - cost_after - STEP_COST + SUCCESS_BONUS * success - COLLISION_PENALTY * collided)


def slot_in_ego_frame(pose: Sequence[float], slot: dict[str, Any]) -> tuple[float, float, float]:
    """The slot's centre and parking heading in the ego frame.

    Args:
        pose: the rear-axle ``(x, y, yaw)``.
        slot: the target slot (``corners``).

    Returns:
        ``(x, y, yaw)``: metres with x forward, y left and the origin under the rear axle; radians.
    """
    centre, slot_yaw = slot_pose(slot)
    x, y, yaw = pose
    dx, dy = centre[0] - x, centre[1] - y
    c, si = math.cos(yaw), math.sin(yaw)
    return (c * dx + si * dy, -si * dx + c * dy, float(wrap_angle(slot_yaw - yaw)))


def step_info(state: VehicleState, slot: dict[str, Any], p: VehicleParams, pos_tol: float, yaw_tol: float,
              collided: bool, privileged: bool) -> dict[str, Any]:
    """The info dict of a reset or a step.

    Args:
        state: the ego now.
        slot: the target slot.
        p: the vehicle.
        pos_tol: the success distance (m).
        yaw_tol: the success heading error (rad).
        collided: whether the ego touched something.
        privileged: add the world ``pose``.

    Returns:
        ``slot`` (id), ``distance``, ``heading_error``, ``collision``, ``is_success`` (parked and untouched),
        ``speed``, and ``pose`` when privileged.
    """
    dist, yaw_err = parking_errors(state.pose, slot, p)
    parked = is_parked(dist, yaw_err, state.v, pos_tol, yaw_tol)
    info = {"slot": slot["id"], "distance": dist, "heading_error": yaw_err, "collision": bool(collided),
            "is_success": bool(parked and not collided), "speed": state.v}
    return info | {"pose": state.pose} if privileged else info


def observation(state: VehicleState, slot: dict[str, Any], privileged: bool, frame: Frame | None
                ) -> dict[str, np.ndarray]:
    """The observation of the ego in ``state`` aiming at ``slot``, with ``frame``'s views.

    Args:
        state: the ego now.
        slot: the target slot.
        privileged: add the world ``pose``.
        frame: the views rendered at ``state.pose``, or None.

    Returns:
        ``state`` float32 ``[v, steer, slot_x, slot_y, slot_yaw]`` (slot in the ego frame), ``pose`` float32
        ``[x, y, yaw]`` when privileged, uint8 ``[H, W, 3]`` per view of ``frame`` and its ``bev`` if any.
    """
    obs: dict[str, np.ndarray] = {"state": np.array([state.v, state.steer, *slot_in_ego_frame(state.pose, slot)],
                                                    np.float32)}
    if privileged:
        obs["pose"] = np.array(state.pose, np.float32)
    if frame is not None:
        obs.update(frame.images)
        if frame.bev is not None:
            obs["bev"] = frame.bev
    return obs
