"""Parking through perception: the slot detector finds the target on the rendered BEV, ``GeometricParker`` drives.

No world pose is used. The planner works in its odometry frame (the ego frame at the episode's start) and
tracks the ego there by dead reckoning: the commanded actions integrated with the env's kinematic model
(``parksim.vehicle.step``). Every ``every`` steps it takes a BEV, detects slots (``parksim.recon.detectors``), turns
them into ground rectangles in the odometry frame (entrance from the two marking points, depth by slot kind)
and picks the one nearest the target the env names in the ego frame (``state[2:4]``, read only to say which
slot: the geometry parked into is the detected one). It replans when the estimate moves, treating the other
detected slots' inner parts as obstacles (occupancy is not detected), until the car reaches the entrance; the last
plan is then followed in. Each plan asks ``GeometricParker`` (forward, one smooth turn) first and, where it finds no
path, ``HybridAStarParker`` (forward and reverse, cusps): the path found is tracked by the parker that found it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..env import ParkingEnv, heading_error, slot_pose, to_controls
from ..rig import BEVSpec
from ..vehicle import Obstacles, VehicleParams, VehicleState, step
from .geometric import GeometricParker
from .hybrid_astar import HybridAStarConfig
from .hybrid_parker import HybridAStarParker

__all__ = ["SlotDepths", "detected_slots", "PerceptionParker", "run_perception_episode"]


@dataclass(frozen=True)
class SlotDepths:
    """Slot depth (m) by kind, which the detector does not see: ps2.0-like bays, as ``parksim synth`` lays out."""

    perpendicular: float = 5.3
    slanted: float = 5.0
    parallel: float = 2.5
    parallel_width: float = 4.5   # an entrance longer than this (m) is a parallel slot

    def depth(self, entrance: float, angle_deg: float) -> float:
        if entrance > self.parallel_width:
            return self.parallel
        return self.perpendicular if abs(angle_deg - 90.0) < 10.0 else self.slanted


def detected_slots(detections: Any, spec: BEVSpec, depths: SlotDepths = SlotDepths()) -> list[np.ndarray]:
    """Corners ``(4, 2)`` in the vehicle frame of each detected slot, ordered as the map's: entrance p1, p2, then in.

    ``detections`` is one ``parksim.recon.detectors.Detections`` of a BEV with ``spec``. The separator direction is the
    mean of the two points' image directions, mapped to the vehicle frame (image (du, dv) = vehicle (-dy, -dx)).
    """
    out = []
    for slot in detections.slots:
        a, b = detections.points[slot.p1], detections.points[slot.p2]
        ends = spec.pixel_to_ground(torch.tensor([[a.x, a.y], [b.x, b.y]], dtype=torch.float64)).numpy()
        du = math.cos(a.direction) + math.cos(b.direction)
        dv = math.sin(a.direction) + math.sin(b.direction)
        into = np.array([-dv, -du]) / math.hypot(du, dv)
        depth = depths.depth(float(np.linalg.norm(ends[1] - ends[0])), slot.angle)
        out.append(np.array([ends[0], ends[1], ends[1] + into * depth, ends[0] + into * depth]))
    return out


def _to_frame(pose: tuple[float, float, float], local: np.ndarray) -> np.ndarray:
    """Points ``(..., 2)`` given in the frame of ``pose`` expressed in the frame ``pose`` is given in."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def _inner_box(corners: np.ndarray, skip: float) -> dict[str, Any]:
    """The part of a slot rectangle deeper than ``skip`` m past its entrance, as a map obstacle box."""
    entrance, back = corners[:2].mean(axis=0), corners[2:].mean(axis=0)
    into = back - entrance
    depth = float(np.linalg.norm(into))
    width = float(np.linalg.norm(corners[1] - corners[0]))
    centre = entrance + into * (skip + depth) / (2 * depth)
    return {"kind": "car", "center": centre.tolist(), "size": [depth - skip, width],
            "yaw": math.atan2(into[1], into[0])}


