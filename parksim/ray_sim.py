"""``RaySim``: one ``LocalSim`` in a Ray actor (on a GPU when it reserves one), shared by every env that names it.

Vector envs on many nodes, or many vector envs in one process, can then step their cars where they are and send
every pose of a step to one GPU in one call (``LocalSim.render_batch``: one kernel launch for all their cameras)
instead of each env loading the bundle and rendering alone. The actor is found by name, so a second ``RaySim``
with the same ``name`` shares the first's actor (and its loaded scene) rather than starting another.
``RaySim`` answers what ``ParkingEnv`` and ``BatchRenderVectorEnv`` ask of a frame source: ``info``, ``cameras``,
``render`` and ``render_batch``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .frames import Frame

__all__ = ["RaySim", "SimHost"]


class SimHost:
    """The actor's side: a ``LocalSim`` on the device the actor resolves (its reserved GPU, if any)."""

    def __init__(self, bundle: str, device: str) -> None:
        from .sim import LocalSim

        self.sim = LocalSim.from_dir(bundle, device=device)

    def info(self) -> dict[str, Any]:
        """``LocalSim.info`` plus the device the scene renders on."""
        return {**self.sim.info(), "device": str(self.sim.device)}

    def render_batch(self, poses: list[list[float]], cameras: list[str] | None, bev: bool, scale: float,
                     depth: bool) -> list[Frame]:
        """``LocalSim.render_batch``."""
        return self.sim.render_batch(poses, cameras, bev, scale, depth)


class RaySim:
    """A frame source whose renders run in a (shared) Ray actor holding the bundle."""

    def __init__(self, bundle: str | Path, device: str = "auto", gpus: float = 0.0, cpus: float = 1.0,
                 name: str | None = None) -> None:
        """Start the actor, or join the one called ``name``.

        Args:
            bundle: a bundle folder every node of the cluster can read.
            device: where the actor renders (``parksim.device``), resolved on its node.
            gpus: GPUs the actor reserves (a fraction shares one); Ray shows it only those.
            cpus: CPUs the actor reserves.
            name: share the actor of this name (started here when there is none).

        Raises:
            ValueError: a bad ``device`` (checked in the actor; a GPU the node lacks included).
        """
        import ray

        options: dict[str, Any] = {"num_gpus": gpus, "num_cpus": cpus}
        if name is not None:
            options.update(name=name, get_if_exists=True)
        host: Any = ray.remote(SimHost).options(**options)   # Ray's actor typing does not follow .options()
        self._ray, self.actor = ray, host.remote(str(bundle), device)
        try:
            self._info: dict[str, Any] = ray.get(self.actor.info.remote())
        except ray.exceptions.RayActorError as err:   # the actor's __init__ raised (bad device, bad bundle)
            raise ValueError(f"RaySim: the render actor did not start: {str(err.__cause__ or err).splitlines()[-1]}"
                             ) from None
        self.id: str = self._info["id"]
        self.cameras: list[str] = list(self._info["cameras"])
        self.device: str = self._info["device"]

    def info(self) -> dict[str, Any]:
        """``LocalSim.info`` of the actor's scene (fetched once).

        Returns:
            The scene's info, with ``device``.
        """
        return self._info

    def render(self, pose: Sequence[float], cameras: Sequence[str] | None = None, bev: bool = False,
               scale: float = 1.0, depth: bool = False) -> Frame:
        """``LocalSim.render`` in the actor.

        Args:
            pose: as ``LocalSim.render``.
            cameras: as ``LocalSim.render``.
            bev: as ``LocalSim.render``.
            scale: as ``LocalSim.render``.
            depth: as ``LocalSim.render``.

        Returns:
            The frame.
        """
        return self.render_batch([pose], cameras, bev, scale, depth)[0]

    def render_batch(self, poses: Sequence[Sequence[float]], cameras: Sequence[str] | None = None, bev: bool = False,
                     scale: float = 1.0, depth: bool = False) -> list[Frame]:
        """``LocalSim.render_batch`` in the actor: every pose in one call.

        Args:
            poses: as ``LocalSim.render_batch``.
            cameras: as ``LocalSim.render_batch``.
            bev: as ``LocalSim.render_batch``.
            scale: as ``LocalSim.render_batch``.
            depth: as ``LocalSim.render_batch``.

        Returns:
            One frame per pose.
        """
        names = list(cameras) if cameras is not None else None
        return list(self._ray.get(self.actor.render_batch.remote([list(p) for p in poses], names, bev, scale,
                                                                 depth)))
