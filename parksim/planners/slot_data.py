"""Training BEVs for the slot detector from a scene bundle: renders at random poses, labelled from its slot map.

The simulator's own BEVs (IPM of the bundle's rendered fisheye views) differ from the sharp ray-traced
BEVs of ``parksim synth``, so the perception planner's detector is trained on them. Each BEV is written
as a ps2.0-style pair (``NAME.png`` + ``NAME.json``, see ``parksim.recon.detectors.labels_ps2``), the format
``parksim detector train`` and ``parksim.recon.detectors.train.train_detector`` read. The labels are the map's
marking points and slots projected into the BEV, so this needs the map (offline, as any labelling does);
the planner that uses the trained detector sees only the rendered images.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..fileio import atomic_directory
from ..rig import BEVSpec
from ..sim import LocalSim
from ..vehicle import Obstacles, VehicleParams, wrap_angle

__all__ = ["training_poses", "bev_labels", "write_training_bevs"]

_PS2_METRES = 10.0
"""Side of a ps2.0 BEV in metres: the label format fixes it, so the bundle's BEV must cover the same."""


def training_poses(world_map: dict[str, Any], count: int, seed: int,
                   vehicle: VehicleParams = VehicleParams()) -> np.ndarray:
    """``count`` collision-free rear-axle poses (x, y, yaw): half on the aisles, half on a slot's axis, going in.

    Aisle poses face either way along the aisle; slot poses sit from 4 m before the entrance to 2 m past it,
    as the car is while it parks, so the detector sees slots beside, ahead and behind the masked ego.
    """
    rng = np.random.default_rng(seed)
    g, obstacles = world_map["garage"], Obstacles(world_map.get("obstacles", []))
    lanes = g.get("lanes") or [float(np.mean(g["y"]))]
    slots = world_map["slots"]
    poses: list[tuple[float, float, float]] = []
    while len(poses) < count:
        if len(poses) % 2 == 0:
            x, y = rng.uniform(g["x"][0] + 3.0, g["x"][1] - 3.0), float(rng.choice(lanes)) + rng.uniform(-0.8, 0.8)
            yaw = rng.uniform(-0.3, 0.3) + (math.pi if rng.random() < 0.5 else 0.0)
        else:
            c = np.asarray(slots[int(rng.integers(len(slots)))]["corners"], np.float64)
            entrance, axis = c[:2].mean(axis=0), c[2:].mean(axis=0) - c[:2].mean(axis=0)
            axis /= np.linalg.norm(axis)
            x, y = entrance + axis * rng.uniform(-4.0, 2.0) + rng.normal(0.0, 0.3, 2)
            yaw = math.atan2(axis[1], axis[0]) + rng.uniform(-0.5, 0.5)
        if not obstacles.collides((x, y, yaw), vehicle, margin=0.1):
            poses.append((float(x), float(y), float(wrap_angle(yaw))))
    return np.array(poses)


def bev_labels(world_map: dict[str, Any], pose: tuple[float, float, float], spec: BEVSpec) -> dict[str, list]:
    """The map's marking points and slots in the BEV at ``pose``, as a ps2.0 label dict (1-based pixels, indices).

    A point is kept when it lies inside the BEV and outside its masked ego box; a slot when both of its
    entrance points are kept. Directions become a second point 10 px along the separator, as ps2.0 stores them.
    """
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    marks: list[list[float]] = []
    index: dict[int, int] = {}
    for m in world_map["marks"]:
        dx, dy = m["x"] - x, m["y"] - y
        vx, vy = c * dx + s * dy, -s * dx + c * dy
        u, v = spec.ground_to_pixel(torch.tensor([vx, vy], dtype=torch.float64)).tolist()
        inside = 0 <= u <= spec.width - 1 and 0 <= v <= spec.height - 1
        box = spec.ego_box
        under_ego = box is not None and box[0] <= vx <= box[1] and box[2] <= vy <= box[3]
        if not inside or under_ego:
            continue
        d = m["direction"] - yaw                     # separator direction in the vehicle frame
        du, dv = -math.sin(d), -math.cos(d)          # vehicle (cos d, sin d) -> image (-dy, -dx)
        index[m["id"]] = len(marks) + 1
        marks.append([u + 1, v + 1, u + 1 + 10 * du, v + 1 + 10 * dv, 1 if m["shape"] == "L" else 0])
    slots = [[index[sl["p1"]], index[sl["p2"]], 1, sl["angle"]] for sl in world_map["slots"]
             if sl["p1"] in index and sl["p2"] in index]
    return {"marks": marks, "slots": slots}


def write_training_bevs(bundle: str | Path, out: str | Path, count: int, seed: int = 0, scale: float = 0.5) -> Path:
    """Render ``count`` BEVs of ``bundle`` (fisheye views at ``scale``) with their labels into the folder ``out``.

    Raises:
        ValueError: the bundle has no slot map, or its BEV does not span the 10 m the ps2.0 format assumes.
    """
    import cv2

    sim = LocalSim(bundle)
    world_map, spec = sim.bundle.map, sim.bundle.rig.bev
    if not world_map or not world_map.get("slots"):
        raise ValueError(f"{bundle}: the bundle has no slot map to label BEVs from")
    if not math.isclose(spec.width * spec.m_per_px, _PS2_METRES) or spec.width != spec.height:
        raise ValueError(f"{bundle}: the BEV must be square and {_PS2_METRES:g} m wide for ps2.0 labels, "
                         f"got {spec.width}x{spec.height} px at {spec.m_per_px} m/px")
    with atomic_directory(out) as tmp:
        for i, pose in enumerate(training_poses(world_map, count, seed)):
            bev = sim.render(tuple(pose), [], bev=True, scale=scale).bev
            assert bev is not None  # asked for
            cv2.imwrite(str(tmp / f"{i:05d}.png"), bev[..., ::-1])
            (tmp / f"{i:05d}.json").write_text(json.dumps(bev_labels(world_map, tuple(pose), spec)))
    return Path(out)
