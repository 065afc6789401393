"""``ParkingEnv`` (gymnasium, registered as ``ParkSim-v0``): park the ego car into a free slot of a scene.

Frames come from the scene bundle in-process (``bundle=``), from ``parksim serve`` (``server=``) or from a
ready frame source shared by several envs (``sim=``); all give the same uint8 images for the same pose.
The ego is a kinematic bicycle (``parksim.vehicle``) stepped at 10 Hz by a normalised action in
``[-1, 1]^2`` (``to_controls``). By default the observation holds no world pose: the ego's speed and
steering, and the target slot in the ego frame; ``privileged=True`` adds the world pose. The car is
parked when its body centre is within ``pos_tol`` of the slot centre, its heading within ``yaw_tol`` of
the slot axis (either way) and it has stopped. Touching a pillar, parked car or wall ends the episode.
Episodes are truncated by gymnasium's ``TimeLimit`` (``max_episode_steps=500`` in the registration).
The full contract (spaces, reward, ends, seeding) is in docs/env.md.
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
from .sim import LocalSim

if TYPE_CHECKING:
    from .ray_sim import RaySim
from .vehicle import Obstacles, VehicleParams, VehicleState, car_centre, footprint, step, wrap_angle

__all__ = ["ParkingEnv", "slot_pose", "free_slots", "heading_error", "to_controls", "to_action",
           "MAX_EPISODE_STEPS"]

MAX_EPISODE_STEPS = 500
"""Steps (50 s simulated) before ``TimeLimit`` truncates an episode of ``gym.make("ParkSim-v0")``."""
_SUCCESS_BONUS, _COLLISION_PENALTY, _STEP_COST, _YAW_WEIGHT = 10.0, 10.0, 0.01, 0.5
_TOP_PX_PER_M = 16
_MARGIN_M = 5.0
"""Slack (m) around the scene bounds in the observation boxes (a start pose may sit near a wall)."""


def slot_pose(slot: dict[str, Any]) -> tuple[np.ndarray, float]:
    """Slot centre (world xy) and its parking heading: into the slot, or along it for parallel slots.

    Args:
        slot: a map slot with ``corners`` ``[4, 2]`` (world metres; the first two on the entrance side).

    Returns:
        ``(centre [2], yaw)``: the centre in metres and the heading in radians along the slot's longer side.
    """
    c = np.asarray(slot["corners"], np.float64)
    centre = c.mean(axis=0)
    into = c[2:].mean(axis=0) - c[:2].mean(axis=0)
    along = c[1] - c[0]
    axis = along if np.linalg.norm(along) > np.linalg.norm(into) else into
    return centre, math.atan2(axis[1], axis[0])


def free_slots(world_map: dict[str, Any]) -> list[dict[str, Any]]:
    """The map's slots that no parked car occupies.

    Args:
        world_map: a scene's ``map.json`` content.

    Returns:
        The slots whose ``occupied`` is false or absent, in map order.
    """
    return [s for s in world_map.get("slots", []) if not s.get("occupied", False)]


def heading_error(yaw: float, slot_yaw: float) -> float:
    """Heading error to the slot axis in [0, pi/2]: forward or backward parking both count.

    Args:
        yaw: the car's heading in radians.
        slot_yaw: the slot's heading in radians (``slot_pose``).

    Returns:
        The smaller angle between the car and the slot axis, radians.

    Example:
        >>> round(heading_error(math.pi - 0.1, 0.0), 6)
        0.1
    """
    e = abs(float(wrap_angle(yaw - slot_yaw)))
    return min(e, math.pi - e)


def to_controls(action: Sequence[float] | np.ndarray, p: VehicleParams) -> tuple[float, float]:
    """(acceleration m/s^2, steering rad) for a normalised action, clipped to [-1, 1] first.

    ``action[0]`` = +1 is ``p.max_accel``, -1 is ``-p.max_decel`` (linear on each side of 0: the car
    brakes harder than it accelerates); ``action[1]`` = +-1 is +-``p.max_steer`` (positive steers left).

    Args:
        action: ``[2]`` normalised ``(acceleration, steering)``.
        p: the vehicle's limits.

    Returns:
        ``(acceleration, steering)`` in m/s^2 and radians.
    """
    a = np.clip(np.asarray(action, np.float64).reshape(2), -1.0, 1.0)
    accel = a[0] * (p.max_accel if a[0] >= 0 else p.max_decel)
    return float(accel), float(a[1] * p.max_steer)


def to_action(accel: float, steer: float, p: VehicleParams) -> np.ndarray:
    """Inverse of ``to_controls``: the float32 normalised action for physical controls (clipped to the limits).

    Args:
        accel: acceleration in m/s^2 (negative brakes).
        steer: steering angle in radians (positive left).
        p: the vehicle's limits.

    Returns:
        ``[2]`` float32 action in [-1, 1].
    """
    a = accel / (p.max_accel if accel >= 0 else p.max_decel)
    return np.clip(np.array([a, steer / p.max_steer], np.float32), -1.0, 1.0)


class ParkingEnv(gym.Env):
    """Closed-loop parking in a reconstructed garage: views and ego-relative target in, normalised controls out."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, bundle: str | Path | Any = None, server: str | None = None, scene: str | None = None,
                 api_key: str | None = None, sim: LocalSim | RemoteSim | RaySim | None = None,
                 cameras: Sequence[str] | None = None, bev: bool = False, scale: float = 0.25,
                 privileged: bool = False, pos_tol: float = 0.35, yaw_tol: float = 0.15,
                 vehicle: VehicleParams = VehicleParams(), render_mode: str | None = None,
                 device: str | None = None) -> None:
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

        Raises:
            ValueError: not exactly one of ``bundle``, ``server``, ``sim``; an unknown ``render_mode``; a
                ``device`` other than None or auto with ``server`` or ``sim``; a scene without a free slot.
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
                [-pi, pi)) and/or ``slot`` = a free slot's id.

        Returns:
            The info dict (``slot``, ``distance``, ``heading_error``, ``collision``, ``is_success``, ``speed``,
            and ``pose`` when privileged).

        Raises:
            ValueError: ``options["start"]`` is not 3 finite numbers within the bounds (nothing is changed then),
                or ``options["slot"]`` is not a free slot.
            RuntimeError: no collision-free random start in 200 tries.
        """
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

    def advance(self, action: np.ndarray) -> tuple[float, bool, dict[str, Any]]:
        """Apply one normalised action for 0.1 s without rendering (``step`` = ``advance`` + ``observe``).

        Args:
            action: ``[2]`` normalised ``(acceleration, steering)`` (``to_controls``).

        Returns:
            ``(reward, terminated, info)``: terminated when parked or collided.

        Raises:
            ValueError: ``action`` holds a NaN or an infinity; it is refused and the state is unchanged.
        """
        if not np.isfinite(np.asarray(action, np.float64)).all():
            raise ValueError(f"action {np.asarray(action).tolist()} has a non-finite value (NaN or inf): refused, "
                             "the vehicle state is unchanged")
        accel, steer = to_controls(action, self.vehicle)
        self.state = step(self.state, accel, steer, self.vehicle)
        collided = self.obstacles.collides(self.state.pose, self.vehicle)
        cost = self._progress_cost()
        info = self._info(collided)
        reward = self._cost - cost - _STEP_COST + _SUCCESS_BONUS * info["is_success"] - _COLLISION_PENALTY * collided
        self._cost = cost
        return float(reward), bool(info["is_success"] or collided), info

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
        """Apply the normalised ``[acceleration, steering]`` for 0.1 s; never truncates (``TimeLimit`` does).

        Args:
            action: ``[2]`` in [-1, 1] (clipped).

        Returns:
            ``(observation, reward, terminated, truncated=False, info)``.

        Raises:
            ValueError: ``action`` holds a NaN or an infinity; it is refused and the state is unchanged.
        """
        reward, terminated, info = self.advance(action)
        return self.observe(self.frame()), reward, terminated, False, info

    # --- measurements --------------------------------------------------------------------
    def errors(self) -> tuple[float, float]:
        """(distance of the body centre to the slot centre in m, heading error to the slot axis in rad).

        Returns:
            ``(distance, heading_error)`` at the current state.
        """
        centre, slot_yaw = slot_pose(self.slot)
        dist = float(np.linalg.norm(car_centre(self.state.pose, self.vehicle) - centre))
        return dist, heading_error(self.state.yaw, slot_yaw)

    def _progress_cost(self) -> float:
        """What the reward decreases: distance + 0.5 heading error."""
        dist, yaw_err = self.errors()
        return dist + _YAW_WEIGHT * yaw_err

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
        centre, slot_yaw = slot_pose(self.slot)
        s = self.state
        dx, dy = centre[0] - s.x, centre[1] - s.y
        c, si = math.cos(s.yaw), math.sin(s.yaw)
        return (c * dx + si * dy, -si * dx + c * dy, float(wrap_angle(slot_yaw - s.yaw)))

    def _info(self, collided: bool) -> dict[str, Any]:
        """The step's info dict (see ``begin``)."""
        dist, yaw_err = self.errors()
        parked = dist < self.pos_tol and yaw_err < self.yaw_tol and abs(self.state.v) < 0.1
        info = {"slot": self.slot["id"], "distance": dist, "heading_error": yaw_err, "collision": bool(collided),
                "is_success": bool(parked and not collided), "speed": self.state.v}
        return info | {"pose": self.state.pose} if self.privileged else info

    @property
    def renders(self) -> bool:
        """Whether observations hold images (a camera or the BEV was asked for)."""
        return bool(self.cameras or self.bev)

    def frame(self) -> Frame | None:
        """The views at the current pose, rendered by ``sim`` (None when ``renders`` is False).

        Returns:
            The frame of the env's cameras (and BEV), or None.
        """
        return self.sim.render(self.state.pose, self.cameras, self.bev, self.scale) if self.renders else None

    def observe(self, frame: Frame | None) -> dict[str, np.ndarray]:
        """The observation at the current state, with ``frame``'s views.

        Args:
            frame: the views rendered at ``state.pose``; None when ``renders`` is False.

        Returns:
            The observation dict (see ``reset``).
        """
        s = self.state
        obs: dict[str, np.ndarray] = {"state": np.array([s.v, s.steer, *self.slot_in_ego_frame()], np.float32)}
        if self.privileged:
            obs["pose"] = np.array(s.pose, np.float32)
        if frame is not None:
            obs.update(frame.images)
            if frame.bev is not None:   # exactly when self.bev asked for one
                obs["bev"] = frame.bev
        return obs

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
        """RGB top view of the garage: target slot in green, the ego footprint in orange with its heading.

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
        body = self._to_px(footprint(self.state.pose, self.vehicle))
        cv2.fillPoly(img, [body], (255, 140, 0), cv2.LINE_AA)
        centre = self._to_px(car_centre(self.state.pose, self.vehicle))
        nose = (body[0] + body[3]) // 2
        cv2.line(img, tuple(int(v) for v in centre), tuple(int(v) for v in nose), (20, 20, 20), 2, cv2.LINE_AA)
        return img


if "ParkSim-v0" not in gym.registry:
    gym.register("ParkSim-v0", entry_point="parksim.env:ParkingEnv", max_episode_steps=MAX_EPISODE_STEPS,
                 vector_entry_point="parksim.vector_env:make_vector_env")
