"""Episodes held by the server between requests, for planners that are not Python (docs/episode_api.md).

Each is a scenario in closed loop (``parksim.scenarios.episode.Episode``), driven over HTTP (``episode_routes``).

``open_episode`` checks a ``POST /episodes`` body against the scene and the server's limits and makes the
``LiveEpisode``; its ``first``, ``step`` and ``result`` run on the render pool's threads, each under the episode's
own lock, so two concurrent steps of one episode run one after the other (and a step that outlived its request's
timeout still finishes before the next begins). They answer JSON bytes: the observation's views as base64 PNG or
JPEG, numbers as JSON numbers (float32 values exactly), the scorecard as a dict.

The ``EpisodeStore`` keeps at most ``capacity`` episodes and drops one no request has touched for ``ttl_s``
seconds. Expiry is checked on every access to the store (no timer thread), so an idle server keeps its expired
episodes until the next episode request; the store runs on the event loop only, so it needs no lock of its own.
"""

from __future__ import annotations

import base64
import json
import math
import secrets
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import PurePosixPath
from typing import Any, Literal

import numpy as np
import yaml

from parksim.frames import RequestError
from parksim.scenarios.episode import Episode
from parksim.scenarios.score import Scorecard
from parksim.scenarios.spec import Scenario, ScenarioError, parse_scenario

from .budget import ReplyTooLarge
from .jobs import encode_image
from .scenes import SceneRegistry
from .schemas import EpisodeRequest, builtin_asset
from .settings import Settings

__all__ = ["EpisodeError", "UnknownEpisode", "EpisodeOver", "EpisodesFull", "LiveEpisode", "EpisodeStore",
           "open_episode", "read_scenario", "scene_id"]

_JSON_OVERHEAD = 4096
"""Bytes of an observation reply besides its images (state, pose, info, scorecard, keys)."""


class EpisodeError(Exception):
    """An episode request answered with ``status`` and ``headers``; the message says why (one line)."""

    status = 400

    def __init__(self, message: str, headers: dict[str, str] | None = None) -> None:
        """Keep the message and the reply's extra headers (None: none)."""
        super().__init__(message)
        self.headers = headers


class UnknownEpisode(EpisodeError):
    """No live episode has this id: it never existed, was deleted, or expired."""

    status = 404


class EpisodeOver(EpisodeError):
    """A step of an episode that has ended (parked, collided or out of time)."""

    status = 409


class EpisodesFull(EpisodeError):
    """The store holds ``capacity`` episodes; ``Retry-After`` says when the next idle one expires."""

    status = 503


class _NoAliases(yaml.SafeLoader):
    """Safe YAML without aliases.

    An alias repeats a node without copying it, so a small body could stand for a scenario of billions of values.
    """

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(None, None, "aliases (*name) are not accepted",
                                              self.peek_event().start_mark)
        return super().compose_node(parent, index)


def read_scenario(data: dict[str, Any] | str) -> Scenario:
    """A request's scenario: its fields, or the text of a scenario file; actors may name built-in assets only.

    Args:
        data: the parsed fields, or YAML/JSON text (no anchors or aliases).

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: text that is not YAML, or a scenario the format refuses (one line, ``scenario: key: why``).
        RequestError: an actor whose asset is not a built-in name.
    """
    if isinstance(data, str):
        try:
            data = yaml.load(data, Loader=_NoAliases)
        except (yaml.YAMLError, RecursionError) as e:
            why = " ".join(str(e).split()) if isinstance(e, yaml.YAMLError) else "nested too deeply"
            raise ScenarioError(f"scenario: not valid YAML: {why}") from None
    scenario = parse_scenario(data, "scenario")
    for i, actor in enumerate(scenario.actors):
        try:
            builtin_asset(actor.asset, f"scenario: actors.{i}.asset")
        except ValueError as e:
            raise RequestError(str(e)) from None
    return scenario


def _plain(value: Any) -> Any:
    """``value`` in JSON types: numpy scalars and arrays as numbers and lists, a ``Scorecard`` as its dict."""
    if isinstance(value, Scorecard):
        return value.to_dict()
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    return value.item() if isinstance(value, np.generic) else value


def _json(value: dict[str, Any]) -> bytes:
    """Compact JSON bytes (a NaN or an infinity is a bug: refused)."""
    return json.dumps(value, allow_nan=False, separators=(",", ":")).encode()


