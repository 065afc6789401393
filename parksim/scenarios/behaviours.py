"""Actor behaviours: how another road user moves, one step at a time, given the ego and the other actors.

A behaviour is a ``Behaviour`` plug-in (``parksim.plugins``) named by the ``type`` of its parameters in a scenario
file (``parksim.scenarios.spec``), registered in ``BEHAVIOURS``: ``start`` fixes its parameters (ranges drawn
from the actor's own generator), ``step`` gives the pose and speed one ``dt`` later, ``plan`` the poses it
intends at future times (what a planner may predict). Every behaviour is deterministic given its generator, and
reads only the snapshot it is given, so ``parksim.scenarios.world.World`` can step all actors at once in any order.

Poses are ``(x, y, yaw)`` of the actor's origin, speeds signed along its heading (negative when reversing).
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..plugins import Plugin, instantiate
from .shapes import Box, box_polygon, overlap_matrix, polygon_distance
from .spec import BehaviourSpec, LaneSpec, PathSpec, PedestrianSpec, StaticSpec, draw

__all__ = ["ActorState", "Behaviour", "BEHAVIOURS", "make_behaviour", "Static", "FollowPath", "FollowLane",
           "Crossing", "LANE_LOOKAHEAD", "LANE_RESOLUTION"]

Pose = tuple[float, float, float]
LANE_LOOKAHEAD = 40.0
"""How far ahead along its lane an IDM actor looks for a leader (m); beyond it the road counts as free."""
LANE_RESOLUTION = 0.05
"""Spacing of the stations at which an IDM actor tests its footprint for contact ahead (m): the gap it sees is
short by less than this, never long."""
_SAME_TIME = 1e-9
"""Times closer than this (s) count as equal, so a trigger at a multiple of ``dt`` fires at that step whatever
the rounding of ``k * dt``."""


@dataclass(frozen=True)
class ActorState:
    """An actor (or the ego) at one instant.

    Attributes:
        pose: ``(x, y, yaw)`` of its origin (metres, radians).
        speed: signed speed along its heading (m/s).
        box: its footprint ``(x_min, x_max, y_min, y_max)`` about the pose.
    """

    pose: Pose
    speed: float
    box: Box

    def polygon(self) -> np.ndarray:
        """The footprint's world corners.

        Returns:
            ``[4, 2]`` float64, counter-clockwise.
        """
        return box_polygon(self.pose, self.box)


class Behaviour(Plugin):
    """How an actor moves (see the module docstring); ``Options`` is its parameters' model in ``spec``."""

    @abstractmethod
    def start(self, options: Any, initial: ActorState, rng: np.random.Generator) -> ActorState:
        """Fix the parameters for an episode (drawing ranges from ``rng``) and give the actor's first state.

        Args:
            options: the behaviour's parameters (an instance of ``Options``).
            initial: the actor at its start pose, standing.
            rng: the actor's generator.

        Returns:
            The state at time 0.
        """

    @abstractmethod
    def step(self, t: float, dt: float, me: ActorState, ego: ActorState,
             others: Sequence[ActorState]) -> tuple[Pose, float]:
        """Where the actor is ``dt`` after ``t``.

        Args:
            t: the time of the snapshot (s).
            dt: the step (s).
            me: the actor at ``t``.
            ego: the ego at ``t`` (its footprint box is the vehicle's extent about the rear axle).
            others: the other actors at ``t``.

        Returns:
            ``(pose, speed)`` at ``t + dt``.
        """

    @abstractmethod
    def plan(self, t: float, me: ActorState, times: np.ndarray) -> np.ndarray:
        """The poses it intends at ``times``, ignoring everyone else (a prediction for planners).

        Args:
            t: now (s).
            me: the actor now.
            times: ``[T]`` future times (s), increasing.

        Returns:
            ``[T, 3]`` poses.
        """