@dataclass
class PerceptionParker:
    """Detect, dead-reckon, plan and track; ``start`` with the first observation, then ``act`` every step.

    ``detector`` is a trained ``parksim.recon.detectors`` model (``detect(bev, m_per_px)``); ``spec`` the env's BEV.
    """

    detector: Any
    spec: BEVSpec
    vehicle: VehicleParams = VehicleParams()
    every: int = 5                 # steps between BEVs
    match_radius: float = 2.0      # m between a detected slot's centre and the env's target to take it
    replan_tol: float = 0.08       # m a corner must move before the path is replanned
    keep_m: float = 3.0            # m of path left below which it is no longer replanned
    detour_m: float = 2.0          # m a replanned path may be longer than the rest of the current one
    depths: SlotDepths = SlotDepths()
    parkers: tuple[GeometricParker | HybridAStarParker, ...] = ()   # tried in order; default: geometric, hybrid

    def __post_init__(self) -> None:
        self.planners = self.parkers or (GeometricParker(self.vehicle), HybridAStarParker(
            self.vehicle, config=HybridAStarConfig(max_nodes=5000, max_seconds=math.inf)))
        self.tracker: GeometricParker | HybridAStarParker = self.planners[0]
        self.state = VehicleState(0.0, 0.0, 0.0)
        self.goal: np.ndarray | None = None          # target corners in the odometry frame
        self.perceived = False                       # whether ``goal`` came from a detection
        self.detections = 0
        self._steps = 0

    # --- perception ----------------------------------------------------------------------
    def _target_hint(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The env's target slot centre, moved from the ego frame to the odometry frame."""
        return _to_frame(self.state.pose, np.asarray(obs["state"][2:4], np.float64))

    def _hinted_slot(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """A perpendicular slot at the env's target (its centre and heading): the goal until the slot is seen."""
        x, y, yaw = (float(v) for v in obs["state"][2:5])
        depth, half = self.depths.perpendicular, 1.25
        local = np.array([[-depth / 2, half], [-depth / 2, -half], [depth / 2, -half], [depth / 2, half]])
        c, s = math.cos(yaw), math.sin(yaw)
        ego = local @ np.array([[c, s], [-s, c]]) + np.array([x, y])
        return _to_frame(self.state.pose, ego)

    def perceive(self, obs: dict[str, np.ndarray]) -> list[np.ndarray]:
        """All detected slots of ``obs["bev"]`` as corners in the odometry frame."""
        bev = torch.from_numpy(np.ascontiguousarray(obs["bev"])).permute(2, 0, 1).float()[None] / 255.0
        detections = self.detector.detect(bev, self.spec.m_per_px)[0]
        self.detections += 1
        return [_to_frame(self.state.pose, c) for c in detected_slots(detections, self.spec, self.depths)]

    def _remaining(self) -> float:
        """Metres of the current path left from its point nearest the dead-reckoned pose (inf without a path)."""
        path = self.tracker.path
        if path is None:
            return math.inf
        near = int(np.argmin(np.hypot(path[:, 0] - self.state.x, path[:, 1] - self.state.y)))
        return _length(path[near:])

    def _moved(self, goal: np.ndarray) -> bool:
        """Whether ``goal`` parks elsewhere than the current goal: centre beyond ``replan_tol`` or axis 0.03 rad."""
        if self.goal is None:
            return True
        (c0, yaw0), (c1, yaw1) = slot_pose({"corners": self.goal}), slot_pose({"corners": goal})
        return bool(np.linalg.norm(c1 - c0) > self.replan_tol or heading_error(yaw1, yaw0) > 0.03)

    def update(self, obs: dict[str, np.ndarray]) -> None:
        """Take a BEV, find the target among the detected slots, and replan when it parks elsewhere.

        A new path is taken only if it is at most ``detour_m`` longer than what is left of the current one: from a
        moving car close to the slot the shortest forward path to a shifted goal can be a loop.
        """
        slots = self.perceive(obs)
        hint = self._target_hint(obs)
        near = [c for c in slots if np.linalg.norm(c.mean(axis=0) - hint) < self.match_radius]
        if near:
            goal = min(near, key=lambda c: float(np.linalg.norm(c.mean(axis=0) - hint)))
        elif self.goal is None:
            goal = self._hinted_slot(obs)
        else:
            return
        remaining = self._remaining()
        if self._moved(goal) and remaining > self.keep_m:
            others = Obstacles([_inner_box(c, 0.6) for c in slots if c is not goal])
            found = self._plan({"corners": goal.tolist()}, others) or self._plan({"corners": goal.tolist()},
                                                                                Obstacles([]))
            if found is None or _length(found[1]) > remaining + self.detour_m:
                return
            self.goal, self.tracker = goal, found[0]
            self.tracker.follow(found[1])
        self.perceived = self.perceived or bool(near)

    def _plan(self, slot: dict[str, Any], obstacles: Obstacles
              ) -> tuple[GeometricParker | HybridAStarParker, np.ndarray] | None:
        """The first of ``planners`` that finds a path from the dead-reckoned pose into ``slot``, and its path."""
        for parker in self.planners:
            path = parker.plan(self.state.pose, slot, obstacles)
            if path is not None:
                return parker, path
        return None

    # --- control -------------------------------------------------------------------------
    def start(self, obs: dict[str, np.ndarray]) -> None:
        """Begin an episode at the odometry origin with the first observation (it must hold the BEV)."""
        self.state = VehicleState(0.0, 0.0, 0.0, float(obs["state"][0]), float(obs["state"][1]))
        self.goal, self.perceived, self.detections, self._steps = None, False, 0, 0
        self.tracker = self.planners[0]
        for parker in self.planners:
            parker.path = None
        self.update(obs)

    @property
    def wants_view(self) -> bool:
        """Whether the observation after the action just taken should hold a BEV (every ``every`` steps)."""
        return self._steps % self.every == 0

    def act(self, obs: dict[str, np.ndarray] | None) -> np.ndarray | None:
        """The next normalised action (None when no path could be planned); ``obs`` with a BEV or None."""
        if obs is not None and "bev" in obs and self._steps > 0:
            self.update(obs)
        if self.tracker.path is None:
            return None
        motion = np.array([self.state.v, self.state.steer], np.float32)
        action = self.tracker.act({"pose": np.array(self.state.pose, np.float32), "state": motion})
        self.state = step(self.state, *to_controls(action, self.vehicle), self.vehicle)
        self._steps += 1
        return action


def _length(path: np.ndarray) -> float:
    """A path's length in metres."""
    return float(np.hypot(*np.diff(path[:, :2], axis=0).T).sum())


def run_perception_episode(env: ParkingEnv, seed: int, planner: PerceptionParker,
                           options: dict[str, Any] | None = None, max_steps: int = 500) -> dict[str, Any]:
    """Reset with ``seed`` (and ``options``), park through ``planner``; final info + steps, BEVs taken, perceived.

    ``env`` renders the BEV (``bev=True``). Steps between the planner's views go through ``env.advance``,
    which renders nothing: the planner would ignore those images.
    """
    if not env.bev:
        raise ValueError("run_perception_episode needs a ParkingEnv made with bev=True")
    obs, info = env.reset(seed=seed, options=options)
    planner.start(obs)
    steps, done, view = 0, False, None
    while not done and steps < max_steps:
        action = planner.act(view)
        if action is None:
            break
        if planner.wants_view:
            view, _, terminated, _, info = env.step(action)
        else:
            view = None
            _, terminated, info = env.advance(action)
        steps, done = steps + 1, terminated
    return {**info, "steps": steps, "planned": planner.goal is not None, "perceived": planner.perceived,
            "views": planner.detections}
