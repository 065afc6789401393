"""DMPR-PS slot labels of one frame, in BEV pixels: marking points and slots visible in that BEV.

Marking point: ``x, y`` (BEV pixels, centres at integers), ``direction`` (rad, in the image:
``atan2(dv, du)``, pointing along the separator into the slot) and ``shape`` ("T" or "L").
Slot: ``p1, p2`` (indices into this frame's marks; the slot lies on the right of p1 -> p2 as
the BEV image is viewed), ``type`` and ``angle`` (deg). A point is labelled only when it is
inside the BEV, outside the masked ego area, and the cameras the IPM takes it from actually
see it (ray cast: not hidden behind a car or pillar); a slot only when both of its points are.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from ..rig import BEVSpec
from .garage import Garage
from .raycast import BoxSet, trace_world

__all__ = ["frame_labels", "VISIBLE_WEIGHT"]

VISIBLE_WEIGHT = 0.3
"""Share of the IPM blend weight that must come from cameras with a clear view of a point. The BEV pixel is a
weighted mean, so the paint keeps this share of its contrast: a third is plainly visible (points beside the ego,
where the front or rear camera sees its own body, showed at 35-77 % clear share and went unlabelled at 0.8)."""
_OCCLUSION_TOL = 0.03  # m: a hit this much before the point means something hides it


def _seen(point: np.ndarray, cam_origins: Mapping[str, np.ndarray], weights: Mapping[str, float],
          boxes: BoxSet, ceiling: float) -> bool:
    """Whether the cameras that carry most of the IPM weight at a floor point see it unoccluded."""
    total = sum(weights.values())
    if total <= 0:
        return False
    clear = 0.0
    for name, w in weights.items():
        if w <= 0:
            continue
        o = cam_origins[name]
        ray = point - o
        dist = float(np.linalg.norm(ray))
        hit = trace_world(o, (ray / dist)[None], boxes, ceiling)
        if hit.t[0] >= dist - _OCCLUSION_TOL:
            clear += w
    return clear >= VISIBLE_WEIGHT * total


def frame_labels(garage: Garage, pose: np.ndarray, spec: BEVSpec, ipm_weights: Mapping[str, np.ndarray],
                 ipm_mask: np.ndarray, cam_origins: Mapping[str, np.ndarray], boxes: BoxSet) -> dict[str, Any]:
    """Labels of the frame at ``pose`` (T_world_vehicle); ``ipm_weights``/``ipm_mask`` are the IPM's."""
    R, t = pose[:3, :3], pose[:3, 3]
    world = np.array([[m.x, m.y, 0.0] for m in garage.marks]).reshape(-1, 3)
    vehicle = (world - t) @ R
    uv = spec.ground_to_pixel(torch.from_numpy(vehicle[:, :2])).numpy()
    marks: list[dict[str, Any]] = []
    index: dict[int, int] = {}
    for i, (m, (u, v)) in enumerate(zip(garage.marks, uv)):
        if not (0 <= u <= spec.width - 1 and 0 <= v <= spec.height - 1):
            continue
        r, c = int(round(v)), int(round(u))
        if not ipm_mask[r, c]:
            continue
        weights = {n: float(w[r, c]) for n, w in ipm_weights.items()}
        if not _seen(world[i], cam_origins, weights, boxes, garage.height):
            continue
        d_world = np.array([math.cos(m.direction), math.sin(m.direction), 0.0])
        dx, dy = (d_world @ R)[:2]  # vehicle frame
        index[i] = len(marks)
        marks.append({"x": float(u), "y": float(v), "direction": math.atan2(-dx, -dy), "shape": m.shape,
                      "id": i})
    slots = [{"p1": index[s.p1], "p2": index[s.p2], "type": s.kind, "angle": s.angle_deg,
              "occupied": s.occupied, "id": j}
             for j, s in enumerate(garage.slots) if s.p1 in index and s.p2 in index]
    return {"bev": {"width": spec.width, "height": spec.height, "m_per_px": spec.m_per_px},
            "marks": marks, "slots": slots}
