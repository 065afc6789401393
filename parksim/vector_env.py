"""Vector ``ParkSim-v0`` envs past one process: sub-envs in Ray actors, or one batched render request per step.

``RayVectorEnv`` runs each ``ParkingEnv`` in its own Ray actor (each loads the bundle and renders itself, on any
node of the cluster); ``BatchRenderVectorEnv`` steps every car in this process and renders all their poses at
once: in one ``POST /render`` to ``parksim serve`` or its Ray Serve deployment, or, given a bundle, in one
in-process ``LocalSim.render_batch`` (on a GPU: one kernel launch for every car's cameras). Both autoreset on the
step after an episode ends (gymnasium's next-step mode) and truncate at ``max_episode_steps`` as ``TimeLimit`` does,
or at a scenario's time limit (``scenario=``: each sub-env draws its scenarios with its own seed).
``make_vector_env`` is the registration's ``vector_entry_point``: ``gym.make_vec("ParkSim-v0", num_envs=N, ...)``.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array

from .client import RemoteSim
from .env import ParkingEnv
from .frames import Frame

if TYPE_CHECKING:
    from .ray_sim import RaySim
    from .sim import LocalSim

__all__ = ["RayVectorEnv", "BatchRenderVectorEnv", "EnvHost", "make_vector_env", "BACKENDS"]

BACKENDS = ("ray", "batch")
"""``make_vector_env`` backends: sub-envs in Ray actors, or in this process with one batch render per step."""

Call = tuple[str, Any, Any]
"""What one sub-env does in a vector step: ``("reset", seed, options)`` or ``("step", action, None)``."""
Outcome = tuple[dict[str, np.ndarray], float, bool, dict[str, Any]]
"""(observation, reward, terminated, info) of one ``Call``."""


def _begin_or_advance(env: ParkingEnv, call: Call) -> tuple[float, bool, dict[str, Any]]:
    """Run ``call`` on ``env`` up to (not including) rendering: (reward, terminated, info); a reset scores 0."""
    kind, arg, options = call
    if kind == "reset":
        return 0.0, False, env.begin(arg, options)
    return env.advance(arg)


class EnvHost:
    """One ``ParkingEnv`` living in a Ray actor's process (``ray.remote(EnvHost)``), driven by ``Call``s."""

    def __init__(self, env_kwargs: dict[str, Any]) -> None:
        self.env = ParkingEnv(**env_kwargs)

    def spaces(self) -> tuple[spaces.Space[Any], spaces.Space[Any]]:
        """The env's (observation space, action space)."""
        return self.env.observation_space, self.env.action_space

    def run(self, call: Call) -> Outcome:
        """Reset or step the env and render its views here."""
        reward, terminated, info = _begin_or_advance(self.env, call)
        return self.env.observe(self.env.frame()), reward, terminated, info


