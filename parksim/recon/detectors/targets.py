"""Training targets from slot labels: DMPR-PS grid targets for the point head, node/edge targets for GCN."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .backbone import POINT_CHANNELS

__all__ = ["point_targets", "graph_targets"]


def point_targets(marks: np.ndarray, size: int, grid: int) -> Tensor:
    """``[6, grid, grid]`` targets (confidence, L, x/y offset, cos, sin) for marks ``[N, 4]`` in a ``size`` px image.

    Cells are ``size / grid`` px wide; labelled points are at least 2 m apart, far more than a cell, so a
    cell holds at most one point (a later point would replace an earlier one).
    """
    target = torch.zeros(POINT_CHANNELS, grid, grid)
    for x, y, direction, is_l in marks:
        u, v = (x + 0.5) / size * grid, (y + 0.5) / size * grid
        c, r = min(int(u), grid - 1), min(int(v), grid - 1)
        target[:, r, c] = torch.tensor([1.0, is_l, u - c, v - r, np.cos(direction), np.sin(direction)])
    return target


def graph_targets(marks: np.ndarray, slots: np.ndarray, size: int, max_nodes: int,
                  jitter_px: float, rng: np.random.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """Nodes ``[max_nodes, 5]`` (jittered labelled points, normalised), their mask and the ordered edge targets."""
    n = min(len(marks), max_nodes)
    nodes = torch.zeros(max_nodes, 5)
    mask = torch.zeros(max_nodes, dtype=torch.bool)
    edges = torch.zeros(max_nodes, max_nodes)
    if n:
        xy = marks[:n, :2] + rng.normal(0.0, jitter_px, (n, 2))
        d = marks[:n, 2] + rng.normal(0.0, 0.05, n)
        feats = np.stack([(xy[:, 0] + 0.5) / size, (xy[:, 1] + 0.5) / size, np.cos(d), np.sin(d), marks[:n, 3]], 1)
        nodes[:n] = torch.from_numpy(np.clip(feats, -1.0, 1.0)).float()
        mask[:n] = True
    for p1, p2 in slots:
        if p1 < n and p2 < n:
            edges[p1, p2] = 1.0
    return nodes, mask, edges
