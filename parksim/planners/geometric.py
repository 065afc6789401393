"""A geometric parking controller: Dubins path to the slot's axis, straight in, pure-pursuit tracking.

It uses what a privileged ``ParkingEnv`` exposes (``privileged=True``: the world pose; the slot map and
obstacles): for the target slot it builds candidate paths (Dubins curves at a few turning radii to an entry pose on
the slot axis, then straight to the head-in parking pose), keeps the shortest whose swept
footprint clears every obstacle, and follows it with pure pursuit and a speed profile that stops
on the goal. The example of closed-loop use; not an optimal planner (forward moves only).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import gymnasium as gym
import numpy as np

from ..env import ParkingEnv, free_slots, slot_pose, to_action
from ..vehicle import Obstacles, VehicleParams, footprint, wrap_angle

__all__ = ["GeometricParker", "Parker", "dubins_paths", "run_episode"]

_TWO_PI = 2 * math.pi


_ZERO_ARC = 1e-6
"""Radians: a wrapped arc this close below 2 pi is a zero arc that rounding pushed below 0 (a -1e-16 arc wraps to
2 pi - 1e-16, a full extra loop). Arcs that pass through ``sqrt`` of a rounded ``p^2`` carry errors of
~sqrt(eps) ~ 1e-8 (``_root``); a real arc of 1e-6 rad is micrometres at a turning radius of metres."""


def _mod(a: float) -> float:
    """``a`` wrapped to [0, 2 pi), with arcs within ``_ZERO_ARC`` below 2 pi taken as 0."""
    wrapped = a % _TWO_PI
    return 0.0 if _TWO_PI - wrapped < _ZERO_ARC else wrapped


def _rounding(d: float) -> float:
    """Bound of the rounding error of the ``p^2`` and ``8 c`` sums of ``_words``.

    Args:
        d: distance between start and goal over the turning radius.

    Returns:
        16 eps times the magnitude of the sums' terms, 4 + d^2 + 4 d.
    """
    return 16 * sys.float_info.epsilon * (4 + d * d + 4 * d)


def _root(p2: float, d: float) -> float | None:
    """``sqrt(p2)`` of a Dubins word's squared straight length, rounding below 0 forgiven.

    Args:
        p2: the word's ``p^2`` as computed.
        d: distance between start and goal over the turning radius (sets the rounding bound, ``_rounding``).

    Returns:
        ``sqrt(max(p2, 0))`` when ``p2`` is at least minus its rounding bound, else None (the word does not exist).
    """
    return math.sqrt(max(p2, 0.0)) if p2 >= -_rounding(d) else None


def _words(alpha: float, beta: float, d: float) -> dict[str, tuple[float, float, float] | None]:
    """Normalised Dubins segment lengths (t, p, q) of the six words, None where a word does not exist."""
    sa, sb, ca, cb, cab = math.sin(alpha), math.sin(beta), math.cos(alpha), math.cos(beta), math.cos(alpha - beta)
    out: dict[str, tuple[float, float, float] | None] = {}
    p = _root(2 + d * d - 2 * cab + 2 * d * (sa - sb), d)
    tmp = math.atan2(cb - ca, d + sa - sb)
    out["LSL"] = (_mod(-alpha + tmp), p, _mod(beta - tmp)) if p is not None else None
    p = _root(2 + d * d - 2 * cab + 2 * d * (sb - sa), d)
    tmp = math.atan2(ca - cb, d - sa + sb)
    out["RSR"] = (_mod(alpha - tmp), p, _mod(-beta + tmp)) if p is not None else None
    p = _root(-2 + d * d + 2 * cab + 2 * d * (sa + sb), d)
    if p is not None:
        tmp = math.atan2(-ca - cb, d + sa + sb) - math.atan2(-2.0, p)
        out["LSR"] = (_mod(-alpha + tmp), p, _mod(-beta + tmp))
    p = _root(-2 + d * d + 2 * cab - 2 * d * (sa + sb), d)
    if p is not None:
        tmp = math.atan2(ca + cb, d - sa - sb) - math.atan2(2.0, p)
        out["RSL"] = (_mod(alpha - tmp), p, _mod(beta - tmp))
    c = (6 - d * d + 2 * cab + 2 * d * (sa - sb)) / 8
    if abs(c) <= 1 + _rounding(d) / 8:
        p = _mod(_TWO_PI - math.acos(min(max(c, -1.0), 1.0)))
        t = _mod(alpha - math.atan2(ca - cb, d - sa + sb) + p / 2)
        out["RLR"] = (t, p, _mod(alpha - beta - t + p))
    c = (6 - d * d + 2 * cab + 2 * d * (sb - sa)) / 8
    if abs(c) <= 1 + _rounding(d) / 8:
        p = _mod(_TWO_PI - math.acos(min(max(c, -1.0), 1.0)))
        t = _mod(-alpha - math.atan2(ca - cb, d + sa - sb) + p / 2)
        out["LRL"] = (t, p, _mod(beta - alpha - t + p))
    return out


def _sample(start: np.ndarray, word: str, lengths: tuple[float, float, float], radius: float,
            step: float) -> np.ndarray:
    """Poses (N, 3) every ``step`` metres along a Dubins word from ``start`` (exact arcs)."""
    x, y, yaw = start
    out = [(x, y, yaw)]
    for kind, length in zip(word, lengths):
        metres = length * radius
        n = max(1, math.ceil(metres / step))
        ds = metres / n
        for _ in range(n):
            if kind == "S":
                x, y = x + ds * math.cos(yaw), y + ds * math.sin(yaw)
            else:
                sign = 1.0 if kind == "L" else -1.0
                turn = sign * ds / radius
                x += sign * radius * (math.sin(yaw + turn) - math.sin(yaw))
                y += sign * radius * (math.cos(yaw) - math.cos(yaw + turn))
                yaw += turn
            out.append((x, y, yaw))
    return np.array(out)


def dubins_paths(start: tuple[float, float, float], goal: tuple[float, float, float], radius: float,
                 step: float = 0.1) -> list[np.ndarray]:
    """Every Dubins path (forward, turning radius ``radius``) from ``start`` to ``goal``, shortest first.

    Args:
        start: ``(x, y, yaw)`` in metres and radians.
        goal: ``(x, y, yaw)`` in metres and radians.
        radius: turning radius in metres.
        step: spacing of the sampled poses in metres.

    Returns:
        Up to six paths, each ``[N, 3]`` poses ``(x, y, yaw)`` from ``start`` to ``goal`` (words whose sampled
        end misses the goal by 5 cm or 0.02 rad are dropped).

    Example:
        >>> paths = dubins_paths((0.0, 0.0, 0.0), (3.0, 3.0, math.pi / 2), radius=2.0)
        >>> len(paths), paths[0][-1].round(3).tolist()
        (6, [3.0, 3.0, 1.571])
    """
    s, g = np.asarray(start, np.float64), np.asarray(goal, np.float64)
    dx, dy = g[0] - s[0], g[1] - s[1]
    theta = math.atan2(dy, dx)
    words = _words(_mod(s[2] - theta), _mod(g[2] - theta), math.hypot(dx, dy) / radius)
    paths = []
    for word, lengths in words.items():
        if lengths is None:
            continue
        path = _sample(s, word, lengths, radius, step)
        end = path[-1]
        if math.hypot(end[0] - g[0], end[1] - g[1]) < 0.05 and abs(float(wrap_angle(end[2] - g[2]))) < 0.02:
            paths.append(path)
    return sorted(paths, key=len)


def _straight(start: np.ndarray, goal: np.ndarray, step: float) -> np.ndarray:
    """Poses from ``start`` to ``goal`` along a line with the goal's heading."""
    n = max(1, math.ceil(float(np.hypot(*(goal[:2] - start[:2]))) / step))
    xy = start[:2] + (goal[:2] - start[:2]) * np.linspace(0, 1, n + 1)[:, None]
    return np.column_stack([xy, np.full(n + 1, goal[2])])