class _ParkVectorEnv(VectorEnv, abc.ABC):
    """Batching, seeding, next-step autoreset and ``max_episode_steps`` truncation; subclasses run the calls."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP}

    def _setup(self, num_envs: int, single: tuple[spaces.Space[Any], spaces.Space[Any]],
               max_episode_steps: int | None) -> None:
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = single
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.max_episode_steps = max_episode_steps
        self._steps = np.zeros(num_envs, np.int64)
        self._ended = np.zeros(num_envs, bool)

    @abc.abstractmethod
    def _run(self, calls: Sequence[Call]) -> list[Outcome]:
        """Run one call per sub-env, in order, and return their outcomes."""

    def _batch(self, outcomes: list[Outcome]) -> tuple[Any, dict[str, Any]]:
        out: Any = create_empty_array(self.single_observation_space, self.num_envs)   # a Dict space: a dict
        obs = concatenate(self.single_observation_space, [o[0] for o in outcomes], out)
        infos: dict[str, Any] = {}
        for i, outcome in enumerate(outcomes):
            infos = self._add_info(infos, outcome[3], i)
        return obs, infos

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
              ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-env; an int ``seed`` seeds sub-env i with ``seed + i`` (as gymnasium's vector envs)."""
        seeds = ([None] * self.num_envs if seed is None else [seed + i for i in range(self.num_envs)]
                 if isinstance(seed, int) else list(seed))
        if len(seeds) != self.num_envs:
            raise ValueError(f"reset got {len(seeds)} seeds for {self.num_envs} envs")
        super().reset(seed=seeds[0])
        outcomes = self._run([("reset", s, options) for s in seeds])
        self._steps[:], self._ended[:] = 0, False
        return self._batch(outcomes)

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every sub-env; one whose episode ended on the previous step is reset instead (reward 0, no end).

        A batch holding a NaN or an infinity is refused (``ValueError``) before any sub-env moves.
        """
        acts = np.asarray(actions, np.float64).reshape(self.num_envs, *self.single_action_space.shape or ())
        bad = np.flatnonzero(~np.isfinite(acts.reshape(self.num_envs, -1)).all(axis=1))
        if bad.size:
            raise ValueError(f"actions of sub-envs {bad.tolist()} ({acts[bad].tolist()}) have a non-finite value "
                             "(NaN or inf): the batch is refused, no sub-env's state changed")
        calls: list[Call] = [("reset", None, None) if self._ended[i] else ("step", acts[i], None)
                             for i in range(self.num_envs)]
        outcomes = self._run(calls)
        self._steps = np.where(self._ended, 0, self._steps + 1)
        rewards = np.array([o[1] for o in outcomes], np.float64)
        terminated = np.array([o[2] for o in outcomes], bool)
        limit = self.max_episode_steps
        truncated = ~self._ended & (self._steps >= limit) if limit is not None else np.zeros(self.num_envs, bool)
        out_of_time = np.array([bool(o[3].get("truncated", False)) for o in outcomes])   # a scenario's time limit
        truncated |= out_of_time & ~terminated
        self._ended = terminated | truncated
        obs, infos = self._batch(outcomes)
        return obs, rewards, terminated, truncated, infos


class RayVectorEnv(_ParkVectorEnv):
    """``num_envs`` ``ParkingEnv``s, each in its own Ray actor; a step runs them all at once.

    Uses the running Ray instance (Ray starts a local one when none is). ``actor_options`` go to
    ``ray.remote(...).options`` (default: one thread each for torch and numba, as renders here run side by
    side). Frame sources must be picklable: ``bundle=`` a path every node can read, or ``server=``. ``device=`` goes
    to each actor's env, which resolves it on its node: Ray shows an actor only the GPUs it reserves, so ask for
    ``{"num_gpus": ...}`` in ``actor_options`` to render there on a GPU."""

    def __init__(self, num_envs: int, max_episode_steps: int | None = None,
                 actor_options: dict[str, Any] | None = None, **env_kwargs: Any) -> None:
        import ray

        if env_kwargs.get("sim") is not None:
            raise ValueError("RayVectorEnv cannot ship sim= to its actors: give bundle= (a path) or server=")
        options = actor_options if actor_options is not None else {
            "runtime_env": {"env_vars": {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}}}
        host: Any = ray.remote(EnvHost).options(**options)   # Ray's actor typing does not follow .options()
        self._ray = ray
        self.actors: list[Any] = [host.remote(env_kwargs) for _ in range(num_envs)]
        observation_space, action_space = ray.get(self.actors[0].spaces.remote())
        self._setup(num_envs, (observation_space, action_space), max_episode_steps)

    def _run(self, calls: Sequence[Call]) -> list[Outcome]:
        return list(self._ray.get([a.run.remote(c) for a, c in zip(self.actors, calls)]))

    def close_extras(self, **kwargs: Any) -> None:
        """End the actors (the Ray instance stays up: its owner shuts it down; a shut-down one took them along)."""
        if self._ray.is_initialized():
            for actor in self.actors:
                self._ray.kill(actor)


class BatchRenderVectorEnv(_ParkVectorEnv):
    """``num_envs`` ``ParkingEnv``s in this process sharing one simulator: each step renders every pose at once,
    in one ``POST /render`` to ``server`` (``parksim serve`` or its Ray Serve deployment) or, with ``bundle``, in
    one ``LocalSim.render_batch`` on ``device``: in this process, or with ``render_actor`` in a Ray actor
    (``RaySim``) reserving ``render_gpus`` GPUs, shared by every vector env that gives the same actor name. With
    ``scenario=`` each car's views are rendered on their own, with its scenario's actors drawn in."""

    def __init__(self, num_envs: int, server: str | None = None, scene: str | None = None,
                 api_key: str | None = None, max_episode_steps: int | None = None, bundle: Any = None,
                 device: str | None = None, render_actor: str | bool | None = None, render_gpus: float = 0.0,
                 render_cpus: float = 1.0, **env_kwargs: Any) -> None:
        if (server is None) == (bundle is None):
            raise ValueError("BatchRenderVectorEnv renders through a server or a bundle: give server=<URL> or "
                             "bundle=<folder>, not both")
        if render_actor and server is not None:
            raise ValueError("render_actor= renders a bundle in a Ray actor: give bundle=, not server=")
        if render_actor:
            from .ray_sim import RaySim

            name = render_actor if isinstance(render_actor, str) else None
            self.sim: RemoteSim | LocalSim | RaySim = RaySim(bundle, device or "auto", render_gpus, render_cpus, name)
        elif server is None:
            from .sim import LocalSim

            self.sim = LocalSim(bundle, device=device or "auto")
        else:
            if device not in (None, "auto"):
                raise ValueError(f"device={device!r} applies to bundle= only: a server renders on its own device")
            self.sim = RemoteSim(server, scene=scene, api_key=api_key)
        self.envs = [ParkingEnv(sim=self.sim, **env_kwargs) for _ in range(num_envs)]
        first = self.envs[0]
        self._setup(num_envs, (first.observation_space, first.action_space), max_episode_steps)

    def _frames(self) -> list[Frame | None]:
        first = self.envs[0]
        if not first.renders:
            return [None] * self.num_envs
        if first.scenarios:   # each car sees its own scenario's actors; a batch render draws one set at every pose
            return [env.frame() for env in self.envs]
        return list(self.sim.render_batch([e.state.pose for e in self.envs], first.cameras, first.bev, first.scale))

    def _run(self, calls: Sequence[Call]) -> list[Outcome]:
        done = [_begin_or_advance(env, call) for env, call in zip(self.envs, calls)]
        return [(env.observe(frame), reward, terminated, info)
                for env, frame, (reward, terminated, info) in zip(self.envs, self._frames(), done)]

    def close_extras(self, **kwargs: Any) -> None:
        """Close the HTTP client (an in-process simulator holds nothing to close)."""
        if isinstance(self.sim, RemoteSim):
            self.sim.close()


def make_vector_env(num_envs: int, backend: str = "ray", max_episode_steps: int | None = None,
                    **kwargs: Any) -> RayVectorEnv | BatchRenderVectorEnv:
    """``vector_entry_point`` of ``ParkSim-v0``: ``backend="ray"`` (``RayVectorEnv``) or ``"batch"``
    (``BatchRenderVectorEnv``, needs ``server=`` or ``bundle=``); the other keywords go to ``ParkingEnv``."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if num_envs < 1:
        raise ValueError(f"num_envs must be at least 1, got {num_envs}")
    if backend == "ray":
        return RayVectorEnv(num_envs, max_episode_steps=max_episode_steps, **kwargs)
    if kwargs.get("server") is None and kwargs.get("bundle") is None:
        raise ValueError("backend='batch' renders through a server or a bundle: give server=<URL> or bundle=<folder>")
    return BatchRenderVectorEnv(num_envs, max_episode_steps=max_episode_steps, **kwargs)
