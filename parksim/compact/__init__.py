"""Scene compaction (``parksim compact``): fewer Gaussians, fewer SH bands, and per-region visibility for serving.

Poses are sampled in the drivable area of the bundle's map (``poses``); each Gaussian's largest blending
weight per grid cell and the Gaussian-pixel pairs it costs there are measured (``measure``), with its summed
weight over the training views (``benefit``) when the ranking needs it; the scene is reduced from those
(``reduce``), optionally fine-tuned in between (a ``tune`` callback: ``parksim.recon.finetune`` in the CLI).
Projections and renders run on the scene's device (``parksim compact --device`` moves it there), the weight and
pair kernels on the CPU; measurements are CPU tensors and the compact scene stays on the scene's device.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..bundle import Bundle
from ..data import DatasetReader
from .benefit import summed_weights
from .measure import cell_weights, pose_measure, pose_weights, tile_pairs
from .poses import GridPoses, sample_grid_poses
from .reduce import (
    RANKINGS,
    budget_count,
    check_budget,
    lower_sh,
    ranking_score,
    select,
    sh_change_bound,
    visibility_grid,
)

__all__ = ["CompactOptions", "Measurement", "compact_bundle", "measure_bundle", "reduce_bundle", "pose_weights",
           "pose_measure", "tile_pairs", "cell_weights", "summed_weights", "sample_grid_poses", "GridPoses",
           "RANKINGS", "check_budget", "budget_count", "ranking_score", "select", "lower_sh", "sh_change_bound",
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
    ranking: str = "weight"

    def __post_init__(self) -> None:
        check_budget(self.budget)
        check_budget(self.cell_budget, "cell budget")
        for name in ("min_weight", "sh_tolerance", "margin"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name.replace('_', ' ')} must be a finite number >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.cell) and self.cell > 0) or self.per_cell < 1:
            raise ValueError(f"need a cell size > 0 and at least 1 pose per cell; got {self.cell} m, {self.per_cell}")
        if self.ranking not in RANKINGS:
            raise ValueError(f"ranking must be one of {', '.join(RANKINGS)}, got {self.ranking!r}")


@dataclass(frozen=True)
class Measurement:
    """What ``reduce_bundle`` ranks by: the poses, per-cell largest weights [cells, N], pairs summed over the poses
    [N], and the summed training-view weights [N] (None when not measured: the weight ranking needs none)."""

    grid: GridPoses
    weights: Tensor
    pairs: Tensor
    benefit: Tensor | None = None

    def score(self, ranking: str) -> Tensor:
        """[N] the key the global budget keeps the largest of (``reduce.ranking_score``)."""
        return ranking_score(ranking, self.weights.amax(dim=0), self.benefit, self.pairs)


def measure_bundle(bundle: Bundle, options: CompactOptions, progress: bool = False,
                   reader: DatasetReader | None = None) -> Measurement:
    """Sample the drivable poses and measure every Gaussian there (the slow step); for the benefit-cost ranking
    also its benefit over the training views of ``reader`` (the bundle's dataset)."""
    grid = sample_grid_poses(bundle.map, options.cell, options.per_cell, options.margin, options.seed)
    if not len(grid.poses):
        raise ValueError("no drivable pose found in the map's garage: nothing to measure the scene from")
    if options.ranking == "benefit-cost" and reader is None:
        raise ValueError("the benefit-cost ranking needs the training dataset (the bundle's, or --dataset)")
    weights, pairs = cell_weights(bundle.scene, bundle.rig, grid.poses, grid.cells, grid.n_cells, progress)
    benefit = (summed_weights(bundle.scene, bundle.rig, reader, progress) if options.ranking == "benefit-cost"
               and reader is not None else None)
    return Measurement(grid, weights, pairs, benefit)


def reduce_bundle(bundle: Bundle, measurement: Measurement, options: CompactOptions,
                  tune: Callable[[Bundle], Bundle] | None = None) -> Bundle:
    """The compact bundle: pruned by ``options.ranking``, then ``tune``d (same Gaussians, e.g. fine-tuned), SH
    lowered and the visibility grid attached."""
    grid, weights = measurement.grid, measurement.weights
    keep = select(weights.amax(dim=0), options.budget, options.min_weight, measurement.score(options.ranking))
    pruned = Bundle(bundle.scene.subset(keep.to(bundle.scene.means.device)), bundle.rig, bundle.map, bundle.meta,
                    None, bundle.poses)
    if tune is not None:
        pruned = tune(pruned)
        if len(pruned.scene) != len(keep):
            raise ValueError(f"tuning changed the Gaussian count ({len(keep)} -> {len(pruned.scene)})")
    scene, degrees = lower_sh(pruned.scene, options.sh_tolerance)
    grid_out = (visibility_grid(grid, weights[:, keep], options.min_weight, options.cell_budget)
                if options.visibility else None)
    report: dict[str, Any] = {
        "source_gaussians": len(bundle.scene), "gaussians": len(scene), "ranking": options.ranking,
        "budget": options.budget, "cell_budget": options.cell_budget, "min_weight": options.min_weight,
        "sh_tolerance": options.sh_tolerance, "sh_degree": scene.sh_degree,
        "sh_degree_counts": torch.bincount(degrees, minlength=pruned.scene.sh_degree + 1).tolist(),
        "poses": len(grid.poses), "cell_m": options.cell, "poses_per_cell": options.per_cell,
        "margin_m": options.margin, "seed": options.seed}
    if grid_out is not None:
        sizes = [len(grid_out.members(c)) for c in range(grid.n_cells) if grid_out.measured[c]]
        report["cells"] = len(sizes)
        report["cell_gaussians_mean"] = sum(sizes) / len(sizes)
    return Bundle(scene, bundle.rig, bundle.map, {**pruned.meta, "compaction": report}, grid_out, bundle.poses)


def compact_bundle(bundle: Bundle, options: CompactOptions = CompactOptions(), progress: bool = False,
                   reader: DatasetReader | None = None, tune: Callable[[Bundle], Bundle] | None = None) -> Bundle:
    """Measure, then reduce: the compact bundle ready for ``bundle.save``."""
    return reduce_bundle(bundle, measure_bundle(bundle, options, progress, reader), options, tune)
