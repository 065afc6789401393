"""A parking controller that plans with Hybrid A* over Reeds-Shepp curves and tracks paths with reverse segments.

``HybridAStarParker`` has ``GeometricParker``'s interface (``choose_slot``, ``plan``, ``follow``, ``act``), so
``run_episode(env, seed, parker=HybridAStarParker(...))`` drives a privileged ``ParkingEnv`` with it. A slot has
two goals, parked head-in and reversed in (the env accepts either heading); the search returns the cheaper it
reaches. Other road users enter as extra obstacle polygons (``actors``: their predicted footprints, optionally in
time windows of the plan's clock).

The path is split at its cusps into segments of one direction each. Each is tracked by pure pursuit on the rear
axle (for a backward segment the geometry is mirrored: the look-ahead point is taken behind the car and the
steering sign flips) with a speed profile that stops on the segment's end. At a cusp the car waits, standing,
until its wheels have turned to the next segment's first steering angle, then drives on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..env import free_slots, slot_pose, to_action
from ..vehicle import Obstacles, VehicleParams
from .hybrid_astar import FootprintChecker, HybridAStarConfig, PlanResult, TimedPolygon, hybrid_astar

__all__ = ["HybridAStarParker", "slot_goals"]

_BOUNDS_SLACK = 2.0
"""Metres the search may go beyond the box around the obstacles, start and goals (walls bound a garage anyway)."""


def slot_goals(slot: dict[str, Any], vehicle: VehicleParams) -> list[tuple[float, float, float]]:
    """The rear-axle poses that park the car centred in ``slot``: head-in, then reversed in.

    Args:
        slot: a map slot (``corners`` ``[4, 2]``).
        vehicle: the car (where its body centre is from the rear axle).

    Returns:
        ``[(x, y, yaw) head-in, (x, y, yaw + pi) reversed in]`` in metres and radians.
    """
    centre, yaw = slot_pose(slot)
    x0, x1, _, _ = vehicle.extent
    d = (x0 + x1) / 2
    c, s = math.cos(yaw), math.sin(yaw)
    return [(float(centre[0] - d * c), float(centre[1] - d * s), yaw),
            (float(centre[0] + d * c), float(centre[1] + d * s), yaw + math.pi)]


@dataclass
class _Segment:
    """A stretch of the path driven in one direction: poses ``[n, 3]``, their arc length ``[n]``, +1 or -1."""

    poses: np.ndarray
    arc: np.ndarray
    direction: int


def _segments(path: np.ndarray) -> list[_Segment]:
    """``path`` ``[N, 4]`` cut at its cusps; each segment ends on the pose the next one starts from."""
    cuts = [0, *(np.flatnonzero(np.diff(path[:-1, 3]) != 0) + 1), len(path) - 1]
    out = []
    for a, b in zip(cuts, cuts[1:]):
        poses = path[a:b + 1, :3]
        seg = np.hypot(*np.diff(poses[:, :2], axis=0).T)
        out.append(_Segment(poses, np.concatenate([[0.0], np.cumsum(seg)]), int(path[a, 3])))
    return out


@dataclass
class HybridAStarParker:
    """Plans with Hybrid A* into a slot, head-in or reversing, and tracks the path, cusps included.

    Attributes:
        vehicle: the car (size, turning radius, limits).
        config: the search's lattice, moves, costs and budgets.
        margin: clearance added around the footprint when planning (m): room for the tracking error.
        actors: extra convex obstacles (other road users' predicted footprints), ``[K, 2]`` or ``TimedPolygon``.
        lookahead: pure-pursuit look-ahead distance (m).
        cruise: top speed forward (m/s).
        reverse_speed: top speed backward (m/s).
        brake: deceleration of the speed profile towards a segment's end (m/s^2), also fed forward while braking.
        gain: speed-error gain of the acceleration command (1/s).
        steer_ready: at a cusp, how close the wheels must be to the next steering angle before driving on (rad).
        stop_speed: below this speed (m/s) the car counts as standing at a cusp.
        arrive: a segment's end counts as reached this close along the path (m).
    """

    vehicle: VehicleParams = VehicleParams()
    config: HybridAStarConfig = HybridAStarConfig()
    margin: float = 0.15
    actors: Sequence[np.ndarray | TimedPolygon] = field(default_factory=list)
    lookahead: float = 0.9
    cruise: float = 1.2
    reverse_speed: float = 0.8
    brake: float = 0.8
    gain: float = 2.0
    steer_ready: float = 0.1
    stop_speed: float = 0.05
    arrive: float = 0.1

    def __post_init__(self) -> None:
        """No path to follow yet."""
        self.path: np.ndarray | None = None
        self.result: PlanResult | None = None
        self._segments: list[_Segment] = []
        self._segment = self._index = 0
        self._rolling = False   # the wheels were ready and the car has set off on the current segment

    def plan(self, pose: tuple[float, float, float], slot: dict[str, Any], obstacles: Obstacles) -> np.ndarray | None:
        """A collision-free path ``[N, 4]`` from ``pose`` to parked in ``slot`` (head-in or reversed in).

        The search's outcome, path or cause of failure, stays in ``self.result``.

        Args:
            pose: the car's rear-axle ``(x, y, yaw)`` (metres, radians).
            slot: a map slot (``corners`` ``[4, 2]``).
            obstacles: the boxes the footprint must clear (``actors`` are added to them).

        Returns:
            ``[N, 4]`` ``(x, y, yaw, direction)`` (``PlanResult.path``), or None when the search found none.
        """
        goals = slot_goals(slot, self.vehicle)
        checker = FootprintChecker(self.vehicle, obstacles, self.actors, self.margin)
        points = np.concatenate([checker.polygons.reshape(-1, 2), [pose[:2]], np.array(goals)[:, :2]])
        low, high = points.min(axis=0) - _BOUNDS_SLACK, points.max(axis=0) + _BOUNDS_SLACK
        self.result = hybrid_astar(pose, goals, checker, ((low[0], high[0]), (low[1], high[1])), self.vehicle,
                                   self.config)
        return self.result.path

    def choose_slot(self, pose: tuple[float, float, float], world_map: dict[str, Any]
                    ) -> tuple[int, np.ndarray] | None:
        """The free slot with the cheapest path from ``pose``, and that path.

        Slots are planned nearest first; a slot whose goals are farther in a straight line than the cheapest path
        found so far costs is skipped (a path costs at least its length).

        Args:
            pose: the car's rear-axle ``(x, y, yaw)`` (metres, radians).
            world_map: the scene's map (``slots``, ``obstacles``).

        Returns:
            ``(slot id, path [N, 4])``, or None when no free slot can be reached.
        """
        obstacles = Obstacles(world_map.get("obstacles", []))

        def reach(slot: dict[str, Any]) -> float:
            return min(math.hypot(g[0] - pose[0], g[1] - pose[1]) for g in slot_goals(slot, self.vehicle))

        best: tuple[float, int, np.ndarray] | None = None
        for slot in sorted(free_slots(world_map), key=reach):
            if best is not None and reach(slot) >= best[0]:
                break
            path = self.plan(pose, slot, obstacles)
            if path is not None and self.result is not None and (best is None or self.result.cost < best[0]):
                best = (self.result.cost, slot["id"], path)
        return None if best is None else (best[1], best[2])

    def follow(self, path: np.ndarray) -> None:
        """Start tracking ``path``.

        Args:
            path: ``[N, 4]`` poses ``(x, y, yaw, direction)`` as ``plan`` gives them, or ``[N, 3]`` driven forward.

        Raises:
            ValueError: ``path`` is not ``[N, 3]`` or ``[N, 4]`` with N >= 2.
        """
        path = np.asarray(path, np.float64)
        if path.ndim != 2 or path.shape[1] not in (3, 4) or len(path) < 2:
            raise ValueError(f"a path must be [N, 3] or [N, 4] poses with N >= 2, got shape {path.shape}")
        if path.shape[1] == 3:
            path = np.column_stack([path, np.ones(len(path))])
        self.path = path
        self._segments = _segments(path)
        self._segment = self._index = 0
        self._rolling = False

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The normalised action for a privileged observation (world ``pose``, ``state`` ``[v, steer, ...]``).

        Args:
            obs: a ``ParkingEnv`` observation with ``pose`` ``[x, y, yaw]`` and ``state`` ``[v, steer, ...]``.

        Returns:
            ``[2]`` float32 normalised ``(acceleration, steering)``.

        Raises:
            RuntimeError: no path to follow (``follow`` was not called).
        """
        if not self._segments:
            raise RuntimeError("HybridAStarParker.act: no path to follow; call follow(path) first")
        x, y, yaw = (float(s) for s in obs["pose"])
        v, wheels = float(obs["state"][0]), float(obs["state"][1])
        seg, remaining = self._progress(x, y)
        if (remaining < self.arrive and abs(v) < self.stop_speed and self._segment + 1 < len(self._segments)):
            self._segment, self._index, self._rolling = self._segment + 1, 0, False
            seg, remaining = self._progress(x, y)
        steer = self._pursuit(seg, x, y, yaw)
        top = self.cruise if seg.direction > 0 else self.reverse_speed
        stopping = math.sqrt(2 * self.brake * max(remaining - 0.5 * self.arrive, 0.0))
        v_ref = seg.direction * min(top, stopping)
        braking = 0.0 < stopping < top and v * seg.direction > 0   # on the stopping curve, moving along the segment
        feedforward = -seg.direction * self.brake * braking
        self._rolling = self._rolling or abs(steer - wheels) <= self.steer_ready
        if not self._rolling:
            v_ref = feedforward = 0.0   # at a cusp or the start: turn the wheels first
        return to_action(self.gain * (v_ref - v) + feedforward, steer, self.vehicle)

    def upcoming(self, metres: float) -> np.ndarray:
        """The poses of the path still ahead over about ``metres`` of arc length.

        They start at the car's place on the path and run across cusps (the segments after the current one follow).

        Args:
            metres: how far ahead (m).

        Returns:
            ``[k, 3]`` poses ``(x, y, yaw)`` in driving order; ``[0, 3]`` without a path.
        """
        out, left = [], metres
        for i, seg in enumerate(self._segments[self._segment:]):
            start = self._index if i == 0 else 0
            stop = int(np.searchsorted(seg.arc, seg.arc[start] + left, side="right"))
            out.append(seg.poses[start:max(stop, start + 1)])
            left -= seg.arc[min(stop, len(seg.arc)) - 1] - seg.arc[start]
            if left <= 0:
                break
        return np.concatenate(out) if out else np.zeros((0, 3))

    def _progress(self, x: float, y: float) -> tuple[_Segment, float]:
        """Advance the nearest-pose index on the current segment; the segment and the metres left to its end."""
        seg = self._segments[self._segment]
        window = seg.poses[self._index:self._index + 40, :2]
        self._index += int(np.argmin(np.hypot(window[:, 0] - x, window[:, 1] - y)))
        if self._index < len(seg.poses) - 1:
            return seg, float(seg.arc[-1] - seg.arc[self._index])
        end = seg.poses[-1]
        along = (end[0] - x) * math.cos(end[2]) + (end[1] - y) * math.sin(end[2])
        return seg, along * seg.direction

    def _pursuit(self, seg: _Segment, x: float, y: float, yaw: float) -> float:
        """Pure-pursuit steering towards the point ``lookahead`` metres on along ``seg``, mirrored when backward.

        Past the segment's end the point lies on the line of its last pose.

        Returns:
            The steering angle (rad), within the lock.
        """
        target = seg.arc[self._index] + self.lookahead
        end = seg.poses[-1]
        if target <= seg.arc[-1]:
            tx, ty = seg.poses[np.searchsorted(seg.arc, target), :2]
        else:
            extra = (target - seg.arc[-1]) * seg.direction
            tx, ty = end[0] + extra * math.cos(end[2]), end[1] + extra * math.sin(end[2])
        heading = yaw if seg.direction > 0 else yaw + math.pi
        alpha = math.atan2(ty - y, tx - x) - heading
        distance = max(math.hypot(tx - x, ty - y), 1e-3)
        steer = seg.direction * math.atan2(2 * self.vehicle.wheelbase * math.sin(alpha), distance)
        return min(max(steer, -self.vehicle.max_steer), self.vehicle.max_steer)
