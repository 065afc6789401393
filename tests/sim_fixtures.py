"""Small real scene bundles for the simulator tests and benchmark: Gaussians on a synthetic garage's surfaces.

A bundle here is what ``parksim reconstruct`` would write, built without training: the preset's
rig and world map, and flat Gaussians sampled on the floor, ceiling, pillars, walls and parked
cars, coloured by the synthetic garage's shader (slot lines included), so renders look like the garage.
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from parksim import bundle as bundle_io
from parksim.gaussians import SH_C0, GaussianScene
from parksim.geometry import quaternion_from_rotation
from parksim.synth.generate import scene_map
from parksim.synth.layout import build_garage
from parksim.synth.points import sample_points
from parksim.synth.presets import get_preset
from parksim.synth.raycast import BoxSet
from parksim.synth.rig import avm_rig, ego_box
from parksim.synth.shading import Shader

__all__ = ["make_bundle", "garage_scene", "running_server"]


def _frames_from_normals(normals: np.ndarray) -> torch.Tensor:
    """Rotations whose third axis is each unit normal (the flat axis of a surface Gaussian)."""
    n = torch.from_numpy(normals / np.linalg.norm(normals, axis=1, keepdims=True))
    helper = torch.where(n[:, 2:3].abs() < 0.9, torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype),
                         torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype))
    a = torch.linalg.cross(helper, n)
    a = a / a.norm(dim=1, keepdim=True)
    b = torch.linalg.cross(n, a)
    return torch.stack([a, b, n], dim=2)


def garage_scene(preset: str = "tiny", n: int = 3000, seed: int = 0) -> tuple[GaussianScene, dict]:
    """``n`` surface Gaussians of the preset's garage and its world map (``scene_map``)."""
    layout = get_preset(preset).layout
    garage = build_garage(layout)
    boxes = BoxSet.from_boxes([*garage.boxes, ego_box(np.eye(4))])
    materials = [b.material for b in garage.boxes] + ["ego"]
    colors = np.array([b.color for b in garage.boxes] + [(0.16, 0.17, 0.19)])
    shader = Shader(garage, boxes, materials, colors, layout.seed)
    span = np.stack([np.eye(4), np.eye(4)])
    span[1, 0, 3] = garage.length
    xyz, rgb, normals = sample_points(garage, shader, boxes, materials, span, n, seed, noise=0.005)
    area = garage.length * (garage.y_max - garage.y_min) * 2.6
    sigma = 0.7 * math.sqrt(area / n)
    log_scales = torch.tensor([math.log(sigma), math.log(sigma), math.log(0.01)]).expand(n, 3).clone()
    sh = ((torch.from_numpy(rgb).double() / 255.0 - 0.5) / SH_C0)[:, None, :]
    scene = GaussianScene(torch.from_numpy(xyz), quaternion_from_rotation(_frames_from_normals(normals)),
                          log_scales.double(), torch.full((n,), 2.5, dtype=torch.float64), sh, 0)
    return scene.to(torch.float32), scene_map(garage)


def make_bundle(out: str | Path, preset: str = "tiny", n: int = 3000, seed: int = 0,
                size: tuple[int, int] | None = None, bev_px: int | None = None) -> Path:
    """Write a bundle folder (gaussians.ply, rig.json, map.json, bundle.json).

    ``size``/``bev_px`` override the preset's. The Gaussians are stored spatially sorted, as ``parksim reconstruct``
    stores them."""
    p = get_preset(preset)
    width, height = size or (p.width, p.height)
    scene, world_map = garage_scene(preset, n, seed)
    rig = avm_rig(width, height, bev_px or p.bev_px)
    meta = {"source": f"synthetic garage {preset!r} (surface samples, not trained)", "gaussians": n}
    return bundle_io.save(out, bundle_io.Bundle(scene.spatially_sorted(), rig, world_map, meta))


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