class _Polyline:
    """Straight segments from a start pose through points, each driven forward or in reverse.

    ``at(s)`` gives the pose at arc length ``s``: the start pose at 0, then on segment i facing along it (away from
    it when reversing), the last point's pose beyond the end.
    """

    def __init__(self, start: Pose, points: Sequence[Sequence[float]]) -> None:
        """Segments from ``start`` through ``points`` (``[x, y]``, or ``[x, y, -1]`` to reverse to it)."""
        xy = np.array([start[:2], *(p[:2] for p in points)], np.float64)
        self.start = start
        self.points = xy
        self.deltas = np.diff(xy, axis=0)
        self.reverse = np.array([len(p) == 3 and p[2] < 0 for p in points])
        self.lengths = np.hypot(self.deltas[:, 0], self.deltas[:, 1])
        self.stations = np.concatenate([[0.0], np.cumsum(self.lengths)])
        self.yaws = np.arctan2(self.deltas[:, 1], self.deltas[:, 0]) + np.where(self.reverse, math.pi, 0.0)

    @property
    def length(self) -> float:
        """The total arc length (m)."""
        return float(self.stations[-1])

    def at(self, s: np.ndarray | float) -> np.ndarray:
        """``[..., 3]`` poses at arc lengths ``s`` (clipped to the line)."""
        s = np.clip(np.asarray(s, np.float64), 0.0, self.length)
        i = np.clip(np.searchsorted(self.stations, s, side="right") - 1, 0, len(self.lengths) - 1)
        xy = self.points[i] + self.deltas[i] * ((s - self.stations[i]) / self.lengths[i])[..., None]
        yaw = np.where(s > 0, self.yaws[i], self.start[2])
        return np.concatenate([xy, yaw[..., None]], -1)

    def direction(self, s: float) -> float:
        """+1 forward, -1 reversing, on the segment at ``s``."""
        i = int(np.clip(np.searchsorted(self.stations, s, side="right") - 1, 0, len(self.lengths) - 1))
        return -1.0 if self.reverse[i] else 1.0


def _as_pose(row: np.ndarray) -> Pose:
    """A ``[3]`` array as a pose of Python floats."""
    return (float(row[0]), float(row[1]), float(row[2]))


class Static(Behaviour):
    """Stands at its start pose."""

    name = "static"
    help = "stand still"
    description = "Stays at its start pose for the whole episode."
    Options = StaticSpec

    def start(self, options: Any, initial: ActorState, rng: np.random.Generator) -> ActorState:
        """Nothing to draw."""
        return initial

    def step(self, t: float, dt: float, me: ActorState, ego: ActorState,
             others: Sequence[ActorState]) -> tuple[Pose, float]:
        """Where it stands."""
        return me.pose, 0.0

    def plan(self, t: float, me: ActorState, times: np.ndarray) -> np.ndarray:
        """Where it stands, at every time."""
        return np.tile(np.array(me.pose, np.float64), (len(times), 1))


