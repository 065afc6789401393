"""The synthetic ego car: a production-like AVM rig (four 190 deg fisheyes) and its body box.

Vehicle frame: origin on the ground under the rear axle, x forward, y left, z up. The
car is ``parksim.vehicle.VehicleParams`` (4.7 m x 1.8 m, 0.95 m rear overhang); the front camera sits in the
bumper, the rear one above the number plate, the side ones under the mirrors looking
down and out, as on a production surround-view system.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..camera import OpenCVFisheye
from ..geometry import make_transform
from ..rig import BEVSpec, Rig, RigCamera
from ..vehicle import VehicleParams
from .garage import Box

__all__ = ["avm_rig", "ego_box", "EGO_EXTENT", "CAR_CENTRE_X"]

EGO_EXTENT = VehicleParams().extent
"""Ego body footprint in the vehicle frame: (x_min, x_max, y_min, y_max)."""
CAR_CENTRE_X = 1.4
"""Vehicle-frame x of the car's centre (the BEV is centred there)."""
_K = [0.05, -0.01, 0.002, -0.0002]   # Kannala-Brandt k1..k4 of the 190 deg lens
_F_640 = 182.0                        # focal length (px) at 640 px width: the 190 deg circle spans the width

# name: (position, forward direction in the vehicle frame, principal point offset in px at 640 wide)
_MOUNTS = {
    "front": ((3.80, 0.0, 0.62), (math.cos(0.35), 0.0, -math.sin(0.35)), (1.8, -2.1)),
    "rear": ((-0.98, 0.0, 0.92), (-math.cos(0.45), 0.0, -math.sin(0.45)), (-1.2, 1.5)),
    "left": ((1.95, 1.02, 1.02), (0.0, math.cos(1.05), -math.sin(1.05)), (0.9, 1.1)),
    "right": ((1.95, -1.02, 1.02), (0.0, -math.cos(1.05), -math.sin(1.05)), (-1.4, 0.6)),
}


def _look(forward: tuple[float, float, float]) -> torch.Tensor:
    """Rotation vehicle<-camera for an OpenCV camera (x right, y down) looking along ``forward``, no roll."""
    z = np.asarray(forward, np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return torch.from_numpy(np.stack([x, y, z], axis=1))


def avm_rig(width: int = 640, height: int = 480, bev_px: int = 600) -> Rig:
    """Four-camera surround-view rig at ``width x height`` and a ``bev_px``-square BEV over 10 m x 10 m."""
    s = width / 640.0
    cams = {}
    for name, (pos, fwd, (dx, dy)) in _MOUNTS.items():
        model = OpenCVFisheye(width, height, _F_640 * s, _F_640 * s, (width - 1) / 2 + dx * s,
                              (height - 1) / 2 + dy * s, _K, max_fov_deg=190.0)
        T = make_transform(_look(fwd), torch.tensor(pos, dtype=torch.float64))
        cams[name] = RigCamera(name, model, T)
    x0, x1, y0, y1 = EGO_EXTENT
    bev = BEVSpec(bev_px, bev_px, 10.0 / bev_px, CAR_CENTRE_X, 0.0, (x0 - 0.1, x1 + 0.1, y0 - 0.1, y1 + 0.1))
    return Rig(cams, bev)


def ego_box(pose: np.ndarray) -> Box:
    """The ego body as a box in the world at ``pose`` (T_world_vehicle, 4x4)."""
    x0, x1, y0, y1 = EGO_EXTENT
    centre = pose[:3, :3] @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]) + pose[:3, 3]
    yaw = math.atan2(pose[1, 0], pose[0, 0])
    return Box(float(centre[0]), float(centre[1]), 0.22, 1.45, x1 - x0, y1 - y0, yaw, "ego", (0.16, 0.17, 0.19))
