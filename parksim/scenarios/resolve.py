"""A scenario made concrete on its scene's map: the start pose, the target slot, the map with the filled slots.

This is the one place that reads a scenario against a map (``map.json``: ``slots`` with ``corners``,
``obstacles`` as boxes), so the env, the episode API and the set generator start the same episode from the same
file. Only the ego's start draws from the seed (stream ``(0,)``, ``world.generator``); the actors draw from theirs.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..vehicle import Obstacles, VehicleParams, car_centre, footprint, wrap_angle
from .shapes import Box, box_polygon, overlaps
from .spec import BUILTIN_BOXES, Scenario, ScenarioError
from .task import free_slots, slot_pose
from .world import generator

__all__ = ["Setup", "prepare", "START_TRIES", "START_MARGIN"]

Pose = tuple[float, float, float]
START_TRIES = 200
"""Draws from the start region before giving up (as the env's random start)."""
START_MARGIN = 0.3
"""Clearance (m) a drawn start keeps around the body, as the env's random start."""


@dataclass(frozen=True)
class Setup:
    """Everything an episode of a scenario needs from its map.

    Attributes:
        start: the ego's rear-axle start pose ``(x, y, yaw)``, yaw in [-pi, pi).
        slot: the target slot (a ``slots`` entry of ``world_map``).
        world_map: the scene's map with the ``occupy`` slots marked occupied and a parked car box each in
            ``obstacles`` (``kind: car``); the input map is not changed.
        parked: the built-in car asset's pose in each filled slot, in ``occupy`` order (to render them).
        pos_tol: the success distance (m), as ``ParkingEnv(pos_tol=)``.
        yaw_tol: the success heading error (rad), as ``ParkingEnv(yaw_tol=)``.
        max_steps: steps in the time limit at the given ``dt``.
    """

    start: Pose
    slot: dict[str, Any]
    world_map: dict[str, Any]
    parked: tuple[Pose, ...]
    pos_tol: float
    yaw_tol: float
    max_steps: int


def _parked_car(slot: dict[str, Any], box: Box) -> tuple[Pose, dict[str, Any]]:
    """The car asset's pose centred in ``slot`` along its axis, and its obstacle box for the map."""
    centre, yaw = slot_pose(slot)
    offset = np.array([(box[0] + box[1]) / 2, (box[2] + box[3]) / 2])
    c, s = math.cos(yaw), math.sin(yaw)
    origin = centre - np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]])
    obstacle = {"kind": "car", "center": [float(centre[0]), float(centre[1])],
                "size": [box[1] - box[0], box[3] - box[2]], "yaw": yaw}
    return (float(origin[0]), float(origin[1]), yaw), obstacle


def _fill(scenario: Scenario, world_map: dict[str, Any]) -> tuple[dict[str, Any], tuple[Pose, ...]]:
    """A copy of the map with the ``occupy`` slots filled, and the parked cars' poses."""
    filled = copy.deepcopy(world_map)
    by_id = {s["id"]: s for s in filled.get("slots", [])}
    parked = []
    for i, slot_id in enumerate(scenario.occupy):
        slot = by_id.get(slot_id)
        if slot is None:
            raise ScenarioError(f"scenario {scenario.name!r}: occupy.{i}: slot {slot_id} is not in the map of "
                                f"{scenario.scene!r} (ids {_ids(filled)})")
        if slot.get("occupied"):
            raise ScenarioError(f"scenario {scenario.name!r}: occupy.{i}: slot {slot_id} is occupied already")
        pose, obstacle = _parked_car(slot, BUILTIN_BOXES["car"])
        slot["occupied"] = True
        filled.setdefault("obstacles", []).append(obstacle)
        parked.append(pose)
    return filled, tuple(parked)


def _ids(world_map: dict[str, Any]) -> str:
    """The map's slot ids, shortened."""
    ids = [str(s["id"]) for s in world_map.get("slots", [])]
    return ", ".join(ids) if len(ids) <= 12 else f"{', '.join(ids[:12])}, ..."


def _start(scenario: Scenario, blocked: Obstacles, actors: np.ndarray, vehicle: VehicleParams) -> Pose:
    """The given start pose (refused when the body touches something), or the first clear draw from the region."""
    ego = scenario.ego
    if ego.pose is not None:
        x, y, yaw = ego.pose
        body = footprint((x, y, yaw), vehicle)
        if blocked.hits(body).any() or overlaps(body[None], actors).any():
            raise ScenarioError(f"scenario {scenario.name!r}: ego.pose: the body at {list(ego.pose)} touches an "
                                "obstacle, a parked car or an actor")
        return (x, y, float(wrap_angle(yaw)))
    region = ego.region
    assert region is not None          # EgoStart holds exactly one of pose and region
    rng = generator(scenario.seed, 0)
    for _ in range(START_TRIES):
        x, y, yaw = (float(rng.uniform(*span)) for span in (region.x, region.y, region.yaw))
        body = footprint((x, y, yaw), vehicle, START_MARGIN)
        if not blocked.hits(body).any() and not overlaps(body[None], actors).any():
            return (x, y, float(wrap_angle(yaw)))
    raise ScenarioError(f"scenario {scenario.name!r}: ego.region: no start {START_MARGIN:g} m clear of obstacles "
                        f"and actors in {START_TRIES} draws")


def _target(scenario: Scenario, world_map: dict[str, Any], start: Pose, vehicle: VehicleParams) -> dict[str, Any]:
    """The target slot: the given free slot, or the free slot whose centre is nearest the ego's body centre."""
    free = free_slots(world_map)
    if scenario.target == "nearest_free":
        if not free:
            raise ScenarioError(f"scenario {scenario.name!r}: target: no free slot in {scenario.scene!r}")
        body = car_centre(start, vehicle)
        return min(free, key=lambda s: float(np.linalg.norm(slot_pose(s)[0] - body)))
    chosen = [s for s in free if s["id"] == scenario.target]
    if not chosen:
        known = any(s["id"] == scenario.target for s in world_map.get("slots", []))
        raise ScenarioError(f"scenario {scenario.name!r}: target: slot {scenario.target} "
                            f"{'is occupied' if known else 'is not in the map'} (free: {[s['id'] for s in free]})")
    return chosen[0]


def prepare(scenario: Scenario, world_map: Mapping[str, Any], vehicle: VehicleParams = VehicleParams(),
            asset_boxes: Mapping[str, Box] | None = None) -> Setup:
    """Make a scenario concrete on its scene's map.

    Args:
        scenario: the scenario.
        world_map: the scene's ``map.json`` content (slots, obstacles).
        vehicle: the ego (its body for the start checks, ``dt`` for the step count).
        asset_boxes: footprints of actor assets read from their folders (``ActorSpec.resolved_box``).

    Returns:
        The setup.

    Raises:
        ScenarioError: a slot of ``occupy`` or ``target`` missing or occupied, a start pose touching something, or
            no clear start in the region.
    """
    filled, parked = _fill(scenario, dict(world_map))
    actors = (np.stack([box_polygon(a.pose, a.resolved_box(asset_boxes)) for a in scenario.actors])
              if scenario.actors else np.zeros((0, 4, 2)))
    start = _start(scenario, Obstacles(filled.get("obstacles", [])), actors, vehicle)
    slot = _target(scenario, filled, start, vehicle)
    return Setup(start, slot, filled, parked, scenario.tolerance.position, math.radians(scenario.tolerance.heading),
                 max(1, math.ceil(scenario.time_limit / vehicle.dt - 1e-9)))