@dataclass
class GeometricParker:
    """Plans a collision-free forward path into a slot and tracks it (pure pursuit + speed profile).

    Attributes:
        vehicle: the car (size, turning radius, limits).
        radius_factors: Dubins turning radii tried, as multiples of the car's minimum.
        entry_offsets: where on the slot axis the straight run may start, metres beyond the slot entrance.
        margin: clearance added around the footprint when checking a path (m).
        lookahead: pure-pursuit lookahead distance (m).
        cruise: top speed of the speed profile (m/s).
        step: spacing of the planned poses (m).
    """

    vehicle: VehicleParams = VehicleParams()
    radius_factors: tuple[float, ...] = (1.1, 1.3, 1.6)
    entry_offsets: tuple[float, ...] = (-1.5, -0.8, 0.0, 1.0, 2.0)
    margin: float = 0.1
    lookahead: float = 1.5
    cruise: float = 1.2
    step: float = 0.1

    def __post_init__(self) -> None:
        """No path to follow yet."""
        self.path: np.ndarray | None = None
        self._arc: np.ndarray | None = None
        self._index = 0

    def _clear(self, path: np.ndarray, obstacles: Obstacles) -> bool:
        """Whether the footprint at every second pose of ``path`` clears every box."""
        return not any(obstacles.hits(footprint(p, self.vehicle, self.margin)).any() for p in path[::2])

    def plan(self, pose: tuple[float, float, float], slot: dict[str, Any], obstacles: Obstacles) -> np.ndarray | None:
        """Shortest collision-free path (N, 3) of rear-axle poses from ``pose`` to head-in parked in ``slot``.

        Args:
            pose: the car's rear-axle ``(x, y, yaw)`` (metres, radians).
            slot: a map slot (``corners`` ``[4, 2]``).
            obstacles: the boxes the footprint must clear.

        Returns:
            ``[N, 3]`` poses ``(x, y, yaw)`` spaced ``step`` apart, or None when no candidate clears them.
        """
        centre, yaw = slot_pose(slot)
        x0, x1, _, _ = self.vehicle.extent
        heading = np.array([math.cos(yaw), math.sin(yaw)])
        goal = np.array([*(centre - heading * (x0 + x1) / 2), yaw])
        entrance = np.asarray(slot["corners"], np.float64)[:2].mean(axis=0)
        depth_in = float(np.dot(goal[:2] - entrance, heading))
        candidates = []
        for factor in self.radius_factors:
            for offset in self.entry_offsets:
                back = max(depth_in + offset, 0.5)
                entry = np.array([*(goal[:2] - heading * back), yaw])
                for path in dubins_paths(pose, tuple(entry), factor * self.vehicle.min_turn_radius, self.step)[:3]:
                    candidates.append(np.concatenate([path, _straight(entry, goal, self.step)[1:]]))
        for path in sorted(candidates, key=len):
            if self._clear(path, obstacles):
                return path
        return None

    def choose_slot(self, pose: tuple[float, float, float], world_map: dict[str, Any]
                    ) -> tuple[int, np.ndarray] | None:
        """The free slot with the shortest collision-free path from ``pose``, and that path.

        Args:
            pose: the car's rear-axle ``(x, y, yaw)`` (metres, radians).
            world_map: the scene's map (``slots``, ``obstacles``).

        Returns:
            ``(slot id, path [N, 3])``, or None when no free slot can be reached.
        """
        obstacles = Obstacles(world_map.get("obstacles", []))
        best = None
        for slot in free_slots(world_map):
            path = self.plan(pose, slot, obstacles)
            if path is not None and (best is None or len(path) < len(best[1])):
                best = (slot["id"], path)
        return best

    def follow(self, path: np.ndarray) -> None:
        """Start tracking ``path``.

        Args:
            path: ``[N, 3]`` poses ``(x, y, yaw)``, as ``plan`` gives them.
        """
        self.path = path
        seg = np.hypot(*np.diff(path[:, :2], axis=0).T)
        self._arc = np.concatenate([[0.0], np.cumsum(seg)])
        self._index = 0

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The normalised action for a privileged observation (world ``pose``, speed ``state[0]``).

        Args:
            obs: a ``ParkingEnv`` observation with ``pose`` ``[x, y, yaw]`` and ``state`` ``[v, ...]``.

        Returns:
            ``[2]`` float32 normalised ``(acceleration, steering)``.

        Raises:
            RuntimeError: no path to follow (``follow`` was not called).
        """
        if self.path is None or self._arc is None:
            raise RuntimeError("GeometricParker.act: no path to follow; call follow(path) first")
        x, y, yaw = (float(s) for s in obs["pose"])
        v = float(obs["state"][0])
        window = self.path[self._index:self._index + 40, :2]
        self._index += int(np.argmin(np.hypot(window[:, 0] - x, window[:, 1] - y)))
        remaining = self._arc[-1] - self._arc[self._index]
        end = self.path[-1]
        target_s = self._arc[self._index] + self.lookahead
        if target_s <= self._arc[-1]:
            tx, ty = self.path[np.searchsorted(self._arc, target_s), :2]
        else:
            extra = target_s - self._arc[-1]
            tx, ty = end[0] + extra * math.cos(end[2]), end[1] + extra * math.sin(end[2])
        alpha = math.atan2(ty - y, tx - x) - yaw
        ld = max(math.hypot(tx - x, ty - y), 1e-3)
        steer = math.atan2(2 * self.vehicle.wheelbase * math.sin(alpha), ld)
        along = (end[0] - x) * math.cos(end[2]) + (end[1] - y) * math.sin(end[2])
        if self._index >= len(self.path) - 1:
            remaining = max(along, 0.0)
        v_ref = min(self.cruise, math.sqrt(2 * 0.8 * max(remaining - 0.05, 0.0)))
        return to_action(2.0 * (v_ref - v), steer, self.vehicle)


class Parker(Protocol):
    """What ``run_episode`` drives with: ``GeometricParker``, ``HybridAStarParker`` or a planner like them."""

    def choose_slot(self, pose: tuple[float, float, float], world_map: dict[str, Any]
                    ) -> tuple[int, np.ndarray] | None:
        """``(slot id, path)`` to drive from ``pose``, or None when no free slot can be reached."""

    def follow(self, path: np.ndarray) -> None:
        """Start tracking ``path``, as ``choose_slot`` gave it."""

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The normalised ``[2]`` action for a privileged observation."""


