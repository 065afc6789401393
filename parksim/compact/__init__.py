"""Scene compaction (``parksim compact``): fewer Gaussians, fewer SH bands, and per-region visibility for serving.

Poses are sampled in the drivable area of the bundle's map (``poses``), each Gaussian's largest blending
weight is measured per grid cell (``measure``), and the scene is reduced from those weights (``reduce``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ..bundle import Bundle
from .measure import cell_weights, pose_weights
from .poses import GridPoses, sample_grid_poses
from .reduce import budget_count, check_budget, lower_sh, select, sh_change_bound, visibility_grid

__all__ = ["CompactOptions", "compact_bundle", "measure_bundle", "reduce_bundle", "pose_weights", "cell_weights",
           "sample_grid_poses", "GridPoses", "check_budget", "budget_count", "select", "lower_sh", "sh_change_bound",
           "visibility_grid"]


@dataclass(frozen=True)
class CompactOptions:
    """What ``compact_bundle`` keeps: see ``parksim compact --help`` for each field's meaning."""

    budget: float = 1.0
    cell_budget: float = 1.0
    min_weight: float = 0.0
    sh_tolerance: float = 0.01
    cell: float = 4.0
    per_cell: int = 16
    margin: float = 1.0
    seed: int = 0
    visibility: bool = True

    def __post_init__(self) -> None:
        check_budget(self.budget)
        check_budget(self.cell_budget, "cell budget")
        for name in ("min_weight", "sh_tolerance", "margin"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name.replace('_', ' ')} must be a finite number >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.cell) and self.cell > 0) or self.per_cell < 1:
            raise ValueError(f"need a cell size > 0 and at least 1 pose per cell; got {self.cell} m, {self.per_cell}")


def measure_bundle(bundle: Bundle, options: CompactOptions, progress: bool = False) -> tuple[GridPoses, torch.Tensor]:
    """Sample the drivable poses and measure every Gaussian's largest weight per cell: the slow step."""
    grid = sample_grid_poses(bundle.map, options.cell, options.per_cell, options.margin, options.seed)
    if not len(grid.poses):
        raise ValueError("no drivable pose found in the map's garage: nothing to measure the scene from")
    return grid, cell_weights(bundle.scene, bundle.rig, grid.poses, grid.cells, grid.n_cells, progress)


def reduce_bundle(bundle: Bundle, grid: GridPoses, weights: torch.Tensor, options: CompactOptions) -> Bundle:
    """The compact bundle from measured ``weights`` [cells, N]: pruned, SH lowered, visibility grid attached."""
    keep = select(weights.amax(dim=0), options.budget, options.min_weight)
    scene, degrees = lower_sh(bundle.scene.subset(keep), options.sh_tolerance)
    grid_out = (visibility_grid(grid, weights[:, keep], options.min_weight, options.cell_budget)
                if options.visibility else None)
    report: dict[str, Any] = {
        "source_gaussians": len(bundle.scene), "gaussians": len(scene), "budget": options.budget,
        "cell_budget": options.cell_budget, "min_weight": options.min_weight, "sh_tolerance": options.sh_tolerance,
        "sh_degree": scene.sh_degree,
        "sh_degree_counts": torch.bincount(degrees, minlength=bundle.scene.sh_degree + 1).tolist(),
        "poses": len(grid.poses), "cell_m": options.cell, "poses_per_cell": options.per_cell,
        "margin_m": options.margin, "seed": options.seed}
    if grid_out is not None:
        sizes = [len(grid_out.members(c)) for c in range(grid.n_cells) if grid_out.measured[c]]
        report["cells"] = len(sizes)
        report["cell_gaussians_mean"] = sum(sizes) / len(sizes)
    return Bundle(scene, bundle.rig, bundle.map, {**bundle.meta, "compaction": report}, grid_out, bundle.poses)


def compact_bundle(bundle: Bundle, options: CompactOptions = CompactOptions(), progress: bool = False) -> Bundle:
    """Measure, then reduce: the compact bundle ready for ``bundle.save``."""
    grid, weights = measure_bundle(bundle, options, progress)
    return reduce_bundle(bundle, grid, weights, options)