@dataclass(frozen=True)
class _Trapezoid:
    """Rest to rest over ``length`` m: accelerate to ``peak``, cruise, decelerate (a triangle when too short)."""

    length: float
    peak: float
    accel: float
    decel: float

    @classmethod
    def fit(cls, length: float, cruise: float, accel: float, decel: float) -> _Trapezoid:
        """The profile that reaches ``cruise`` where the leg is long enough, else the highest speed it can."""
        peak = min(cruise, math.sqrt(2 * length * accel * decel / (accel + decel)))
        return cls(length, peak, accel, decel)

    @property
    def duration(self) -> float:
        """Seconds from rest to rest."""
        return self.peak / self.accel + self.cruise_length / self.peak + self.peak / self.decel

    @property
    def cruise_length(self) -> float:
        """Metres at the peak speed (0 for a triangle, up to rounding)."""
        return max(self.length - self.peak ** 2 / (2 * self.accel) - self.peak ** 2 / (2 * self.decel), 0.0)

    def at(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(distance, speed)`` at times ``tau`` since the leg began (clipped to the leg)."""
        t1 = self.peak / self.accel
        t2 = t1 + self.cruise_length / self.peak
        tau = np.clip(tau, 0.0, self.duration)
        left = np.maximum(self.duration - tau, 0.0)
        s = np.where(tau < t1, 0.5 * self.accel * tau ** 2,
                     np.where(tau < t2, self.peak * (tau - 0.5 * t1), self.length - 0.5 * self.decel * left ** 2))
        v = np.where(tau < t1, self.accel * tau, np.where(tau < t2, self.peak, self.decel * left))
        return np.clip(s, 0.0, self.length), v


class FollowPath(Behaviour):
    """Along waypoints with a trapezoidal speed profile per leg, a leg ending at each change of direction."""

    name = "path"
    help = "drive through waypoints with a speed profile"
    description = ("Drives straight segments from its start pose through its waypoints (reversing where marked), "
                   "stopping at each change of direction, from start_time on; it ignores everyone else.")
    Options = PathSpec

    def start(self, options: Any, initial: ActorState, rng: np.random.Generator) -> ActorState:
        """Draw the cruise speed and start time; cut the line into legs of one direction."""
        self.line = _Polyline(initial.pose, options.waypoints)
        cruise, self.t0 = draw(options.speed, rng), draw(options.start_time, rng)
        turns = np.flatnonzero(self.line.reverse[1:] != self.line.reverse[:-1]) + 1
        bounds = self.line.stations[np.concatenate([[0], turns, [len(self.line.lengths)]])]
        self.legs = [_Trapezoid.fit(float(b - a), cruise, options.accel, options.decel)
                     for a, b in zip(bounds[:-1], bounds[1:])]
        self.leg_start_s = bounds[:-1]
        self.leg_start_t = np.concatenate([[0.0], np.cumsum([leg.duration for leg in self.legs])])
        return initial

    def _at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``([T, 3] poses, [T] signed speeds)`` at absolute times."""
        tau = np.asarray(t, np.float64) - self.t0
        j = np.clip(np.searchsorted(self.leg_start_t, tau, side="right") - 1, 0, len(self.legs) - 1)
        s, v = np.zeros_like(tau), np.zeros_like(tau)
        for k, leg in enumerate(self.legs):
            sk, vk = leg.at(tau - self.leg_start_t[k])
            s, v = np.where(j == k, self.leg_start_s[k] + sk, s), np.where(j == k, vk, v)
        s = np.where(tau > 0, s, 0.0)
        sign = np.array([self.line.direction(float(x)) for x in np.atleast_1d(s)]).reshape(s.shape)
        return self.line.at(s), np.where(tau > 0, sign * v, 0.0)

    def step(self, t: float, dt: float, me: ActorState, ego: ActorState,
             others: Sequence[ActorState]) -> tuple[Pose, float]:
        """The profile's pose and speed at ``t + dt``."""
        poses, speeds = self._at(np.array([t + dt]))
        return _as_pose(poses[0]), float(speeds[0])

    def plan(self, t: float, me: ActorState, times: np.ndarray) -> np.ndarray:
        """The profile's poses at ``times``."""
        return self._at(times)[0]


class FollowLane(Behaviour):
    """Forward along its lane with IDM gap keeping to the first footprint ahead, stopping at the lane's end."""

    name = "lane"
    help = "follow a lane keeping the gap (IDM)"
    description = ("Drives forward along its waypoints; the Intelligent Driver Model keeps its gap to the ego or "
                   "another actor whose footprint lies ahead on the lane, and it stops at the lane's end.")
    Options = LaneSpec

    def start(self, options: Any, initial: ActorState, rng: np.random.Generator) -> ActorState:
        """Draw the desired speed; start at the lane's beginning at ``initial_speed``."""
        self.line = _Polyline(initial.pose, options.waypoints)
        self.o: LaneSpec = options
        self.v0 = draw(options.speed, rng)
        self.s, self.v = 0.0, float(options.initial_speed)
        return replace(initial, speed=self.v)

    def _idm(self, gap: float, v_lead: float) -> float:
        """IDM acceleration behind a leader ``gap`` m ahead moving at ``v_lead`` along the lane."""
        o, v = self.o, self.v
        wanted = o.min_gap + max(0.0, v * o.headway + v * (v - v_lead) / (2 * math.sqrt(o.accel * o.decel)))
        return o.accel * (1 - (v / self.v0) ** o.exponent - (wanted / max(gap, 1e-9)) ** 2)

    def _free_run(self, box: Box, others: Sequence[ActorState]) -> tuple[float, float | None]:
        """How far it can move before its footprint touches another, and that one's speed along the lane.

        Returns:
            ``(distance, speed)``, or ``(distance, None)`` when nothing lies within ``LANE_LOOKAHEAD`` on the rest
            of the lane.
        """
        reach = min(LANE_LOOKAHEAD, self.line.length - self.s)
        if not others or reach <= 0:
            return reach, None
        ahead = np.minimum(LANE_RESOLUTION * np.arange(1, math.ceil(reach / LANE_RESOLUTION) + 1), reach)
        poses = self.line.at(self.s + ahead)
        polygons = np.stack([o.polygon() for o in others])
        hits = overlap_matrix(box_polygon(poses, box), polygons)                          # [stations, others]
        rows = np.flatnonzero(hits.any(1))
        if not len(rows):
            return reach, None
        k = int(rows[0])
        lane_yaw = poses[k, 2]
        along = [others[j].speed * math.cos(others[j].pose[2] - lane_yaw) for j in np.flatnonzero(hits[k]).tolist()]
        return (float(ahead[k - 1]) if k else 0.0), min(along)

    def step(self, t: float, dt: float, me: ActorState, ego: ActorState,
             others: Sequence[ActorState]) -> tuple[Pose, float]:
        """IDM behind the leader and behind the lane's end; never past the first contact or the end."""
        run, v_lead = self._free_run(me.box, [ego, *others])
        to_end = self.line.length - self.s
        accel = self._idm(to_end + self.o.min_gap, 0.0)
        if v_lead is not None:
            accel = min(accel, self._idm(run, v_lead))
        v_next = self.v + accel * dt
        ds = 0.5 * (self.v + v_next) * dt if v_next >= 0 else self.v ** 2 / (2 * -accel)
        limit = min(run, to_end)
        if ds >= limit:      # the leader or the end is reached within the step: stop there
            ds, v_next = limit, 0.0
        self.s, self.v = self.s + ds, max(v_next, 0.0)
        return _as_pose(self.line.at(self.s)), self.v

    def plan(self, t: float, me: ActorState, times: np.ndarray) -> np.ndarray:
        """On along the lane at today's speed, stopping at its end."""
        return self.line.at(self.s + self.v * (np.asarray(times, np.float64) - t))


class Crossing(Behaviour):
    """A pedestrian walking straight to ``to`` once triggered by the clock or by the ego coming near."""

    name = "pedestrian"
    help = "cross when triggered by time or the ego's approach"
    description = ("Stands until the trigger time or until the ego's footprint comes within the trigger distance "
                   "of its own, then walks straight to its goal at its speed and stands there.")
    Options = PedestrianSpec

    def start(self, options: Any, initial: ActorState, rng: np.random.Generator) -> ActorState:
        """Draw the speed, then the trigger time and distance (those given)."""
        self.line = _Polyline(initial.pose, [options.to])
        self.speed = draw(options.speed, rng)
        trigger = options.trigger
        self.t_trigger = None if trigger.time is None else draw(trigger.time, rng)
        self.d_trigger = None if trigger.distance is None else draw(trigger.distance, rng)
        self.since: float | None = None
        return initial

    def _walked(self, since: float, t: np.ndarray) -> np.ndarray:
        """Metres walked at times ``t`` after setting off at ``since``."""
        return np.clip(self.speed * (np.asarray(t, np.float64) - since), 0.0, self.line.length)

    def step(self, t: float, dt: float, me: ActorState, ego: ActorState,
             others: Sequence[ActorState]) -> tuple[Pose, float]:
        """Fire the trigger at ``t`` if due, then walk."""
        if self.since is None and (
                (self.t_trigger is not None and t >= self.t_trigger - _SAME_TIME)
                or (self.d_trigger is not None and float(polygon_distance(ego.polygon(), me.polygon()))
                    <= self.d_trigger)):
            self.since = t
        if self.since is None:
            return me.pose, 0.0
        s = float(self._walked(self.since, np.array(t + dt)))
        return _as_pose(self.line.at(s)), self.speed if s < self.line.length else 0.0

    def plan(self, t: float, me: ActorState, times: np.ndarray) -> np.ndarray:
        """Walking from when it set off, or if not yet, from the trigger time or from now when the ego may trigger it.

        Setting off now is the cautious guess: it may step out as soon as the ego comes near.

        Returns:
            ``[T, 3]`` poses.
        """
        if self.since is not None:
            since = self.since
        elif self.d_trigger is not None or self.t_trigger is None:
            since = t
        else:
            since = max(t, self.t_trigger)
        return self.line.at(self._walked(since, times))


BEHAVIOURS: dict[str, str] = {"static": "behaviours:Static", "path": "behaviours:FollowPath",
                              "lane": "behaviours:FollowLane", "pedestrian": "behaviours:Crossing"}
"""Behaviour name (a scenario's ``behaviour.type``) -> ``module:Class`` under ``parksim.scenarios``."""


def make_behaviour(options: BehaviourSpec, initial: ActorState,
                   rng: np.random.Generator) -> tuple[Behaviour, ActorState]:
    """The behaviour named by ``options.type``, started for an episode.

    Args:
        options: the behaviour's parameters from the scenario.
        initial: the actor at its start pose, standing.
        rng: the actor's generator.

    Returns:
        ``(behaviour, state at time 0)``.

    Raises:
        ValueError: an unknown behaviour name.
    """
    behaviour: Behaviour = instantiate(BEHAVIOURS, options.type, "parksim.scenarios", Behaviour, "behaviour")
    return behaviour, behaviour.start(options, initial, rng)