def run_episode(env: gym.Env, seed: int, parker: Parker | None = None,
                on_step: Callable[[ParkingEnv], None] | None = None) -> dict[str, Any]:
    """Reset with ``seed``, pick the free slot with the best path, drive into it; returns the final info + steps.

    ``env`` is a privileged ``ParkingEnv``, bare or wrapped (``gym.make``: its ``TimeLimit`` ends a stuck episode).

    Args:
        env: the environment.
        seed: the reset seed (the start pose).
        parker: the planner (default: a ``GeometricParker`` for the env's vehicle).
        on_step: called with the unwrapped env after every step (to record or draw).

    Returns:
        The final step's info, plus ``steps`` and ``planned`` (False, with 0 steps, when no path cleared the
        obstacles).

    Raises:
        ValueError: ``env`` is not a privileged ``ParkingEnv``.
    """
    park = env.unwrapped
    if not isinstance(park, ParkingEnv) or not park.privileged:
        raise ValueError("run_episode needs a ParkingEnv made with privileged=True (the planner reads the world pose)")
    parker = parker or GeometricParker(park.vehicle)
    obs, info = env.reset(seed=seed)
    x, y, yaw = (float(v) for v in obs["pose"])
    chosen = parker.choose_slot((x, y, yaw), park.world_map)
    if chosen is None:
        return {**info, "steps": 0, "planned": False}
    obs, info = env.reset(seed=seed, options={"slot": chosen[0]})
    parker.follow(chosen[1])
    steps, done = 0, False
    while not done:
        obs, _, terminated, truncated, info = env.step(parker.act(obs))
        steps, done = steps + 1, terminated or truncated
        if on_step is not None:
            on_step(park)
    return {**info, "steps": steps, "planned": True}
