"""Planners that drive scenario episodes: the contract ``scenario_runs`` drives, the built-in ones and their registry.

A scenario planner is started once per episode and then asked for an action every step. A privileged planner is
handed the ``Episode`` itself (the filled map, the target slot, the actors and their behaviours' intent); a
non-privileged one gets ``None`` and only the observations. The built-ins:

- ``geometric``: ``GeometricParker``'s forward Dubins path into the scenario's slot, around the static obstacles and
  parked cars, tracked blind to the actors (the baseline as it was).
- ``hybrid``: Hybrid A* over Reeds-Shepp curves (forward and reverse) around the static obstacles and the actors'
  predicted footprints in time windows of the plan's clock; while tracking it yields: it stops when an actor is
  predicted (constant velocity, ``yield_horizon`` seconds) on the path just ahead, and plans again after waiting
  ``replan_after`` seconds. Its search budget is in nodes only, so a run repeats exactly on any machine.
- ``perception``: ``PerceptionParker``: no world pose or map, a slot detector on the rendered BEV, dead reckoning; it
  needs a trained detector (``detector=``).

``"module:Class"`` names a planner of one's own: a class with this module's ``ScenarioPlanner`` members, made with
no arguments.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from ..scenarios.shapes import Box, box_polygon, overlap_matrix
from ..scenarios.task import to_action
from ..vehicle import VehicleParams
from .geometric import GeometricParker
from .hybrid_astar import HybridAStarConfig, TimedPolygon
from .hybrid_parker import HybridAStarParker

if TYPE_CHECKING:
    from ..scenarios.episode import Episode

__all__ = ["ScenarioPlanner", "PathPlanner", "PerceptionPlanner", "PLANNERS", "make_planner", "check_planner",
           "actor_obstacles"]

PLANNERS = {"geometric": "privileged Dubins path (forward only), blind to the actors",
            "hybrid": "privileged Hybrid A* around the actors' predicted footprints, yielding while tracking",
            "perception": "BEV slot detector and dead reckoning (needs --detector)"}
"""The built-in planners, with what each is."""


@runtime_checkable
class ScenarioPlanner(Protocol):
    """What ``scenario_runs`` drives an episode with.

    Attributes:
        privileged: whether ``start`` and ``act`` get the ``Episode`` (the world state) rather than None.
        bev: whether its observations must hold the BEV (rendered only on steps after which ``wants_view``).
        status: why it gave up ("" while it has not), starting "no path found" when it found none.
    """

    privileged: bool
    bev: bool
    status: str

    def start(self, world: Episode | None, obs: dict[str, np.ndarray]) -> None:
        """Begin an episode from its first observation."""

    def act(self, world: Episode | None, obs: dict[str, np.ndarray] | None) -> np.ndarray | None:
        """The normalised ``[2]`` action (None: it gives up, with ``status`` saying why)."""

    @property
    def wants_view(self) -> bool:
        """Whether the observation after the action just taken should hold images."""


def actor_obstacles(world: Episode, horizon: float = 30.0, every: float = 0.5, slack: float = 1.0,
                    drift: float = 0.2) -> list[TimedPolygon]:
    """The actors' predicted footprints as obstacles in time windows of a plan starting now.

    An actor that stays put over ``horizon`` (behaviour intent, ``World.predict("plan")``) is one obstacle for all
    time; a moving one is its footprint every ``every`` seconds, each present from ``every`` before to ``every``
    after its time, widened by ``slack + drift * t`` seconds (the plan's clock is not the tracker's).

    Args:
        world: the episode (privileged).
        horizon: seconds predicted.
        every: seconds between the footprints of a moving actor.
        slack: seconds added to each window at the start.
        drift: seconds added per second ahead.

    Returns:
        The obstacles, plan time 0 being now.
    """
    prediction = world.world.predict(horizon, "plan")
    now = world.world.polygons()
    out: list[TimedPolygon] = []
    stride = max(1, round(every / world.vehicle.dt))
    for k in range(now.shape[0]):
        moved = float(np.abs(prediction.polygons[:, k] - now[k]).max()) if len(prediction.times) else 0.0
        if moved < 0.05:
            out.append(TimedPolygon(now[k]))
            continue
        times = prediction.times[stride - 1::stride] - world.world.t
        polys = prediction.polygons[stride - 1::stride, k]
        out.append(TimedPolygon(now[k], -math.inf, every + slack))
        for t, poly in zip(times, polys):
            wide = every + slack + drift * t
            out.append(TimedPolygon(poly, t - wide, t + wide))
    return out


def _grown(box: Box, margin: float) -> Box:
    """``box`` grown by ``margin`` on every side."""
    x0, x1, y0, y1 = box
    return (x0 - margin, x1 + margin, y0 - margin, y1 + margin)


@dataclass
class PathPlanner:
    """Plan once into the scenario's slot, then track; privileged (see the module docstring).

    Attributes:
        parker: plans and tracks (``GeometricParker`` or ``HybridAStarParker``).
        aware: plan around the actors' predicted footprints and yield to them (``HybridAStarParker`` only).
        yield_horizon: seconds of constant-velocity prediction the yield check looks ahead.
        yield_margin: metres around the ego's footprint in the yield check.
        replan_after: seconds of waiting before planning again.
    """

    parker: GeometricParker | HybridAStarParker
    aware: bool = False
    yield_horizon: float = 2.0
    yield_margin: float = 0.1
    replan_after: float = 5.0
    privileged: bool = field(default=True, init=False)
    bev: bool = field(default=False, init=False)
    status: str = field(default="", init=False)

    def __post_init__(self) -> None:
        """Check that an aware planner can take actors."""
        if self.aware and not isinstance(self.parker, HybridAStarParker):
            raise ValueError("PathPlanner(aware=True) needs a HybridAStarParker (it plans around the actors)")
        self._waited = 0.0

    @property
    def wants_view(self) -> bool:
        """Never: it reads the world state."""
        return False

    def _plan(self, world: Episode) -> bool:
        """Plan from the ego's pose into the target slot and follow the path; whether a path was found."""
        if self.aware:
            assert isinstance(self.parker, HybridAStarParker)
            self.parker.actors = actor_obstacles(world)
        path = self.parker.plan(world.state.pose, world.slot, world.obstacles)
        if path is not None:
            self.parker.follow(path)
        return path is not None

    def start(self, world: Episode | None, obs: dict[str, np.ndarray]) -> None:
        """Plan from the start pose; ``status`` says "no path found" when there is none.

        Args:
            world: the episode.
            obs: the first observation (unused: the world state is read).

        Raises:
            ValueError: ``world`` is None (this planner is privileged).
        """
        if world is None:
            raise ValueError("PathPlanner is privileged: it needs the Episode")
        self._waited, self.status = 0.0, ""
        if not self._plan(world):
            cause = getattr(self.parker, "result", None)   # a Hybrid A* search says why it ended
            self.status = "no path found" + (f" ({cause.status.value})" if cause is not None else "")

    def _blocked(self, world: Episode, speed: float) -> bool:
        """Whether an actor is predicted on the path the car will drive within ``yield_horizon``."""
        assert isinstance(self.parker, HybridAStarParker)
        ahead = self.parker.upcoming(abs(speed) * self.yield_horizon + 1.0)
        if not len(ahead) or not world.world.states:
            return False
        ego = box_polygon(ahead, _grown(world.vehicle.extent, self.yield_margin))
        soon = world.world.predict(self.yield_horizon, "constant_velocity").polygons.reshape(-1, 4, 2)
        actors = np.concatenate([world.world.polygons(), soon])
        return bool(overlap_matrix(ego, actors).any())

    def act(self, world: Episode | None, obs: dict[str, np.ndarray] | None) -> np.ndarray | None:
        """Track the path, or stand while an actor is about to cross it (aware).

        Args:
            world: the episode.
            obs: the privileged observation (``pose``, ``state``).

        Returns:
            The action, or None when there is no path.
        """
        if self.status or world is None or obs is None:
            return None
        v, wheels = float(obs["state"][0]), float(obs["state"][1])
        if self.aware and self._blocked(world, v):
            self._waited += world.vehicle.dt
            if self._waited >= self.replan_after:
                self._waited = 0.0
                self._plan(world)   # keeps the old path when no new one is found
            return to_action(-2.0 * v, wheels, world.vehicle)
        self._waited = 0.0
        return self.parker.act(obs)


