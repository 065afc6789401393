"""Dense pure-torch rasterizer: every pixel against every Gaussian, the oracle for the fast kernels.

Memory is O(pixels x Gaussians) per chunk of pixels, so use it on small images or few Gaussians.
Autograd provides its backward; run it in float64 to get reference gradients.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...camera import pixel_grid
from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN

__all__ = ["rasterize_reference", "max_weights_reference", "gaussian_is_drawable"]


def gaussian_is_drawable(conics: Tensor, opacities: Tensor) -> Tensor:
    """[M] bool: conic positive definite and finite, and opacity able to reach ALPHA_MIN; others are culled.

    Args:
        conics: ``[M, 3]`` inverse 2D covariances ``(a, b, c)``.
        opacities: ``[M]`` in [0, 1].

    Returns:
        ``[M]`` bool mask of the Gaussians every backend draws.
    """
    a, b, c = conics.unbind(-1)
    finite = torch.isfinite(conics).all(-1) & torch.isfinite(opacities)
    return finite & (a > 0) & (a * c - b * b > 0) & (opacities >= ALPHA_MIN)


def _depth_sorted(conics: Tensor, opacities: Tensor, depths: Tensor) -> Tensor:
    """Indices of the drawable Gaussians by ascending depth (ties by index): the compositing order."""
    keep = gaussian_is_drawable(conics, opacities)
    return torch.argsort(torch.where(keep, depths, torch.inf), stable=True)[: int(keep.sum())]


def _pair_alphas(pix: Tensor, mean: Tensor, conic: Tensor, opac: Tensor) -> Tensor:
    """[P, M] alpha of every pixel-Gaussian pair: min(ALPHA_MAX, o exp(power)), 0 below ALPHA_MIN."""
    dx = pix[:, None, 0] - mean[None, :, 0]
    dy = pix[:, None, 1] - mean[None, :, 1]
    power = -0.5 * (conic[:, 0] * dx * dx + 2.0 * conic[:, 1] * dx * dy + conic[:, 2] * dy * dy)
    alpha = torch.clamp(opac * torch.exp(power.clamp(max=0.0)), max=ALPHA_MAX)
    return torch.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))


def _alive(alpha: Tensor) -> Tensor:
    """[P, M] bool: the pair is composited (transmittance after it stays >= T_MIN; non-increasing, so a prefix)."""
    with torch.no_grad():
        return torch.cumprod(1.0 - alpha, dim=1) >= T_MIN


def rasterize_reference(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    bg: Tensor | None = None,
    chunk_pixels: int = 4096,
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back compositing sorted by depth; returns (rgb [H,W,3], alpha [H,W], depth [H,W]).

    Same semantics as the fast kernels: alpha = min(ALPHA_MAX, o exp(power)), pairs with alpha < ALPHA_MIN
    skipped, and a pixel stops before the Gaussian that would push its transmittance below T_MIN.
    depth is the unnormalised expected depth sum_i d_i alpha_i T_i (divide by alpha for a mean depth).

    Args:
        means2d: ``[M, 2]`` centres in pixels (u, v).
        conics: ``[M, 3]`` inverse 2D covariances ``(a, b, c)`` in 1/px^2.
        colors: ``[M, 3]`` RGB.
        opacities: ``[M]`` in [0, 1].
        depths: ``[M]`` sort keys, also what ``depth`` averages.
        width: image width ``W`` in pixels.
        height: image height ``H`` in pixels.
        bg: ``[3]`` background behind the remaining transmittance; None for black.
        chunk_pixels: pixels per dense ``[P, M]`` block (memory ~ ``chunk_pixels * M`` per tensor).

    Returns:
        ``(rgb [H, W, 3], alpha [H, W], depth [H, W])`` in ``means2d``'s dtype, differentiable by autograd.
    """
    dtype, device = means2d.dtype, means2d.device
    order = _depth_sorted(conics, opacities, depths)
    mean, conic, color, opac, depth = means2d[order], conics[order], colors[order], opacities[order], depths[order]

    pix = pixel_grid(width, height, dtype, device).reshape(-1, 2)
    rgb_chunks, trans_chunks, depth_chunks = [], [], []
    for start in range(0, pix.shape[0], chunk_pixels):
        alpha = _pair_alphas(pix[start : start + chunk_pixels], mean, conic, opac)
        alpha = alpha * _alive(alpha)
        trans = torch.cumprod(torch.cat([alpha.new_ones(alpha.shape[0], 1), 1.0 - alpha], dim=1), dim=1)
        weights = alpha * trans[:, :-1]
        rgb_chunks.append(weights @ color)
        depth_chunks.append(weights @ depth)
        trans_chunks.append(trans[:, -1])
    rgb = torch.cat(rgb_chunks).reshape(height, width, 3)
    t_final = torch.cat(trans_chunks).reshape(height, width)
    if bg is not None:
        rgb = rgb + t_final[..., None] * bg.to(dtype)
    return rgb, 1.0 - t_final, torch.cat(depth_chunks).reshape(height, width)


@torch.no_grad()
def max_weights_reference(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, width: int,
                          height: int, chunk_pixels: int = 4096) -> Tensor:
    """[M]: each Gaussian's largest blending weight alpha * T over the pixels, the oracle of ``contribution``.

    The Gaussian at which a pixel stops counts with the weight it would have had (see ``contribution``).

    Args:
        means2d: ``[M, 2]`` centres in pixels (u, v).
        conics: ``[M, 3]`` inverse 2D covariances ``(a, b, c)``.
        opacities: ``[M]`` in [0, 1].
        depths: ``[M]`` sort keys.
        width: image width in pixels.
        height: image height in pixels.
        chunk_pixels: pixels per dense block.

    Returns:
        ``[M]`` largest weights, 0 for a Gaussian that is never drawn.
    """
    order = _depth_sorted(conics, opacities, depths)
    mean, conic, opac = means2d[order], conics[order], opacities[order]
    pix = pixel_grid(width, height, means2d.dtype, means2d.device).reshape(-1, 2)
    best = means2d.new_zeros(order.shape[0])
    for start in range(0, pix.shape[0], chunk_pixels):
        alpha = _pair_alphas(pix[start : start + chunk_pixels], mean, conic, opac)
        alive = _alive(alpha)
        reached = torch.cat([torch.ones_like(alive[:, :1]), alive[:, :-1]], dim=1)   # not stopped before this one
        trans = torch.cumprod(torch.cat([alpha.new_ones(alpha.shape[0], 1), 1.0 - alpha * alive], dim=1), dim=1)
        best = torch.maximum(best, (alpha * trans[:, :-1] * reached).amax(dim=0))
    return means2d.new_zeros(means2d.shape[0]).index_copy(0, order, best)
