"""Dense pure-torch rasterizer: every pixel against every Gaussian, the oracle for the fast kernels.

Memory is O(pixels x Gaussians) per chunk of pixels, so use it on small images or few Gaussians.
Autograd provides its backward; run it in float64 to get reference gradients.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...camera import pixel_grid
from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN


def gaussian_is_drawable(conics: Tensor, opacities: Tensor) -> Tensor:
    """[M] bool: conic positive definite and finite, and opacity able to reach ALPHA_MIN; others are culled."""
    a, b, c = conics.unbind(-1)
    finite = torch.isfinite(conics).all(-1) & torch.isfinite(opacities)
    return finite & (a > 0) & (a * c - b * b > 0) & (opacities >= ALPHA_MIN)


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
    """
    dtype, device = means2d.dtype, means2d.device
    keep = gaussian_is_drawable(conics, opacities)
    order = torch.argsort(torch.where(keep, depths, torch.inf), stable=True)[: int(keep.sum())]
    mean, conic, color, opac, depth = means2d[order], conics[order], colors[order], opacities[order], depths[order]

    pix = pixel_grid(width, height, dtype, device).reshape(-1, 2)
    rgb_chunks, trans_chunks, depth_chunks = [], [], []
    for start in range(0, pix.shape[0], chunk_pixels):
        p = pix[start : start + chunk_pixels]
        dx = p[:, None, 0] - mean[None, :, 0]
        dy = p[:, None, 1] - mean[None, :, 1]
        power = -0.5 * (conic[:, 0] * dx * dx + 2.0 * conic[:, 1] * dx * dy + conic[:, 2] * dy * dy)
        alpha = torch.clamp(opac * torch.exp(power.clamp(max=0.0)), max=ALPHA_MAX)
        alpha = torch.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            # Transmittance after each Gaussian is non-increasing, so this mask is the prefix a pixel composites.
            alive = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
        alpha = alpha * alive
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