@dataclass
class LiveEpisode:
    """An episode between requests, with what its replies need.

    Attributes:
        episode: the episode (touched only under ``lock``).
        image_format: ``png`` or ``jpeg``.
        jpeg_quality: of JPEG views.
        reply_bytes: an upper bound of one observation reply (what the reply budget reserves).
        id: unguessable (128 random bits).
        used: the store clock's time of the last request's start or end.
        active: requests in flight (an episode is never expired while one is).
        lock: serialises the work on ``episode``.
    """

    episode: Episode
    image_format: Literal["png", "jpeg"]
    jpeg_quality: int
    reply_bytes: int
    id: str = field(default_factory=lambda: secrets.token_hex(16))
    used: float = 0.0
    active: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def _observation(self, obs: dict[str, np.ndarray]) -> dict[str, Any]:
        """``state``, ``pose`` (when privileged) as numbers; each view and the BEV as base64 image text."""
        def text(image: np.ndarray) -> str:
            return base64.b64encode(encode_image(image, self.image_format, self.jpeg_quality)).decode()

        out: dict[str, Any] = {"state": _plain(obs["state"])}
        if "pose" in obs:
            out["pose"] = _plain(obs["pose"])
        out["images"] = {name: text(obs[name]) for name in self.episode.cameras}
        if "bev" in obs:
            out["bev"] = text(obs["bev"])
        return out

    def first(self, seed: int | None) -> bytes:
        """Start the episode (``Episode.begin``) and observe, as ``ParkingEnv.reset`` of the scenario does.

        Args:
            seed: replaces the scenario's seed (None: its own).

        Returns:
            JSON ``{"id", "observation", "info"}``; the info holds the scenario's name as ``scenario``.
        """
        with self.lock:
            info = self.episode.begin(seed) | {"scenario": self.episode.scenario.name}
            obs = self.episode.observe(self.episode.frame())
            return _json({"id": self.id, "observation": self._observation(obs), "info": _plain(info)})

    def step(self, action: Sequence[float]) -> bytes:
        """One ``dt`` step under ``action`` (``Episode.step``).

        Args:
            action: ``[acceleration, steering]``, finite, normalised to [-1, 1].

        Returns:
            JSON ``{"observation", "reward", "done", "truncated", "info"}``.

        Raises:
            EpisodeOver: the episode has ended.
        """
        with self.lock:
            if self.episode.done:
                raise self.over()
            obs, reward, done, info = self.episode.step(action)
            return _json({"observation": self._observation(obs), "reward": float(reward), "done": done,
                          "truncated": bool(info["truncated"]), "info": _plain(info)})

    def result(self) -> bytes:
        """The scorecard so far.

        Returns:
            JSON ``{"id", "scenario", "done", "scorecard"}``.
        """
        with self.lock:
            card = self.episode.result()
            return _json({"id": self.id, "scenario": self.episode.scenario.name, "done": self.episode.done,
                          "scorecard": card.to_dict()})

    def over(self) -> EpisodeOver:
        """The error of a step after the end.

        Returns:
            ``EpisodeOver`` naming the episode and what to do instead.
        """
        return EpisodeOver(f"episode {self.id} of scenario {self.episode.scenario.name!r} is over: GET "
                           f"/episodes/{self.id}/result has its scorecard; POST /episodes starts another")


def scene_id(scene: str, loaded: Sequence[str]) -> str:
    """The loaded scene a scenario's ``scene`` names.

    That is the id itself, or a path whose last part is a loaded id (as ``parksim scenarios make`` writes it,
    relative to its set). A request never names a server file: the path is read only for its last part.

    Args:
        scene: ``Scenario.scene``.
        loaded: the loaded scene ids.

    Returns:
        ``scene``, or its last path part when that is loaded and ``scene`` is not.
    """
    last = PurePosixPath(scene.replace("\\", "/")).name
    return last if scene not in loaded and last in loaded else scene


