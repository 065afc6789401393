"""The actors of a scenario stepped together at a fixed ``dt``, and their footprints predicted for planners.

Each step every behaviour reads the same snapshot (the ego and all actors at ``t``) and the new states replace the
old ones together, so the order of the actors changes nothing. Every random draw comes from the scenario's seed
through independent streams (``generator``), an actor's keyed by its name: adding, removing or reordering actors
leaves the others' draws as they were.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..vehicle import VehicleParams
from .behaviours import ActorState, Behaviour, make_behaviour
from .shapes import Box, box_polygon
from .spec import ActorSpec, Scenario

__all__ = ["World", "Prediction", "generator", "ego_actor"]


def generator(seed: int, *key: int) -> np.random.Generator:
    """One of a scenario's independent random streams.

    Args:
        seed: the scenario's seed.
        key: the stream: ``(0,)`` draws the ego's start, ``(1, crc32(name))`` an actor's behaviour.

    Returns:
        A generator that depends only on ``seed`` and ``key``.
    """
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


def ego_actor(pose: Sequence[float], speed: float, vehicle: VehicleParams = VehicleParams()) -> ActorState:
    """The ego as the actors see it: its rear-axle pose, speed and body.

    Args:
        pose: rear-axle ``(x, y, yaw)``.
        speed: signed speed (m/s).
        vehicle: its size (the footprint box is ``vehicle.extent``).

    Returns:
        The ego's state.
    """
    x, y, yaw = (float(v) for v in pose)
    return ActorState((x, y, yaw), float(speed), vehicle.extent)


@dataclass(frozen=True)
class Prediction:
    """Where the actors are expected over a horizon.

    Attributes:
        times: ``[K]`` future times (s).
        poses: ``[K, N, 3]`` actor poses.
        polygons: ``[K, N, 4, 2]`` actor footprints (world metres).
    """

    times: np.ndarray
    poses: np.ndarray
    polygons: np.ndarray


class World:
    """The actors of one episode (see the module docstring)."""

    def __init__(self, actors: Sequence[ActorSpec], seed: int = 0, dt: float = 0.1,
                 asset_boxes: Mapping[str, Box] | None = None) -> None:
        """Place the actors at their start poses (``reset``).

        Args:
            actors: the scenario's actors.
            seed: the scenario's seed.
            dt: seconds per step (the env's 0.1).
            asset_boxes: footprints of assets read from their folders (``ActorSpec.resolved_box``).

        Raises:
            ValueError: ``dt`` is not positive.
            ScenarioError: an actor whose asset has no known footprint.
        """
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt!r}")
        self.specs = tuple(actors)
        self.names = tuple(a.name for a in self.specs)
        self.boxes = tuple(a.resolved_box(asset_boxes) for a in self.specs)
        self.seed, self.dt = seed, dt
        self.reset()

    @classmethod
    def from_scenario(cls, scenario: Scenario, dt: float = 0.1,
                      asset_boxes: Mapping[str, Box] | None = None) -> World:
        """The world of a scenario's actors and seed.

        Args:
            scenario: the scenario.
            dt: seconds per step.
            asset_boxes: footprints of assets read from their folders.

        Returns:
            The world at time 0.
        """
        return cls(scenario.actors, scenario.seed, dt, asset_boxes)

    def reset(self) -> None:
        """Back to time 0: every actor at its start pose, its behaviour's draws made afresh from the seed."""
        self.steps = 0
        started = [make_behaviour(a.behaviour, ActorState(a.pose, 0.0, box),
                                  generator(self.seed, 1, zlib.crc32(a.name.encode())))
                   for a, box in zip(self.specs, self.boxes)]
        self.behaviours: list[Behaviour] = [b for b, _ in started]
        self.states: tuple[ActorState, ...] = tuple(s for _, s in started)

    @property
    def t(self) -> float:
        """The time of ``states`` (s): steps times ``dt``, never a running sum."""
        return self.steps * self.dt

    def step(self, ego: ActorState) -> tuple[ActorState, ...]:
        """Move every actor by ``dt`` from the same snapshot.

        Args:
            ego: the ego at ``t`` (``ego_actor``).

        Returns:
            The actors' states at ``t + dt`` (also in ``states``).
        """
        now, t = self.states, self.t
        moved = []
        for i, (behaviour, me) in enumerate(zip(self.behaviours, now)):
            pose, speed = behaviour.step(t, self.dt, me, ego, now[:i] + now[i + 1:])
            moved.append(ActorState(pose, speed, me.box))
        self.states, self.steps = tuple(moved), self.steps + 1
        return self.states

    def polygons(self) -> np.ndarray:
        """The actors' footprints now.

        Returns:
            ``[N, 4, 2]`` world corners.
        """
        return np.stack([s.polygon() for s in self.states]) if self.states else np.zeros((0, 4, 2))

    def rollout(self, ego: Sequence[ActorState]) -> np.ndarray:
        """From time 0, the actors' footprints beside a given ego trajectory (one state per step).

        Args:
            ego: the ego at times ``0, dt, ..., (T - 1) dt``.

        Returns:
            ``[T, N, 4, 2]``: at step k, where the actors are at ``k dt``.
        """
        self.reset()
        frames = [self.polygons()]
        for state in ego[:-1]:
            self.step(state)
            frames.append(self.polygons())
        return np.stack(frames)

    def predict(self, horizon: float, mode: Literal["plan", "constant_velocity"] = "plan") -> Prediction:
        """The actors' footprints at every step of the next ``horizon`` seconds, without stepping the world.

        ``plan``: what each behaviour intends, ignoring the others (``Behaviour.plan``); ``constant_velocity``:
        each actor keeps its heading and speed (what a planner without the behaviours would assume).

        Args:
            horizon: seconds ahead (``round(horizon / dt)`` steps).
            mode: how to predict.

        Returns:
            The prediction at ``t + dt, ..., t + K dt``.

        Raises:
            ValueError: an unknown ``mode`` or a negative ``horizon``.
        """
        if not horizon >= 0:
            raise ValueError(f"horizon must be >= 0 seconds, got {horizon!r}")
        times = (self.steps + np.arange(1, round(horizon / self.dt) + 1)) * self.dt
        if mode == "plan":
            per_actor = [b.plan(self.t, s, times) for b, s in zip(self.behaviours, self.states)]
        elif mode == "constant_velocity":
            per_actor = []
            for s in self.states:
                x, y, yaw = s.pose
                run = s.speed * (times - self.t)
                per_actor.append(np.stack([x + run * np.cos(yaw), y + run * np.sin(yaw), np.full_like(times, yaw)],
                                          -1))
        else:
            raise ValueError(f"mode must be 'plan' or 'constant_velocity', got {mode!r}")
        poses = np.stack(per_actor, 1) if per_actor else np.zeros((len(times), 0, 3))
        polygons = (np.stack([box_polygon(poses[:, i], box) for i, box in enumerate(self.boxes)], 1)
                    if per_actor else np.zeros((len(times), 0, 4, 2)))
        return Prediction(times, poses, polygons)
