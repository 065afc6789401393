"""The three reductions of ``parksim compact``: keep the best-ranked Gaussians, drop unneeded SH bands, cell lists.

Each is a pure function of the measurements (``measure``, ``benefit``) and the scene.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..gaussians import GaussianScene
from ..visibility import VisibilityGrid
from .poses import GridPoses

__all__ = ["RANKINGS", "check_budget", "budget_count", "ranking_score", "select", "sh_change_bound", "lower_sh",
           "visibility_grid"]


def check_budget(budget: float, name: str = "budget") -> None:
    """ValueError (naming ``name``) unless ``budget`` is a fraction in (0, 1] or a whole count above 1."""
    if not (math.isfinite(budget) and budget > 0):
        raise ValueError(f"{name} must be a fraction in (0, 1] or a Gaussian count > 1, got {budget}")
    if budget > 1 and budget != int(budget):
        raise ValueError(f"a {name} above 1 is a Gaussian count and must be whole, got {budget}")


def budget_count(budget: float, n: int) -> int:
    """Gaussians a budget allows out of ``n``: a fraction when 0 < budget <= 1, else a whole count (> 1)."""
    check_budget(budget)
    return round(budget * n) if budget <= 1 else min(int(budget), n)


RANKINGS = ("weight", "benefit-cost")
"""How ``--budget`` ranks Gaussians: by largest blending weight, or by summed training-view weight per pair."""


def ranking_score(ranking: str, weights: Tensor, benefit: Tensor | None = None, pairs: Tensor | None = None) -> Tensor:
    """[N] the key ``select`` keeps the largest of: ``weights`` as they are, or ``benefit / pairs``.

    benefit-cost is a knapsack's greedy ratio: what a Gaussian adds to the images per Gaussian-pixel pair it costs
    at serving poses; a Gaussian with no pairs there (never drawn) scores 0.
    """
    if ranking == "weight":
        return weights
    if ranking != "benefit-cost":
        raise ValueError(f"ranking must be one of {', '.join(RANKINGS)}, got {ranking!r}")
    if benefit is None or pairs is None:
        raise ValueError("the benefit-cost ranking needs the measured benefit and pairs")
    return torch.where(pairs > 0, benefit / pairs.clamp(min=1.0), 0.0)


def select(weights: Tensor, budget: float, min_weight: float = 0.0, score: Tensor | None = None) -> Tensor:
    """Indices (ascending) of the Gaussians to keep: weight above ``min_weight``, at most the budget's count.

    Among those above ``min_weight``, the largest ``score`` (default: the weights) win; ties go to the lower index.
    """
    candidates = (weights > min_weight).nonzero().squeeze(1)
    k = min(budget_count(budget, len(weights)), len(candidates))
    key = (weights if score is None else score)[candidates]
    order = torch.argsort(key, descending=True, stable=True)[:k]
    return candidates[order].sort().values


def sh_change_bound(sh: Tensor, degree: int) -> Tensor:
    """[N, degree + 1]: column d bounds the colour change (any direction, any channel) of zeroing bands above d.

    Band l's basis has norm sqrt((2l + 1) / 4 pi) for every unit direction (addition theorem), so by
    Cauchy-Schwarz its term is at most that times the norm of the band's coefficients, per channel.
    """
    bands = [sh[:, b * b:(b + 1) * (b + 1)].norm(dim=1).amax(dim=-1) * math.sqrt((2 * b + 1) / (4 * math.pi))
             for b in range(degree + 1)]
    per_band = torch.stack(bands, dim=1)                                   # [N, degree + 1]
    tail = per_band.flip(1).cumsum(1).flip(1)                              # bands >= d
    return torch.cat([tail[:, 1:], torch.zeros_like(tail[:, :1])], dim=1)  # bands > d


def lower_sh(scene: GaussianScene, tolerance: float) -> tuple[GaussianScene, Tensor]:
    """Zero each Gaussian's SH bands above the lowest degree that keeps its colour within ``tolerance``.

    Returns the scene (its ``sh_degree`` lowered to the highest degree any Gaussian still needs, which is
    what makes SH evaluation cheaper) and the per-Gaussian degrees. Zeroing bands is the least-squares
    choice: the higher bands average to zero over the sphere.
    """
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"SH tolerance must be >= 0, got {tolerance}")
    bound = sh_change_bound(scene.sh, scene.sh_degree)
    degrees = (bound > tolerance).sum(dim=1)   # bound is non-increasing in d, so this is the first d within it
    keep_k = (degrees + 1) ** 2
    coeff = torch.arange(scene.sh.shape[1], device=scene.sh.device)
    sh = torch.where((coeff[None, :] < keep_k[:, None])[..., None], scene.sh, torch.zeros_like(scene.sh))
    top = int(degrees.max()) if len(degrees) else 0
    return GaussianScene(scene.means, scene.quats, scene.log_scales, scene.opacity_logits,
                         sh[:, :(top + 1) ** 2].contiguous(), top), degrees


def visibility_grid(grid: GridPoses, cell_weights: Tensor, min_weight: float = 0.0,
                    cell_budget: float = 1.0) -> VisibilityGrid:
    """Per cell with poses, the Gaussians (columns of ``cell_weights`` [cells, N]) ``select`` keeps from its weights.

    ``cell_budget`` bounds each cell's list (fraction of N or count), the most visible from that cell first.
    """
    measured = np.zeros(grid.n_cells, bool)
    measured[np.unique(grid.cells)] = True
    empty = torch.zeros(0, dtype=torch.long)
    members = [select(cell_weights[c], cell_budget, min_weight) if measured[c] else empty for c in range(grid.n_cells)]
    offsets = np.zeros(grid.n_cells + 1, np.int64)
    np.cumsum([len(m) for m in members], out=offsets[1:])
    indices = torch.cat(members).numpy().astype(np.int32)
    return VisibilityGrid(grid.x0, grid.y0, grid.cell, grid.nx, grid.ny, offsets, indices, measured)
