"""Sparse initial point cloud: noisy samples of the garage's surfaces, coloured by the shader.

Stands in for an SfM point cloud: floor, box faces and ceiling around the driven path, with
a few centimetres of position noise, as 3DGS initialisation expects.
"""

from __future__ import annotations

import numpy as np

from .garage import Garage
from .raycast import CEILING, FLOOR, BoxSet, Hits
from .shading import Shader, to_srgb

__all__ = ["sample_points"]

_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


def _box_samples(boxes: BoxSet, keep: np.ndarray, n: int, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted samples on the side and top faces of the kept boxes: points, box index, face."""
    idx = np.nonzero(keep)[0]
    h = boxes.halves[idx]
    # faces 0..4 (+-x, +-y, +z): areas
    areas = np.stack([h[:, 1] * h[:, 2], h[:, 1] * h[:, 2], h[:, 0] * h[:, 2], h[:, 0] * h[:, 2], h[:, 0] * h[:, 1]], 1)
    flat = areas.reshape(-1) / areas.sum()
    pick = rng.choice(len(flat), size=n, p=flat)
    b, face = idx[pick // 5], pick % 5
    local = rng.uniform(-1, 1, (n, 3)) * boxes.halves[b]
    axis = face // 2
    sign = np.where(face % 2 == 0, 1.0, -1.0)
    local[np.arange(n), axis] = sign * boxes.halves[b, axis]
    c, s = boxes.yaw_cs[b, 0], boxes.yaw_cs[b, 1]
    world = np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], 1)
    return world + boxes.centres[b], b, face


def sample_points(garage: Garage, shader: Shader, boxes: BoxSet, materials: list[str], poses: np.ndarray,
                  n: int, seed: int, noise: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points within 12 m of the path: positions, uint8 colours and normals (world frame)."""
    rng = np.random.default_rng(seed + 13)
    lo = np.maximum(poses[:, :2, 3].min(0) - 12.0, [0.0, garage.y_min])
    hi = np.minimum(poses[:, :2, 3].max(0) + 12.0, [garage.length, garage.y_max])
    n_floor, n_ceil = n // 2, n // 10
    floor = np.column_stack([rng.uniform(lo, hi, (n_floor, 2)), np.zeros(n_floor)])
    ceil = np.column_stack([rng.uniform(lo, hi, (n_ceil, 2)), np.full(n_ceil, garage.height)])
    near = np.all((boxes.centres[:, :2] >= lo) & (boxes.centres[:, :2] <= hi), axis=1)
    solid = np.array([m not in ("ego", "fixture", "fixture_off") for m in materials])
    pts, b, face = _box_samples(boxes, near & solid, n - n_floor - n_ceil, rng)
    points = np.concatenate([floor, ceil, pts])
    prim = np.concatenate([np.full(n_floor, FLOOR), np.full(n_ceil, CEILING), b + 2]).astype(np.int32)
    faces = np.concatenate([np.full(n_floor, 4), np.full(n_ceil, 5), face]).astype(np.int8)
    hits = Hits(np.zeros(n), prim, faces, points, np.zeros((n, 3)))
    rgb = np.rint(to_srgb(1.25 * shader.radiance(hits, boxes)) * 255).astype(np.uint8)
    yaw_cs = np.where(prim[:, None] >= 2, boxes.yaw_cs[np.maximum(prim - 2, 0)], [1.0, 0.0])
    local_n = _NORMALS[faces]
    normals = np.stack([yaw_cs[:, 0] * local_n[:, 0] - yaw_cs[:, 1] * local_n[:, 1],
                        yaw_cs[:, 1] * local_n[:, 0] + yaw_cs[:, 0] * local_n[:, 1], local_n[:, 2]], 1)
    return points + rng.normal(0, noise, points.shape), rgb, normals
