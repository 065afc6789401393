"""CUDA backend: our screen-space Gaussians through gsplat's tile intersection and rasterize_to_pixels.

gsplat (>= 1.5, radii [..., N, 2]) puts pixel centres at (j + 0.5, i + 0.5), so means are shifted by half
a pixel; depth is rendered as a 4th colour channel. Radii come from the same alpha-threshold ellipse as the
CPU binning. gsplat clamps alpha at 0.999 (not 0.99), so results near saturation differ slightly.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .constants import ALPHA_MIN, TILE
from .reference import gaussian_is_drawable

__all__ = ["rasterize_gsplat", "rasterize_gsplat_views"]


def _import_gsplat():
    """gsplat module, or a RuntimeError saying what is missing."""
    if not torch.cuda.is_available():
        raise RuntimeError("rasterize backend 'gsplat' needs CUDA; use backend='numba' on CPU")
    try:
        import gsplat
    except ImportError as err:
        raise RuntimeError("rasterize backend 'gsplat' needs the gsplat package (pip install 'parksim[cuda]')") from err
    return gsplat


def _radii(conics: Tensor, opacities: Tensor) -> Tensor:
    """[..., M, 2] int32 half extents (x, y) of the alpha-threshold ellipse; 0 for culled Gaussians."""
    a, b, c = conics.detach().unbind(-1)
    q = 2.0 * torch.log(opacities.detach().clamp(min=ALPHA_MIN) / ALPHA_MIN)
    det = (a * c - b * b).clamp(min=1e-30)
    extent = torch.stack([torch.sqrt(q * c / det), torch.sqrt(q * a / det)], -1).ceil()
    keep = gaussian_is_drawable(conics.detach(), opacities.detach())
    return torch.where(keep[..., None], extent, torch.zeros_like(extent)).to(torch.int32)


def rasterize_gsplat_views(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor,
                           width: int, height: int, bg: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """V images of one size in one gsplat call: tile intersection, sort and compositing for all views at once.

    Rows with opacity 0 (or a degenerate conic) get radius 0 and touch no tile, so dense per-view rows (every
    Gaussian, most not drawn) need no gather.

    Args:
        means2d: ``[V, M, 2]`` pixel centres (pixel ``(i, j)`` at ``(j, i)``).
        conics: ``[V, M, 3]``.
        colors: ``[V, M, 3]``.
        opacities: ``[V, M]``.
        depths: ``[V, M]`` distances, the sort key and the depth channel.
        width: image width in pixels.
        height: image height in pixels.
        bg: ``(3,)`` background behind the Gaussians, or None for black.

    Returns:
        ``(rgb [V, H, W, 3], alpha [V, H, W], depth_sum [V, H, W])`` in ``means2d``'s dtype.

    Raises:
        RuntimeError: no CUDA device or no gsplat.
    """
    gsplat = _import_gsplat()
    dtype, views = means2d.dtype, means2d.shape[0]
    means = means2d.float() + 0.5
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    _, isect_ids, flatten_ids = gsplat.isect_tiles(
        means, _radii(conics, opacities), depths.detach().float(), TILE, tiles_x, tiles_y)
    offsets = gsplat.isect_offset_encode(isect_ids, views, tiles_x, tiles_y)
    features = torch.cat([colors, depths[..., None]], -1).float()
    rendered, alphas = gsplat.rasterize_to_pixels(
        means, conics.float(), features, opacities.float(), width, height, TILE, offsets, flatten_ids)
    rgb, depth, alpha = rendered[..., :3], rendered[..., 3], alphas[..., 0]
    if bg is not None:
        rgb = rgb + (1.0 - alpha)[..., None] * bg.detach().to(rgb)
    return rgb.to(dtype), alpha.to(dtype), depth.to(dtype)


def rasterize_gsplat(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor,
                     width: int, height: int, bg: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """gsplat CUDA rasterizer; same contract as `parksim.render.rasterize.rasterize` (CUDA tensors)."""
    rgb, alpha, depth = rasterize_gsplat_views(means2d[None], conics[None], colors[None], opacities[None],
                                               depths[None], width, height, bg)
    return rgb[0], alpha[0], depth[0]
