"""Small real scene bundles for the simulator tests and benchmark: Gaussians on a synthetic garage's surfaces.

A bundle here is what ``parksim reconstruct`` would write, built without training: the preset's
rig and world map, and flat Gaussians sampled on the floor, ceiling, pillars, walls and parked
cars, coloured by the synthetic garage's shader (slot lines included), so renders look like the garage.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from parksim.bench.scenes import surface_bundle, surface_scene
from parksim.gaussians import GaussianScene

__all__ = ["make_bundle", "garage_scene", "running_server", "easy_scenario"]


def garage_scene(preset: str = "tiny", n: int = 3000, seed: int = 0) -> tuple[GaussianScene, dict]:
    """``n`` surface Gaussians of the preset's garage and its world map (``parksim.bench.scenes.surface_scene``)."""
    return surface_scene(preset, n, seed)


def make_bundle(out: str | Path, preset: str = "tiny", n: int = 3000, seed: int = 0,
                size: tuple[int, int] | None = None, bev_px: int | None = None) -> Path:
    """Write a bundle folder (gaussians.ply, rig.json, map.json, bundle.json) of ``garage_scene``'s Gaussians,
    spatially sorted as ``parksim reconstruct`` stores them (``parksim.bench.scenes.surface_bundle``); ``size`` /
    ``bev_px`` override the preset's."""
    return surface_bundle(Path(out), preset, n, seed, size, bev_px)


@contextlib.contextmanager
def running_server(app: Any) -> Iterator[str]:
    """Serve ``app`` with uvicorn on a free 127.0.0.1 port in a thread; yields the base URL, stops on exit."""
    import uvicorn

    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start within 30 s")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()


def easy_scenario(sim: Any, seed: int, name: str = "easy", actors: tuple = ()) -> Any:
    """A scenario on ``sim``'s scene (a ``LocalSim``): the env's random start of ``seed``, the slot Hybrid A* picks
    from it as the target, and ``actors``."""
    from parksim.env import ParkingEnv
    from parksim.planners import HybridAStarParker
    from parksim.scenarios import Scenario
    from parksim.scenarios.spec import EgoStart

    plain = ParkingEnv(sim=sim, cameras=[], privileged=True)
    obs, _ = plain.reset(seed=seed)
    start = tuple(float(v) for v in obs["pose"])
    slot_id, _ = HybridAStarParker().choose_slot(start, plain.world_map)
    return Scenario(name=name, scene=sim.id, ego=EgoStart(pose=start), target=slot_id, actors=actors)
