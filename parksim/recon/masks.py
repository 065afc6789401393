"""Per-camera pixel masks: which pixels show the scene (inside the lens circle, not the ego car's body)."""

from __future__ import annotations

import torch
from torch import Tensor

from parksim.camera import pixel_grid
from parksim.rig import BEVSpec, RigCamera

__all__ = ["scene_mask", "EGO_MIN_PATH"]

EGO_MIN_PATH = 0.15
"""A ray that runs this far (m) inside the ego box sees the car (cameras sit on the box's surface)."""


def _path_inside_box(origin: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Length of each unit ray ``origin + t dirs`` (t >= 0) inside the axis-aligned box [lo, hi] (slab method)."""
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0, t1 = (lo - origin) / safe, (hi - origin) / safe
    t_enter = torch.minimum(t0, t1).amax(dim=-1).clamp(min=0.0)
    t_exit = torch.maximum(t0, t1).amin(dim=-1)
    return (t_exit - t_enter).clamp(min=0.0)


def scene_mask(camera: RigCamera, bev: BEVSpec | None) -> Tensor:
    """Bool ``[H, W]``: pixel inside the lens' valid circle and its ray not blocked by the ego body.

    The body is the BEV spec's ``ego_box`` footprint from the ground up to the camera's height; a camera
    inside the (padded) footprint has the nearest side face moved onto it, so it looks out of the body.
    """
    model = camera.model
    uv = pixel_grid(model.width, model.height)
    valid = model.pixel_valid(uv)
    if bev is None or bev.ego_box is None:
        return valid
    T = camera.T_vehicle_camera
    dirs = model.unproject(uv) @ T[:3, :3].T
    origin = T[:3, 3]
    x0, x1, y0, y1 = bev.ego_box
    lo = torch.tensor([x0, y0, 0.0], dtype=torch.float64)
    hi = torch.tensor([x1, y1, float(origin[2])], dtype=torch.float64)
    inside = bool(((origin[:2] > lo[:2]) & (origin[:2] < hi[:2])).all())
    if inside:
        gaps = torch.cat([origin[:2] - lo[:2], hi[:2] - origin[:2]])
        face = int(gaps.argmin())
        (lo if face < 2 else hi)[face % 2] = origin[face % 2]
    return valid & (_path_inside_box(origin, dirs, lo, hi) < EGO_MIN_PATH)