@dataclass
class PerceptionPlanner:
    """``PerceptionParker`` as a scenario planner: not privileged, the BEV every ``every`` steps.

    Attributes:
        parker: the perception parker (its detector, BEV spec and cadence).
    """

    parker: Any
    privileged: bool = field(default=False, init=False)
    bev: bool = field(default=True, init=False)
    status: str = field(default="", init=False)

    @property
    def wants_view(self) -> bool:
        """Every ``parker.every`` steps."""
        return bool(self.parker.wants_view)

    def start(self, world: Episode | None, obs: dict[str, np.ndarray]) -> None:
        """Detect in the first BEV and plan.

        Args:
            world: None (not used).
            obs: the first observation, with its BEV.
        """
        self.status = ""
        self.parker.start(obs)

    def act(self, world: Episode | None, obs: dict[str, np.ndarray] | None) -> np.ndarray | None:
        """The parker's action, with a new BEV when ``obs`` has one.

        Args:
            world: None (not used).
            obs: the observation with a BEV after a step that wanted one, else None.

        Returns:
            The action, or None when it found no path.
        """
        action = self.parker.act(obs)
        if action is None:
            self.status = "no path found"
        return action


def _deterministic() -> HybridAStarConfig:
    """The search's defaults with a node budget only (a wall-clock budget would make runs machine-dependent)."""
    return dataclasses.replace(HybridAStarConfig(), max_seconds=math.inf)


