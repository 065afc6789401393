"""``ParkingEnv`` (gymnasium, registered as ``ParkSim-v0``): park the ego car into a free slot of a scene.

Frames come from the scene bundle in-process (``bundle=``), from ``parksim serve`` (``server=``) or from a
ready frame source shared by several envs (``sim=``); all give the same uint8 images for the same pose.
The ego is a kinematic bicycle (``parksim.vehicle``) stepped at 10 Hz by a normalised action in
``[-1, 1]^2`` (``to_controls``). By default the observation holds no world pose: the ego's speed and
steering, and the target slot in the ego frame; ``privileged=True`` adds the world pose. The car is
parked when its body centre is within ``pos_tol`` of the slot centre, its heading within ``yaw_tol`` of
the slot axis (either way) and it has stopped. Touching a pillar, parked car or wall ends the episode.
Episodes are truncated by gymnasium's ``TimeLimit`` (``max_episode_steps=500`` in the registration).
With ``scenario=`` (a scenario file, or a set folder sampled on reset) each episode is a scenario's
(``parksim.scenarios.episode.Episode``: its start, slot, parked cars, moving actors, time limit and tolerances)
and the last step's info holds its ``scorecard``. The full contract (spaces, reward, ends, seeding) is in
docs/env.md; the rules themselves are ``parksim.scenarios.task``'s:

    >>> to_controls([1.0, -0.5], VehicleParams(max_accel=2.0, max_steer=0.5))
    (2.0, -0.25)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .client import RemoteSim
from .frames import Frame
from .scenarios.episode import Episode
from .scenarios.spec import Scenario, load_scenarios
from .scenarios.task import (
    drive,
    free_slots,
    heading_error,
    observation,
    parking_errors,
    progress_cost,
    reward,
    slot_in_ego_frame,
    slot_pose,
    step_info,
    to_action,
    to_controls,
)
from .sim import LocalSim
from .vehicle import Obstacles, VehicleParams, VehicleState, car_centre, footprint, wrap_angle

if TYPE_CHECKING:
    from .ray_sim import RaySim

__all__ = ["ParkingEnv", "slot_pose", "free_slots", "heading_error", "to_controls", "to_action",
           "MAX_EPISODE_STEPS"]

MAX_EPISODE_STEPS = 500
"""Steps (50 s simulated) before ``TimeLimit`` truncates an episode of ``gym.make("ParkSim-v0")``."""
_TOP_PX_PER_M = 16
_MARGIN_M = 5.0
"""Slack (m) around the scene bounds in the observation boxes (a start pose may sit near a wall)."""


class ParkingEnv(gym.Env):
    """Closed-loop parking in a reconstructed garage: views and ego-relative target in, normalised controls out."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, bundle: str | Path | Any = None, server: str | None = None, scene: str | None = None,
                 api_key: str | None = None, sim: LocalSim | RemoteSim | RaySim | None = None,
                 cameras: Sequence[str] | None = None, bev: bool = False, scale: float = 0.25,
                 privileged: bool = False, pos_tol: float = 0.35, yaw_tol: float = 0.15,
                 vehicle: VehicleParams = VehicleParams(), render_mode: str | None = None,
                 device: str | None = None, scenario: str | Path | None = None) -> None:
        """Open the frame source and build the spaces (docs/env.md has the full contract).

        Args:
            bundle: a bundle folder (or ``Bundle``) rendered in-process by a ``LocalSim``.
            server: URL of ``parksim serve``, rendered there by a ``RemoteSim``.
            scene: the server's scene id (default: its first).
            api_key: the server's API key, if it needs one.
            sim: a ready frame source, shared by several envs.
            cameras: the camera views in the observation (default: all; ``[]`` for none).
            bev: add the BEV to the observation.
            scale: image size relative to the rig's cameras (the BEV keeps its spec's size).
            privileged: add the world pose ``[x, y, yaw]`` to the observation and the info.
            pos_tol: parked when the body centre is within this distance of the slot centre (m).
            yaw_tol: parking also needs the heading within this angle of the slot axis, either way (rad).
            vehicle: the ego's size, limits and steering geometry.
            render_mode: None, or "rgb_array" for ``render()``'s top view.
            device: where ``bundle=`` renders: ``"auto"`` (None: the same), ``"cpu"`` or ``"cuda[:N]"``
                (``LocalSim``). A server or a given sim renders on its own device, so it takes only None or auto.
            scenario: a scenario file, or a set folder whose scenarios ``reset`` samples with the env's seed; its
                start, slot, parked cars, actors, time limit and tolerances replace the env's (``pos_tol`` and
                ``yaw_tol`` are not used then). None: random starts and slots.

        Raises:
            ValueError: not exactly one of ``bundle``, ``server``, ``sim``; an unknown ``render_mode``; a
                ``device`` other than None or auto with ``server`` or ``sim``; a scene without a free slot;
                ``scenario`` with images from a source that cannot draw its actors (only a ``LocalSim`` can).
            ScenarioError: ``scenario`` is not a valid scenario file or set, or does not fit the scene's map.
            DeviceError: a bad ``device`` name, or a GPU this machine lacks.
            RequestError: an unknown camera or a too small ``scale``.
        """
        if sum(source is not None for source in (bundle, server, sim)) != 1:
            raise ValueError("ParkingEnv needs exactly one frame source: bundle=<bundle folder>, server=<URL> "
                             "or sim=<LocalSim or RemoteSim>")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if bundle is None and device not in (None, "auto"):
            raise ValueError(f"device={device!r} applies to bundle= only: with server= or sim= the frames are "
                             "rendered on that source's own device (parksim serve --device)")
        self.sim: LocalSim | RemoteSim | RaySim = (sim if sim is not None else LocalSim(bundle, device=device or "auto")
                                          if server is None else RemoteSim(server, scene=scene, api_key=api_key))
        info = self.sim.info()
        if not info.get("map") or not free_slots(info["map"]):
            raise ValueError(f"scene {info['id']!r} has no slot map with a free slot to park in")
        self.world_map: dict[str, Any] = info["map"]
        self.cameras = list(self.sim.cameras if cameras is None else cameras)
        if isinstance(self.sim, LocalSim):
            self.sim.check(self.cameras, scale)
        self.bev, self.scale, self.privileged = bev, scale, privileged
        self.pos_tol, self.yaw_tol, self.vehicle = pos_tol, yaw_tol, vehicle
        self.render_mode = render_mode
        self.obstacles = Obstacles(self.world_map.get("obstacles", []))
        (x0, x1), (y0, y1) = info["bounds"]["x"], info["bounds"]["y"]
        self._start_box = ((x0 - _MARGIN_M, x1 + _MARGIN_M), (y0 - _MARGIN_M, y1 + _MARGIN_M))
        self.action_space: spaces.Box = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = spaces.Dict(self._image_spaces(info) | self._state_spaces(info))
        self.state = VehicleState(0.0, 0.0, 0.0)
        self.slot: dict[str, Any] = free_slots(self.world_map)[0]
        self._cost = 0.0
        self._background: np.ndarray | None = None
        self._scene_map = self.world_map
        self.scenarios: tuple[Scenario, ...] = ()
        self._episodes: dict[int, Episode] = {}
        self.episode: Episode | None = None
        if scenario is not None:
            self._open_scenarios(Path(scenario))

    def _open_scenarios(self, path: Path) -> None:
        """Read the scenario file or set and make each scenario's ``Episode`` once (checked against the map)."""
        self.scenarios = tuple(load_scenarios(path))
        if self.renders and not isinstance(self.sim, LocalSim):
            raise ValueError("scenario= draws its actors into the views in-process: give bundle= or sim=<LocalSim>, "
                             "or ask for no images (cameras=[], bev=False)")
        renderer = self.sim if self.renders and isinstance(self.sim, LocalSim) else None
        root = path if path.is_dir() else path.parent
        self._episodes = {i: Episode(s, self._scene_map, renderer, cameras=self.cameras, bev=self.bev,
                                     scale=self.scale, privileged=self.privileged, vehicle=self.vehicle,
                                     asset_root=root)
                          for i, s in enumerate(self.scenarios)}

    def _state_spaces(self, info: dict[str, Any]) -> dict[str, spaces.Space[Any]]:
        """``state`` = ``[v, steer, slot_x, slot_y, slot_yaw]`` (slot in the ego frame); ``pose`` when privileged."""
        (x0, x1), (y0, y1), p = info["bounds"]["x"], info["bounds"]["y"], self.vehicle
        reach = math.hypot(x1 - x0, y1 - y0) + 2 * _MARGIN_M
        out: dict[str, spaces.Space[Any]] = {"state": spaces.Box(
            np.array([-p.max_reverse, -p.max_steer, -reach, -reach, -math.pi], np.float32),
            np.array([p.max_speed, p.max_steer, reach, reach, math.pi], np.float32))}
        if self.privileged:
            out["pose"] = spaces.Box(np.array([x0 - _MARGIN_M, y0 - _MARGIN_M, -math.pi], np.float32),
                                     np.array([x1 + _MARGIN_M, y1 + _MARGIN_M, math.pi], np.float32))
        return out

    def _image_spaces(self, info: dict[str, Any]) -> dict[str, spaces.Space[Any]]:
        """uint8 HxWx3 boxes for the requested views at ``scale`` (the BEV has the rig's BEV size)."""
        out: dict[str, spaces.Space[Any]] = {}
        for name in self.cameras:
            c = info["rig"]["cameras"][name]["intrinsics"]
            shape = (round(c["height"] * self.scale), round(c["width"] * self.scale), 3)
            out[name] = spaces.Box(0, 255, shape, np.uint8)
        if self.bev:
            out["bev"] = spaces.Box(0, 255, (info["bev"]["height"], info["bev"]["width"], 3), np.uint8)
        return out

    # --- episode -------------------------------------------------------------------------
    def _random_start(self) -> VehicleState:
        """A collision-free pose on an aisle centre line, facing along the aisle (either way); 200 tries."""
        g = self.world_map["garage"]
        lanes = g.get("lanes") or [float(np.mean(g["y"]))]
        for _ in range(200):
            x = self.np_random.uniform(g["x"][0] + 4.0, g["x"][1] - 4.0)
            y = float(self.np_random.choice(lanes)) + self.np_random.uniform(-0.4, 0.4)
            yaw = self.np_random.uniform(-0.15, 0.15) + (math.pi if self.np_random.random() < 0.5 else 0.0)
            if not self.obstacles.collides((x, y, yaw), self.vehicle, margin=0.3):
                return VehicleState(x, y, float(wrap_angle(yaw)))
        raise RuntimeError("no collision-free start pose found on the aisles")

    def _given_start(self, start: Any) -> VehicleState:
        """``options["start"]`` as a standing state, yaw wrapped; refused unless 3 finite values inside the box."""
        pose = np.asarray(start, np.float64)
        if pose.shape != (3,):
            raise ValueError(f"options['start'] must be (x, y, yaw), 3 numbers, got {start!r}")
        if not np.isfinite(pose).all():
            raise ValueError(f"options['start'] {pose.tolist()} has a non-finite value (NaN or inf)")
        (x0, x1), (y0, y1) = self._start_box
        x, y, yaw = map(float, pose)
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            raise ValueError(f"options['start'] {pose.tolist()} is outside the scene: x must lie in [{x0:g}, {x1:g}] "
                             f"and y in [{y0:g}, {y1:g}] (its bounds plus {_MARGIN_M:g} m)")
        return VehicleState(x, y, float(wrap_angle(yaw)))

    def begin(self, seed: int | None = None, options: dict[str, Any] | None = None) -> dict[str, Any]:
        """Start an episode without rendering (``reset`` = ``begin`` + ``observe``); returns its info.

        Args:
            seed: seeds ``np_random`` (gymnasium's rule: only the first reset needs one).
            options: ``start`` = ``(x, y, yaw)`` (finite, within the scene's bounds plus 5 m; yaw is wrapped to
                [-pi, pi)) and/or ``slot`` = a free slot's id; none with ``scenario=`` (the scenario fixes both).

        Returns:
            The info dict (``slot``, ``distance``, ``heading_error``, ``collision``, ``is_success``, ``speed``,
            and ``pose`` when privileged; with ``scenario=`` also ``scenario``, ``actor_collision``, ``truncated``
            and ``time``).

        Raises:
            ValueError: ``options["start"]`` is not 3 finite numbers within the bounds (nothing is changed then),
                or ``options["slot"]`` is not a free slot, or options are given with ``scenario=``.
            RuntimeError: no collision-free random start in 200 tries.
        """
        if self.scenarios:
            return self._begin_scenario(seed, options)
        options = options or {}
        start = self._given_start(options["start"]) if "start" in options else None
        super().reset(seed=seed)
        self.state = start if start is not None else self._random_start()
        slots = free_slots(self.world_map)
        if "slot" in options:
            chosen = [s for s in slots if s["id"] == options["slot"]]
            if not chosen:
                raise ValueError(f"slot {options['slot']!r} is not a free slot; free slots: {[s['id'] for s in slots]}")
            self.slot = chosen[0]
        else:
            self.slot = slots[int(self.np_random.integers(len(slots)))]
        self._cost = self._progress_cost()
        return self._info(collided=False)

    def _begin_scenario(self, seed: int | None, options: dict[str, Any] | None) -> dict[str, Any]:
        """``begin`` with ``scenario=``: draw a scenario of the set and start its episode."""
        if options:
            raise ValueError(f"reset options {sorted(options)} do not apply with scenario=: the scenario fixes the "
                             "start and the slot")
        super().reset(seed=seed)
        index = int(self.np_random.integers(len(self.scenarios)))
        self.episode = self._episodes[index]
        info = self.episode.begin()
        self.world_map, self.obstacles = self.episode.setup.world_map, self.episode.obstacles   # parked cars added
        self.state, self.slot, self._background = self.episode.state, self.episode.slot, None
        return info | {"scenario": self.scenarios[index].name}

    def advance(self, action: np.ndarray) -> tuple[float, bool, dict[str, Any]]:
        """Apply one normalised action for 0.1 s without rendering (``step`` = ``advance`` + ``observe``).

        Args:
            action: ``[2]`` normalised ``(acceleration, steering)`` (``to_controls``).

        Returns:
            ``(reward, terminated, info)``: terminated when parked or collided (with ``scenario=``, the scenario's
            time limit sets ``info["truncated"]`` instead, and the episode's last info holds its ``scorecard``).

        Raises:
            ValueError: ``action`` holds a NaN or an infinity; it is refused and the state is unchanged.
        """
        if self.episode is not None:
            r, done, info = self.episode.advance(action)
            self.state = self.episode.state
            return r, done and not info["truncated"], info
        self.state, _ = drive(self.state, action, self.vehicle)
        collided = self.obstacles.collides(self.state.pose, self.vehicle)
        cost = self._progress_cost()
        info = self._info(collided)
        r = reward(self._cost, cost, info["is_success"], collided)
        self._cost = cost
        return r, bool(info["is_success"] or collided), info

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """New episode. ``options``: ``start`` = (x, y, yaw) and/or ``slot`` = slot id (default: random free slot).

        The random start is drawn before the slot, so the same seed gives the same start whatever slot is chosen.

        Args:
            seed: seeds ``np_random``.
            options: ``start`` = ``(x, y, yaw)`` and/or ``slot`` = a free slot's id.

        Returns:
            ``(observation, info)``: uint8 ``[H, W, 3]`` per camera, ``bev`` when asked, ``state`` float32
            ``[v, steer, slot_x, slot_y, slot_yaw]``, ``pose`` when privileged; info as ``begin``.

        Raises:
            ValueError: as ``begin``: a bad ``options["start"]`` or ``options["slot"]``.
        """
        info = self.begin(seed, options)
        return self.observe(self.frame()), info

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Apply the normalised ``[acceleration, steering]`` for 0.1 s; truncates only at a scenario's time limit.

        Args:
            action: ``[2]`` in [-1, 1] (clipped).

        Returns:
            ``(observation, reward, terminated, truncated, info)``; ``truncated`` is False without ``scenario=``
            (``TimeLimit`` truncates then).

        Raises:
            ValueError: ``action`` holds a NaN or an infinity; it is refused and the state is unchanged.
        """
        r, terminated, info = self.advance(action)
        return self.observe(self.frame()), r, terminated, bool(info.get("truncated", False)), info

    # --- measurements --------------------------------------------------------------------
    def errors(self) -> tuple[float, float]:
        """(distance of the body centre to the slot centre in m, heading error to the slot axis in rad).

        Returns:
            ``(distance, heading_error)`` at the current state.
        """
        return parking_errors(self.state.pose, self.slot, self.vehicle)

    def _progress_cost(self) -> float:
        """What the reward decreases: distance + 0.5 heading error."""
        return progress_cost(*self.errors())

    def target_pose(self) -> tuple[float, float, float]:
        """Rear-axle pose that parks the car head-in, centred in the target slot.

        Returns:
            ``(x, y, yaw)`` in world metres and radians.
        """
        centre, yaw = slot_pose(self.slot)
        x0, x1, _, _ = self.vehicle.extent
        d = (x0 + x1) / 2
        return (float(centre[0] - d * math.cos(yaw)), float(centre[1] - d * math.sin(yaw)), yaw)

    def slot_in_ego_frame(self) -> tuple[float, float, float]:
        """The target slot's centre and parking heading in the ego frame.

        Returns:
            ``(x, y, yaw)``: metres with x forward, y left and the origin under the rear axle; radians.
        """
        return slot_in_ego_frame(self.state.pose, self.slot)

    def _info(self, collided: bool) -> dict[str, Any]:
        """The step's info dict (see ``begin``)."""
        return step_info(self.state, self.slot, self.vehicle, self.pos_tol, self.yaw_tol, collided, self.privileged)

    @property
    def renders(self) -> bool:
        """Whether observations hold images (a camera or the BEV was asked for)."""
        return bool(self.cameras or self.bev)

    def frame(self) -> Frame | None:
        """The views at the current pose, rendered by ``sim`` (None when ``renders`` is False).

        Returns:
            The frame of the env's cameras (and BEV), with a scenario's actors drawn in, or None.
        """
        if self.episode is not None:
            return self.episode.frame()
        return self.sim.render(self.state.pose, self.cameras, self.bev, self.scale) if self.renders else None

    def observe(self, frame: Frame | None) -> dict[str, np.ndarray]:
        """The observation at the current state, with ``frame``'s views.

        Args:
            frame: the views rendered at ``state.pose``; None when ``renders`` is False.

        Returns:
            The observation dict (see ``reset``).
        """
        return observation(self.state, self.slot, self.privileged, frame)

    # --- top view ------------------------------------------------------------------------
    def _to_px(self, xy: np.ndarray) -> np.ndarray:
        """World ``[..., 2]`` -> top-view pixels ``[..., 2]`` int32."""
        g = self.world_map["garage"]
        u = (xy[..., 0] - g["x"][0]) * _TOP_PX_PER_M
        v = (g["y"][1] - xy[..., 1]) * _TOP_PX_PER_M
        return np.round(np.stack([u, v], -1)).astype(np.int32)

    def _static_top_view(self) -> np.ndarray:
        """Floor, slots (occupied grey, free white) and obstacles, drawn once."""
        import cv2

        g = self.world_map["garage"]
        w = int((g["x"][1] - g["x"][0]) * _TOP_PX_PER_M)
        h = int((g["y"][1] - g["y"][0]) * _TOP_PX_PER_M)
        img = np.full((h, w, 3), 60, np.uint8)
        for s in self.world_map.get("slots", []):
            colour = (120, 120, 120) if s.get("occupied") else (230, 230, 230)
            cv2.polylines(img, [self._to_px(np.asarray(s["corners"]))], True, colour, 1, cv2.LINE_AA)
        kinds = {"pillar": (150, 150, 170), "car": (90, 110, 160), "wall": (180, 170, 150)}
        for kind, corners in zip(self.obstacles.kinds, self.obstacles.corners()):
            cv2.fillPoly(img, [self._to_px(corners)], kinds.get(kind, (200, 200, 200)), cv2.LINE_AA)
        return img

    def render(self) -> np.ndarray | None:
        """RGB top view of the garage: target slot in green, a scenario's actors in red, the ego in orange.

        Returns:
            uint8 ``[H, W, 3]`` at 16 px/m over the garage floor, or None unless ``render_mode="rgb_array"``.
        """
        import cv2

        if self.render_mode != "rgb_array":
            return None
        if self._background is None:
            self._background = self._static_top_view()
        img = self._background.copy()
        cv2.polylines(img, [self._to_px(np.asarray(self.slot["corners"]))], True, (40, 220, 60), 2, cv2.LINE_AA)
        for actor in (self.episode.world.polygons() if self.episode is not None else ()):
            cv2.fillPoly(img, [self._to_px(actor)], (220, 50, 50), cv2.LINE_AA)
        body = self._to_px(footprint(self.state.pose, self.vehicle))
        cv2.fillPoly(img, [body], (255, 140, 0), cv2.LINE_AA)
        centre = self._to_px(car_centre(self.state.pose, self.vehicle))
        nose = (body[0] + body[3]) // 2
        cv2.line(img, tuple(int(v) for v in centre), tuple(int(v) for v in nose), (20, 20, 20), 2, cv2.LINE_AA)
        return img


if "ParkSim-v0" not in gym.registry:
    gym.register("ParkSim-v0", entry_point="parksim.env:ParkingEnv", max_episode_steps=MAX_EPISODE_STEPS,
                 vector_entry_point="parksim.vector_env:make_vector_env")
