"""The scorecard of one parking episode, computed from its trajectory log alone, and its summary over a set.

The log is what happened (the ego's poses, speeds and controls, the actors' footprints, the static obstacles and
the target slot); the card is a pure function of it, in float64 numpy without randomness, so the same log always
gives the same numbers. Collisions are footprint polygons overlapping (separating axes, touching counts), as the
env judges its own; clearance is the polygon distance. docs/scenarios.md defines every field.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..vehicle import VehicleParams, car_centre
from .shapes import box_polygon, nearest_distance, overlap_matrix, overlaps, polygon_distance
from .task import heading_error, is_parked, slot_pose

__all__ = ["EpisodeLog", "Scorecard", "score_episode", "aggregate", "MOVING_SPEED"]

MOVING_SPEED = 0.01
"""Speeds of at most this (m/s) are standing still when direction changes are counted."""


@dataclass(frozen=True)
class EpisodeLog:
    """What happened in one episode, step by step at times ``t``.

    Attributes:
        t: ``[T]`` times (s), increasing.
        poses: ``[T, 3]`` the ego's rear-axle ``(x, y, yaw)``.
        speeds: ``[T]`` the ego's signed speed (m/s).
        controls: ``[T - 1, 2]`` ``(acceleration m/s^2, steering rad)`` applied from step k to k + 1.
        actors: ``[T, N, 4, 2]`` the actors' footprints (N may be 0).
        obstacles: ``[M, 4, 2]`` the static obstacles' footprints (``Obstacles.corners()``, occupied slots' cars
            included).
        slot: ``[4, 2]`` the target slot's corners (the map's ``corners``).
    """

    t: np.ndarray
    poses: np.ndarray
    speeds: np.ndarray
    controls: np.ndarray
    actors: np.ndarray
    obstacles: np.ndarray
    slot: np.ndarray

    def __post_init__(self) -> None:
        """Arrays as float64, shapes checked against each other."""
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, np.asarray(getattr(self, f.name), np.float64))
        n = len(self.t)
        expected = {"t": (n,), "poses": (n, 3), "speeds": (n,), "controls": (max(n - 1, 0), 2),
                    "actors": (n, self.actors.shape[1] if self.actors.ndim == 4 else -1, 4, 2),
                    "obstacles": (self.obstacles.shape[0] if self.obstacles.ndim == 3 else -1, 4, 2),
                    "slot": (4, 2)}
        if n < 1:
            raise ValueError("EpisodeLog: t must hold at least one time")
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"EpisodeLog.{name} must have shape {shape} for {n} steps, got "
                                 f"{getattr(self, name).shape}")
        if not all(np.isfinite(getattr(self, f.name)).all() for f in dataclasses.fields(self)):
            raise ValueError("EpisodeLog holds a NaN or an infinity")
        if (np.diff(self.t) <= 0).any():
            raise ValueError("EpisodeLog.t must increase")


@dataclass(frozen=True)
class Scorecard:
    """One episode's grades (JSON-ready through ``to_dict``).

    Attributes:
        success: parked at the end (position, heading, stopped) and no collision during the episode.
        final_distance: body centre to slot centre at the end (m).
        final_heading_error: heading to the slot axis, either way, at the end (degrees).
        static_collisions: contacts begun with static obstacles (an obstacle touched again after letting go
            counts again).
        first_static_collision: time of the first static contact (s), or None.
        actor_collisions: contacts begun with actors, counted as for obstacles.
        first_actor_collision: time of the first actor contact (s), or None.
        min_clearance_static: the smallest footprint distance to a static obstacle (m; 0 in contact), or None
            without obstacles.
        min_clearance_actors: the same to the actors, or None without actors.
        time: episode length (s).
        path_length: distance travelled by the rear-axle centre (m).
        direction_changes: switches between driving forward and reversing (stops in between do not count).
        peak_jerk: the largest change rate of the commanded acceleration (m/s^3).
        steps: logged steps after the first.
    """

    success: bool
    final_distance: float
    final_heading_error: float
    static_collisions: int
    first_static_collision: float | None
    actor_collisions: int
    first_actor_collision: float | None
    min_clearance_static: float | None
    min_clearance_actors: float | None
    time: float
    path_length: float
    direction_changes: int
    peak_jerk: float
    steps: int

    @property
    def collided(self) -> bool:
        """Whether the ego touched anything."""
        return bool(self.static_collisions or self.actor_collisions)

    def to_dict(self) -> dict[str, Any]:
        """The card as plain JSON types.

        Returns:
            Field name -> bool, int, float or None.
        """
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Scorecard:
        """A card from ``to_dict``'s output (a ``results.json`` entry).

        Args:
            data: field name -> value.

        Returns:
            The card.
        """
        return cls(**{f.name: data[f.name] for f in dataclasses.fields(cls)})


def _onsets(contact: np.ndarray, t: np.ndarray) -> tuple[int, float | None]:
    """(contacts begun, summed over objects; time of the first contact or None) from ``[T, M]`` overlaps."""
    begun = contact & ~np.concatenate([np.zeros((1, contact.shape[1]), bool), contact[:-1]])
    steps = np.flatnonzero(contact.any(1))
    return int(begun.sum()), (float(t[steps[0]]) if len(steps) else None)


def _direction_changes(speeds: np.ndarray) -> int:
    """Sign changes of the speed, skipping the steps standing still."""
    signs = np.sign(speeds[np.abs(speeds) > MOVING_SPEED])
    return int((signs[1:] != signs[:-1]).sum())


def score_episode(log: EpisodeLog, vehicle: VehicleParams = VehicleParams(), position_tolerance: float = 0.35,
                  heading_tolerance: float = math.degrees(0.15)) -> Scorecard:
    """Grade one episode from its log.

    Args:
        log: the episode.
        vehicle: the ego's body (its footprint box is ``vehicle.extent``).
        position_tolerance: parked needs the body centre this close to the slot centre (m).
        heading_tolerance: and the heading this close to the slot axis, either way (degrees).

    Returns:
        The scorecard.
    """
    ego = box_polygon(log.poses, vehicle.extent)                                        # [T, 4, 2]
    static_hit = overlap_matrix(ego, log.obstacles)                                      # [T, M]
    actor_hit = overlaps(ego[:, None], log.actors)                                       # [T, N]
    static_count, static_first = _onsets(static_hit, log.t)
    actor_count, actor_first = _onsets(actor_hit, log.t)
    centre, slot_yaw = slot_pose({"corners": log.slot})
    distance = float(np.linalg.norm(car_centre(log.poses[-1], vehicle) - centre))
    heading_rad = heading_error(float(log.poses[-1, 2]), slot_yaw)
    heading = math.degrees(heading_rad)
    parked = is_parked(distance, heading_rad, float(log.speeds[-1]), position_tolerance,
                       math.radians(heading_tolerance))
    mid_times = 0.5 * (log.t[:-1] + log.t[1:])             # each control acts from t[k] to t[k + 1]
    jerk = np.abs(np.diff(log.controls[:, 0])) / np.diff(mid_times)
    return Scorecard(
        success=bool(parked and not static_count and not actor_count),
        final_distance=distance, final_heading_error=heading,
        static_collisions=static_count, first_static_collision=static_first,
        actor_collisions=actor_count, first_actor_collision=actor_first,
        min_clearance_static=nearest_distance(ego, log.obstacles) if len(log.obstacles) else None,
        min_clearance_actors=float(polygon_distance(ego[:, None], log.actors).min()) if log.actors.size else None,
        time=float(log.t[-1] - log.t[0]),
        path_length=float(np.hypot(*np.diff(log.poses[:, :2], axis=0).T).sum()),
        direction_changes=_direction_changes(log.speeds),
        peak_jerk=float(jerk.max()) if jerk.size else 0.0,
        steps=len(log.t) - 1)


_SUMMARISED = ("final_distance", "final_heading_error", "static_collisions", "actor_collisions",
               "min_clearance_static", "min_clearance_actors", "time", "path_length", "direction_changes",
               "peak_jerk")
"""The numeric fields ``aggregate`` summarises."""
_PERCENTILES = (50, 90)


def aggregate(cards: Sequence[Scorecard]) -> dict[str, Any]:
    """A set's summary: rates, and per numeric field its mean and percentiles over the episodes that have it.

    Args:
        cards: the episodes' scorecards.

    Returns:
        ``{"episodes", "success_rate", "collision_rate", FIELD: {"n", "mean", "p50", "p90", "max"}}`` in plain
        JSON types (a field no episode has, such as actor clearance without actors, is ``{"n": 0}``).

    Raises:
        ValueError: no cards.
    """
    if not cards:
        raise ValueError("aggregate needs at least one scorecard")
    out: dict[str, Any] = {"episodes": len(cards),
                           "success_rate": sum(c.success for c in cards) / len(cards),
                           "collision_rate": sum(c.collided for c in cards) / len(cards)}
    for name in _SUMMARISED:
        values = np.array([v for c in cards if (v := getattr(c, name)) is not None], np.float64)
        out[name] = {"n": len(values)} if not len(values) else {
            "n": len(values), "mean": float(values.mean()),
            **{f"p{p}": float(np.percentile(values, p)) for p in _PERCENTILES}, "max": float(values.max())}
    return out
