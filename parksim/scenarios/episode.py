"""One scenario run in closed loop, without gym: the core that ``ParkingEnv(scenario=)``, an episode API and a
batch runner share.

``Episode(scenario, world_map, renderer)`` makes the scenario concrete on the scene's map (``resolve.prepare``),
drives the ego with the env's vehicle model and rules (``task``), steps the other road users with the ``World``
after each ego step (they react to the ego as it was at the step's start), ends the episode when the car is parked,
when its footprint touches a static obstacle or an actor, or at the scenario's time limit, and logs every step for
the scorecard (``log``, ``result``). With a renderer (a ``LocalSim``) the observation holds its views, the actors
and the parked cars of ``occupy`` drawn into them as Gaussian actors at their poses; without one it holds the
state only. Everything random comes from the scenario's seed, so a given seed gives the same episode every time.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..frames import Frame
from ..vehicle import Obstacles, VehicleParams, VehicleState
from .resolve import Setup, prepare
from .score import EpisodeLog, Scorecard, score_episode
from .shapes import Box, box_polygon, overlaps
from .spec import BUILTIN_BOXES, Scenario, ScenarioError
from .task import drive, observation, parking_errors, progress_cost, reward, step_info
from .world import World, ego_actor

if TYPE_CHECKING:
    from ..actor_asset import ActorAsset
    from ..sim import LocalSim

__all__ = ["Episode", "load_actor_asset"]


@functools.lru_cache(maxsize=len(BUILTIN_BOXES))
def _builtin_asset(kind: str) -> ActorAsset:
    """A built-in asset baked once per process (``parksim.actor_sources.bake``, seed 0: always the same)."""
    from ..actor_sources import bake

    return bake(kind)


def load_actor_asset(asset: str, root: str | Path | None = None) -> ActorAsset:
    """The Gaussians an actor's ``asset`` names: a built-in name, a 3DGS PLY (``.ply``) or an asset folder.

    Args:
        asset: ``ActorSpec.asset``.
        root: the folder relative paths are read from (None: the working directory).

    Returns:
        The asset (built-ins are baked once per process and shared: do not change them).

    Raises:
        parksim.actor_asset.AssetError: a folder that is not an asset.
        parksim.gaussians.PLYFormatError: an unreadable PLY.
    """
    if asset in BUILTIN_BOXES:
        return _builtin_asset(asset)
    path = Path(root or ".") / asset
    if path.suffix.lower() == ".ply":
        from ..actor_sources import asset_from_ply

        return asset_from_ply(path)
    from ..actor_asset import load_asset

    return load_asset(path)


def _floor_box(asset: ActorAsset) -> Box:
    """The asset box's floor rectangle ``(x_min, x_max, y_min, y_max)``."""
    (x0, y0, _), (x1, y1, _) = asset.box
    return (x0, x1, y0, y1)