def check_planner(spec: str, detector: str | Path | None = None) -> None:
    """Refuse a planner spec ``make_planner`` would refuse, without reading a detector.

    Args:
        spec: the planner's spec.
        detector: the slot detector checkpoint.

    Raises:
        ValueError: as ``make_planner``.
    """
    if spec == "perception":
        if detector is None:
            raise ValueError(_NO_DETECTOR)
        return
    make_planner(spec)


_NO_DETECTOR = "the perception planner needs a slot detector checkpoint (--detector PATH)"


def make_planner(spec: str, vehicle: VehicleParams = VehicleParams(), detector: Any = None,
                 bev_spec: Any = None) -> ScenarioPlanner:
    """A fresh planner from its name in ``PLANNERS`` or ``"module:Class"``.

    Args:
        spec: ``geometric``, ``hybrid``, ``perception`` or ``"module:Class"`` (made with no arguments).
        vehicle: the ego.
        detector: the slot detector (``perception`` only): a loaded one, or its checkpoint path.
        bev_spec: the scene rig's ``BEVSpec`` (``perception`` only).

    Returns:
        The planner.

    Raises:
        ValueError: an unknown name, a module or class that cannot be loaded or lacks the planner members, or
            ``perception`` without a detector.
    """
    makers: dict[str, Callable[[], ScenarioPlanner]] = {
        "geometric": lambda: PathPlanner(GeometricParker(vehicle)),
        "hybrid": lambda: PathPlanner(HybridAStarParker(vehicle, config=_deterministic()), aware=True)}
    if spec in makers:
        return makers[spec]()
    if spec == "perception":
        if detector is None or bev_spec is None:
            raise ValueError(_NO_DETECTOR)
        from ..recon.detectors import load_detector
        from .perception import PerceptionParker

        model = load_detector(Path(detector)) if isinstance(detector, (str, Path)) else detector
        return PerceptionPlanner(PerceptionParker(model, bev_spec, vehicle))
    module, _, name = spec.partition(":")
    if not (module and name):
        raise ValueError(f"unknown planner {spec!r}: choose {', '.join(PLANNERS)} or module:Class")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"planner {spec!r} cannot be loaded: {e}") from None
    if not isinstance(cls, type):
        raise ValueError(f"planner {spec!r} is not a class")
    planner = cls()
    if not isinstance(planner, ScenarioPlanner):
        raise ValueError(f"planner {spec!r} lacks a ScenarioPlanner member (privileged, bev, status, start, act, "
                         "wants_view)")
    return planner
