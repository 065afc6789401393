"""Slot-aware weight maps (paper "Parking Corner Guidance" and "Slot Edge-aware Extension", reference
lines 246-330): confidence shaping, the teacher/student mix with stop-gradient, upsampling, edge tubes.

Maps are ``[B, 1, h, w]`` (the detector's layout) unless stated; BEV points are ``(u, v)`` pixels.
Edge tubes of several edges are aggregated by a pixel-wise max (the paper says "aggregating" without
naming the operator; the max keeps W_edge in [0, 1] like the corner masks). A tube does not carry its
edge score: the paper's e_ij (reference line 305) depends on the corner locations only.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from parksim.camera import pixel_grid

__all__ = ["shape_confidence", "mix", "upsample", "top_edges", "edge_tubes", "edge_weights", "TUBE_CUTOFF"]

TUBE_CUTOFF = 5.0
"""Edge tubes are evaluated within this many sigma of their segment (ParkSim: a cost bound, not the paper's)."""


def shape_confidence(conf: Tensor, tau: float = 0.25, temperature: float = 0.5, gamma: float = 1.0) -> Tensor:
    """W = sigmoid((H_conf - tau) / T)^gamma: soft, differentiable corner mask (the paper's shaping equation)."""
    return torch.sigmoid((conf - tau) / temperature) ** gamma


def mix(teacher: Tensor, student: Tensor, share: float) -> Tensor:
    """share * teacher + (1 - share) * sg(student): the student never receives gradient through its weights."""
    return share * teacher + (1.0 - share) * student.detach()


def upsample(weights: Tensor, size: tuple[int, int]) -> Tensor:
    """Grid weights ``[B, 1, h, w]`` -> ``[B, 1, H, W]`` at the BEV resolution ``size`` = (H, W), bilinearly."""
    return F.interpolate(weights, size=size, mode="bilinear", align_corners=False)


def top_edges(scores: Tensor, k: int) -> Tensor:
    """The ``k`` highest-scoring ordered pairs ``(i, j)``, i != j, of an ``[N, N]`` edge-score matrix, as ``[E, 2]``."""
    n = scores.shape[0]
    off_diagonal = ~torch.eye(n, dtype=torch.bool)
    flat = torch.where(off_diagonal, scores.detach(), torch.full_like(scores, -torch.inf)).flatten()
    count = min(k, n * (n - 1))
    picked = flat.topk(count).indices if count > 0 else flat.new_zeros(0, dtype=torch.long)
    return torch.stack([picked // max(n, 1), picked % max(n, 1)], dim=1)


def edge_tubes(points: Tensor, pairs: Tensor, size: tuple[int, int], sigma: float = 1.5, samples: int = 32,
               cutoff: float = TUBE_CUTOFF) -> Tensor:
    """Max over edges of e_ij(u, v) = max_t exp(-|(u, v) - l_ij(t)|^2 / 2 sigma^2), t sampled at ``samples`` points.

    ``points`` ``[N, 2]`` (u, v) pixels, ``pairs`` ``[E, 2]`` indices into them; returns ``[H, W]`` (``size``).
    Each tube is evaluated in its segment's bounding box widened by ``cutoff`` sigma; pixels outside it keep 0
    (exp(-cutoff^2 / 2) = 4e-6 at the default), so a tube costs its box rather than the whole BEV.
    """
    height, width = size
    out = points.new_zeros(height, width)
    t = torch.linspace(0.0, 1.0, samples, dtype=points.dtype)[:, None]
    reach = cutoff * sigma
    for i, j in pairs.tolist():
        line = (1.0 - t) * points[i] + t * points[j]
        u0, v0 = (max(0, math.floor(float(x) - reach)) for x in line.amin(0))
        u1, v1 = (math.ceil(float(x) + reach) for x in line.amax(0))
        u1, v1 = min(u1, width - 1), min(v1, height - 1)
        if u0 > u1 or v0 > v1:
            continue
        pixels = pixel_grid(u1 - u0 + 1, v1 - v0 + 1, points.dtype) + points.new_tensor([u0, v0])
        dist2 = ((pixels.reshape(-1, 1, 2) - line) ** 2).sum(-1).amin(1)
        tube = torch.exp(-dist2 / (2.0 * sigma ** 2)).reshape(v1 - v0 + 1, u1 - u0 + 1)
        out[v0:v1 + 1, u0:u1 + 1] = torch.maximum(out[v0:v1 + 1, u0:u1 + 1], tube)
    return out


def edge_weights(points: Tensor, scores: Tensor, k: int, size: tuple[int, int], sigma: float = 1.5,
                 samples: int = 32) -> Tensor:
    """One image's edge weight map ``[H, W]``: tubes along the top-``k`` edges of its edge-score matrix."""
    return edge_tubes(points, top_edges(scores, k), size, sigma, samples)