class Episode:
    """A scenario in closed loop (see the module docstring).

    Attributes:
        scenario: the scenario as given.
        setup: the scenario made concrete at the last ``begin`` (start, target slot, filled map, parked cars).
        world: the actors at the last ``begin``, stepped with the ego.
        state: the ego now.
        obstacles: the filled map's static obstacles (parked cars of ``occupy`` included).
        done: whether the episode has ended (parked, touched something or out of time).
    """

    def __init__(self, scenario: Scenario, world_map: Mapping[str, Any], renderer: LocalSim | None = None, *,
                 cameras: Sequence[str] | None = None, bev: bool = False, scale: float = 0.25,
                 privileged: bool = True, vehicle: VehicleParams = VehicleParams(),
                 asset_root: str | Path | None = None) -> None:
        """Check the scenario against the map and read the actors' assets.

        Args:
            scenario: the scenario.
            world_map: the scene's ``map.json`` content (not changed).
            renderer: renders the views with the actors (None: state-only observations).
            cameras: the views in the observation (None: all of the renderer's; ``[]`` for none).
            bev: add the BEV to the observation.
            scale: image size relative to the rig's cameras.
            privileged: add the world pose to the observation and the info.
            vehicle: the ego (its ``dt`` is the step).
            asset_root: the folder the actors' relative asset paths are read from (None: the working directory).

        Raises:
            ScenarioError: an actor's asset that cannot be read, or a scenario that does not fit the map
                (``prepare``).
        """
        self.scenario, self.vehicle, self.privileged = scenario, vehicle, privileged
        self._map = dict(world_map)
        self.renderer = renderer
        self.cameras = [] if renderer is None else list(renderer.cameras if cameras is None else cameras)
        self.bev, self.scale = bool(bev and renderer is not None), scale
        needed = [a for a in scenario.actors if self.renders or (a.box is None and a.asset not in BUILTIN_BOXES)]
        self._assets: dict[str, ActorAsset] = {}
        for actor in needed:
            if actor.asset not in self._assets:
                try:
                    self._assets[actor.asset] = load_actor_asset(actor.asset, asset_root)
                except (OSError, ValueError) as e:   # AssetError and PLYFormatError are ValueErrors
                    raise ScenarioError(f"scenario {scenario.name!r}: actor {actor.name!r}: "
                                        f"{' '.join(str(e).split())}") from None
        self._boxes = {name: _floor_box(a) for name, a in self._assets.items() if name not in BUILTIN_BOXES}
        self.begin()

    @property
    def renders(self) -> bool:
        """Whether observations hold images (a renderer, and a camera or the BEV asked for)."""
        return self.renderer is not None and bool(self.cameras or self.bev)

    @property
    def t(self) -> float:
        """Seconds since the start (steps times ``dt``)."""
        return self._steps * self.vehicle.dt

    @property
    def slot(self) -> dict[str, Any]:
        """The target slot (a ``slots`` entry of ``setup.world_map``)."""
        return self.setup.slot

    # --- episode -------------------------------------------------------------------------
    def begin(self, seed: int | None = None) -> dict[str, Any]:
        """Start the episode again without rendering (``reset`` = ``begin`` + ``observe``).

        Args:
            seed: replaces the scenario's seed (None: the scenario's own); the start region and the actors' ranges
                are drawn from it.

        Returns:
            The info dict, as ``step`` gives (``actor_collision``, ``truncated`` and ``time`` included).

        Raises:
            ScenarioError: as ``prepare``: no clear start, a slot that does not fit the map.
        """
        scenario = self.scenario if seed is None else self.scenario.model_copy(update={"seed": int(seed)})
        self.setup: Setup = prepare(scenario, self._map, self.vehicle, self._boxes)
        self.world = World.from_scenario(scenario, self.vehicle.dt, self._boxes)
        self.obstacles = Obstacles(self.setup.world_map.get("obstacles", []))
        self.state = VehicleState(*self.setup.start)
        self._steps, self.done = 0, False
        self._poses, self._speeds = [self.state.pose], [self.state.v]
        self._controls: list[tuple[float, float]] = []
        self._actors = [self.world.polygons()]
        self._cost = progress_cost(*parking_errors(self.state.pose, self.slot, self.vehicle))
        return self._info(False, False)

    def advance(self, action: Sequence[float] | np.ndarray) -> tuple[float, bool, dict[str, Any]]:
        """One ``dt`` step without rendering (``step`` = ``advance`` + ``observe``).

        The ego moves under ``action``; then every actor moves, seeing the ego as it was before the step; then the
        ego's footprint is tested against the static obstacles and the actors where they now are.

        Args:
            action: ``[2]`` normalised ``(acceleration, steering)`` (``task.to_controls``).

        Returns:
            ``(reward, done, info)`` as ``step``.

        Raises:
            ValueError: ``action`` holds a NaN or an infinity (refused; nothing moved).
            RuntimeError: the episode is over (``begin`` or ``reset`` first).
        """
        if self.done:
            raise RuntimeError(f"episode of scenario {self.scenario.name!r} is over: call reset() first")
        before = self.state
        self.state, controls = drive(before, action, self.vehicle)
        self.world.step(ego_actor(before.pose, before.v, self.vehicle))
        self._steps += 1
        actors = self.world.polygons()
        body = box_polygon(self.state.pose, self.vehicle.extent)
        static = self.obstacles.collides(self.state.pose, self.vehicle)
        hit = bool(overlaps(body[None], actors).any()) if len(actors) else False
        self._poses.append(self.state.pose)
        self._speeds.append(self.state.v)
        self._controls.append(controls)
        self._actors.append(actors)
        info = self._info(static, hit)
        cost = progress_cost(info["distance"], info["heading_error"])
        r = reward(self._cost, cost, info["is_success"], info["collision"])
        self._cost = cost
        self.done = bool(info["is_success"] or info["collision"] or info["truncated"])
        if self.done:
            info["scorecard"] = self.result()
        return r, self.done, info

    def frame(self) -> Frame | None:
        """The views at the ego's pose with the actors and parked cars drawn in (None when ``renders`` is False).

        Returns:
            The renderer's frame of ``cameras`` (and the BEV), or None.
        """
        if not self.renders:
            return None
        from ..render.actors import Actor

        car = self._assets.get("car") or load_actor_asset("car")
        placed = [Actor(car, pose) for pose in self.setup.parked]     # standing first: their rows never change
        placed += [Actor(self._assets[spec.asset], state.pose)
                   for spec, state in zip(self.world.specs, self.world.states)]
        assert self.renderer is not None     # renders implies a renderer
        return self.renderer.render(self.state.pose, self.cameras, self.bev, self.scale, actors=placed)

    def observe(self, frame: Frame | None) -> dict[str, np.ndarray]:
        """The observation now, with ``frame``'s views (``task.observation``).

        Args:
            frame: the views rendered at the ego's pose (``frame()``), or None.

        Returns:
            ``state`` float32 ``[v, steer, slot_x, slot_y, slot_yaw]``, ``pose`` when privileged, the views.
        """
        return observation(self.state, self.slot, self.privileged, frame)

    def reset(self, seed: int | None = None) -> dict[str, np.ndarray]:
        """Start the episode again and observe.

        Args:
            seed: as ``begin``.

        Returns:
            The first observation (``observe``).
        """
        self.begin(seed)
        return self.observe(self.frame())

    def step(self, action: Sequence[float] | np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, dict[str, Any]]:
        """Apply ``action`` for one ``dt`` and observe.

        Args:
            action: ``[2]`` normalised ``(acceleration, steering)``, clipped to [-1, 1].

        Returns:
            ``(observation, reward, done, info)``: the env's reward; done when parked, on a collision or at the
            time limit; info as the env's (``collision`` is any contact) plus ``actor_collision``, ``truncated``
            (the time limit ended it), ``time`` (s), and ``scorecard`` (``Scorecard``) once done.

        Raises:
            ValueError: ``action`` holds a NaN or an infinity (refused; nothing moved).
            RuntimeError: the episode is over.
        """
        r, done, info = self.advance(action)
        return self.observe(self.frame()), r, done, info

    def _info(self, static: bool, actor: bool) -> dict[str, Any]:
        """The env's info (``task.step_info``) with the actor contact, the time and whether time ran out."""
        info = step_info(self.state, self.slot, self.vehicle, self.setup.pos_tol, self.setup.yaw_tol,
                         static or actor, self.privileged)
        out_of_time = self._steps >= self.setup.max_steps and not (info["is_success"] or info["collision"])
        return info | {"actor_collision": actor, "truncated": out_of_time, "time": self.t}

    # --- results -------------------------------------------------------------------------
    @property
    def log(self) -> EpisodeLog:
        """What happened since ``begin``, for the scorecard.

        Returns:
            The log: ``T`` = steps + 1 times, poses, speeds, controls, actor footprints ``[T, N, 4, 2]``, the
            filled map's obstacles and the target slot.
        """
        n = len(self._poses)
        return EpisodeLog(t=np.arange(n) * self.vehicle.dt, poses=np.array(self._poses),
                          speeds=np.array(self._speeds), controls=np.array(self._controls).reshape(-1, 2),
                          actors=np.stack(self._actors), obstacles=self.obstacles.corners().reshape(-1, 4, 2),
                          slot=np.asarray(self.slot["corners"], np.float64))

    def result(self) -> Scorecard:
        """The scorecard of the episode so far (final once ``done``).

        Returns:
            ``score_episode`` of ``log`` with the scenario's tolerances.
        """
        tol = self.scenario.tolerance
        return score_episode(self.log, self.vehicle, tol.position, tol.heading)
