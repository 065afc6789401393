"""Per-region visibility: a grid over the drivable area, each cell listing the Gaussians seen from it.

Written by ``parksim compact`` (``visibility.npz`` in a bundle) and read by ``LocalSim``, which then
renders only the cell's Gaussians for a planar pose (z = 0, level) whose rear axle lies in a measured
cell; any other pose renders them all. Cell (i, j) covers ``x0 + i*cell <= x < x0 + (i+1)*cell`` and the
same along y; its Gaussians are ``indices[offsets[c]:offsets[c + 1]]`` with ``c = i * ny + j``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["VisibilityGrid", "PLANAR_TOL"]

PLANAR_TOL = 1e-6
"""A pose is planar (the kind the grid was measured at) when z, roll and pitch are within this of 0."""


@dataclass(frozen=True)
class VisibilityGrid:
    """Cells of ``cell`` m from ``(x0, y0)``, ``nx`` by ``ny``; ``measured[c]`` False means: render everything."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    offsets: np.ndarray   # [nx*ny + 1] int64
    indices: np.ndarray   # [offsets[-1]] int32, ascending within a cell
    measured: np.ndarray  # [nx*ny] bool

    def __post_init__(self) -> None:
        n = self.nx * self.ny
        if self.offsets.shape != (n + 1,) or self.measured.shape != (n,) or self.offsets[-1] != len(self.indices):
            raise ValueError(f"visibility grid: {self.nx}x{self.ny} cells do not match offsets "
                             f"{self.offsets.shape}, measured {self.measured.shape} and {len(self.indices)} indices")
        if not (math.isfinite(self.cell) and self.cell > 0):
            raise ValueError(f"visibility grid: cell size must be positive, got {self.cell}")

    def cell_of(self, x: float, y: float) -> int | None:
        """Index of the measured cell containing (x, y), or None (outside the grid or not measured)."""
        i, j = math.floor((x - self.x0) / self.cell), math.floor((y - self.y0) / self.cell)
        if not (0 <= i < self.nx and 0 <= j < self.ny):
            return None
        c = i * self.ny + j
        return c if self.measured[c] else None

    def members(self, c: int) -> np.ndarray:
        """Indices of the Gaussians visible from cell ``c``."""
        return self.indices[self.offsets[c]:self.offsets[c + 1]]

    def check(self, n_gaussians: int) -> None:
        """Raise ValueError when an index does not name one of ``n_gaussians`` Gaussians."""
        if len(self.indices) and (self.indices.min() < 0 or self.indices.max() >= n_gaussians):
            raise ValueError(f"visibility grid names Gaussians outside 0..{n_gaussians - 1}")

    def save(self, path: str | Path) -> None:
        """Write an uncompressed ``.npz`` (``path`` must end in .npz)."""
        np.savez(path, origin=np.array([self.x0, self.y0]), cell=np.array(self.cell),
                 shape=np.array([self.nx, self.ny]), offsets=self.offsets, indices=self.indices, measured=self.measured)

    @classmethod
    def load(cls, path: str | Path) -> VisibilityGrid:
        """Read a grid written by ``save``; a malformed file raises ValueError."""
        try:
            with np.load(path, allow_pickle=False) as z:
                return cls(float(z["origin"][0]), float(z["origin"][1]), float(z["cell"]), int(z["shape"][0]),
                           int(z["shape"][1]), z["offsets"].astype(np.int64), z["indices"].astype(np.int32),
                           z["measured"].astype(bool))
        except (OSError, KeyError, IndexError, TypeError, ValueError) as e:
            raise ValueError(f"{path}: unreadable visibility grid ({e})") from None