def open_episode(registry: SceneRegistry, settings: Settings, request: EpisodeRequest) -> LiveEpisode:
    """Check a ``POST /episodes`` body and make its episode (not yet started: ``LiveEpisode.first``).

    Reads the scenario, finds its scene, checks the views and scale against the scene and the limits, and bounds
    one observation reply by ``max_reply_bytes`` (PNG of its raw pixels plus a little, times 4/3 for base64).

    Args:
        registry: the loaded scenes.
        settings: the limits.
        request: the body.

    Returns:
        The episode.

    Raises:
        ScenarioError: as ``read_scenario``, or a scenario that does not fit the scene's map.
        RequestError: a non-built-in actor asset, a scene without a slot map, a bad camera or scale.
        UnknownScene: the scenario's scene is not loaded.
        ReplyTooLarge: one observation would exceed ``max_reply_bytes``.
    """
    scenario = read_scenario(request.scenario)
    sim = registry.get(scene_id(scenario.scene, registry.ids))
    if not sim.bundle.map or not sim.bundle.map.get("slots"):
        raise RequestError(f"scene {sim.id!r} has no slot map (map.json with slots): episodes need one")
    if not settings.min_scale <= request.scale <= settings.max_scale:
        raise RequestError(f"scale={request.scale:g} is out of range: it must be in [{settings.min_scale:g}, "
                           f"{settings.max_scale:g}]")
    cameras = sim.check(request.cameras, request.scale)
    raw = sim.reply_bytes(1, cameras, request.bev, request.scale, False) if cameras or request.bev else 0
    size = math.ceil(raw * 1.01 * 4 / 3) + 1024 * (len(cameras) + 1) + _JSON_OVERHEAD
    if size > settings.max_reply_bytes:
        raise ReplyTooLarge(f"an observation would be up to {size} bytes ({len(cameras)} camera(s)"
                            f"{' + BEV' if request.bev else ''} at scale {request.scale:g}, base64), over this "
                            f"server's limit of {settings.max_reply_bytes} bytes per reply: ask for fewer views or a "
                            f"smaller scale")
    episode = Episode(scenario, sim.bundle.map, sim, cameras=cameras, bev=request.bev, scale=request.scale,
                      privileged=request.privileged)
    return LiveEpisode(episode, request.image_format, settings.jpeg_quality, size)


class EpisodeStore:
    """The live episodes by id: at most ``capacity``, each dropped after ``ttl_s`` seconds untouched.

    ``clock`` gives the time in seconds (``time.monotonic``; a test may pass its own).
    """

    def __init__(self, capacity: int, ttl_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        """Start empty.

        Args:
            capacity: episodes held at once.
            ttl_s: idle seconds before an episode is dropped.
            clock: the time source.
        """
        self.capacity, self.ttl_s, self.clock = capacity, ttl_s, clock
        self._live: dict[str, LiveEpisode] = {}
        self._opening = 0

    def __len__(self) -> int:
        """Live episodes (expired ones included until the next sweep)."""
        return len(self._live)

    def sweep(self) -> list[str]:
        """Drop every episode idle for more than ``ttl_s`` with no request in flight.

        Returns:
            The ids dropped.
        """
        now = self.clock()
        gone = [i for i, e in self._live.items() if not e.active and now - e.used > self.ttl_s]
        for i in gone:
            del self._live[i]
        return gone

    @contextmanager
    def opening(self) -> Iterator[Callable[[LiveEpisode], None]]:
        """Hold a place for an episode being made; yields the function that adds it once started.

        Yields:
            ``add(live)``: store the episode (stamped as used now).

        Raises:
            EpisodesFull: ``capacity`` episodes are live or being made (``Retry-After``: until the next idle one
                expires).
        """
        self.sweep()
        if len(self._live) + self._opening >= self.capacity:
            now = self.clock()
            idle = [e.used + self.ttl_s - now for e in self._live.values() if not e.active]
            wait = max(1, math.ceil(min(idle, default=self.ttl_s)))
            raise EpisodesFull(f"episode store full: this server holds at most {self.capacity} (max_episodes); "
                               f"DELETE finished ones, or retry after {wait} s (an episode idle for {self.ttl_s:g} s "
                               f"is dropped)",
                               {"Retry-After": str(wait)})
        self._opening += 1

        def add(live: LiveEpisode) -> None:
            live.used = self.clock()
            self._live[live.id] = live

        try:
            yield add
        finally:
            self._opening -= 1

    @contextmanager
    def using(self, episode_id: str) -> Iterator[LiveEpisode]:
        """The live episode ``episode_id`` for one request: never expired while in use, stamped at both ends.

        Args:
            episode_id: from ``POST /episodes``.

        Yields:
            The episode.

        Raises:
            UnknownEpisode: no such live episode.
        """
        self.sweep()
        live = self._live.get(episode_id)
        if live is None:
            raise UnknownEpisode(f"no episode {episode_id!r}: it never existed, was deleted, or expired after "
                                 f"{self.ttl_s:g} s without a request")
        live.active += 1
        live.used = self.clock()
        try:
            yield live
        finally:
            live.active -= 1
            live.used = self.clock()

    def delete(self, episode_id: str) -> None:
        """Drop an episode (a step in flight still finishes; its episode is then gone).

        Args:
            episode_id: from ``POST /episodes``.

        Raises:
            UnknownEpisode: no such live episode.
        """
        with self.using(episode_id):
            del self._live[episode_id]
