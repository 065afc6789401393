"""Ego poses to measure a scene from: random drivable poses in each cell of a grid over the garage floor.

Drivable means the car body (``parksim.vehicle``) lies inside the garage rectangle of the bundle's
``map.json`` and overlaps none of its obstacles (pillars, parked cars, walls). A cell's poses are drawn
from the cell grown by a margin, so that its visibility list also covers poses just across its border.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..vehicle import Obstacles, VehicleParams, footprint

__all__ = ["GridPoses", "garage_extent", "sample_grid_poses"]

_ATTEMPTS_PER_POSE = 20


@dataclass(frozen=True)
class GridPoses:
    """A grid of ``cell`` m cells from ``(x0, y0)``, ``nx`` by ``ny``, and poses ``(x, y, yaw)`` tagged by cell."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    poses: np.ndarray   # [P, 3] float64
    cells: np.ndarray   # [P] int64: the cell (i * ny + j) each pose was drawn for

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny


def garage_extent(world_map: dict[str, Any] | None) -> tuple[tuple[float, float], tuple[float, float]]:
    """((x_min, x_max), (y_min, y_max)) of the map's garage; ValueError when the bundle has no such map."""
    garage = (world_map or {}).get("garage")
    if not garage or "x" not in garage or "y" not in garage:
        raise ValueError("the bundle has no map.json with a garage extent: cannot sample drivable poses")
    (x0, x1), (y0, y1) = (tuple(map(float, garage[k])) for k in ("x", "y"))
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"map.json garage extent is empty: x {garage['x']}, y {garage['y']}")
    return (x0, x1), (y0, y1)


def _drivable(pose: np.ndarray, extent: tuple[tuple[float, float], tuple[float, float]], obstacles: Obstacles,
              vehicle: VehicleParams) -> bool:
    """The body at ``pose`` is inside the garage and touches no obstacle."""
    corners = footprint(pose, vehicle)
    (x0, x1), (y0, y1) = extent
    inside = (corners.min(axis=0) >= (x0, y0)).all() and (corners.max(axis=0) <= (x1, y1)).all()
    return bool(inside) and not obstacles.collides(pose, vehicle)


def sample_grid_poses(world_map: dict[str, Any] | None, cell: float, per_cell: int, margin: float, seed: int = 0,
                      vehicle: VehicleParams = VehicleParams()) -> GridPoses:
    """Up to ``per_cell`` drivable poses (uniform position in the cell grown by ``margin``, uniform yaw) per cell.

    Cells where no drivable pose turns up in ``20 * per_cell`` draws get none (nothing can stand there).
    """
    extent = garage_extent(world_map)
    (gx0, gx1), (gy0, gy1) = extent
    nx, ny = math.ceil((gx1 - gx0) / cell), math.ceil((gy1 - gy0) / cell)
    obstacles = Obstacles((world_map or {}).get("obstacles", []))
    rng = np.random.default_rng(seed)
    poses, cells = [], []
    for c in range(nx * ny):
        i, j = divmod(c, ny)
        lo = (max(gx0, gx0 + i * cell - margin), max(gy0, gy0 + j * cell - margin))
        hi = (min(gx1, gx0 + (i + 1) * cell + margin), min(gy1, gy0 + (j + 1) * cell + margin))
        found = 0
        for _ in range(_ATTEMPTS_PER_POSE * per_cell):
            pose = np.array([rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), rng.uniform(-math.pi, math.pi)])
            if _drivable(pose, extent, obstacles, vehicle):
                poses.append(pose)
                cells.append(c)
                found += 1
                if found == per_cell:
                    break
    return GridPoses(gx0, gy0, float(cell), nx, ny, np.array(poses, np.float64).reshape(-1, 3),
                     np.array(cells, np.int64))
