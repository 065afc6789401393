"""Gaussian-pixel pairs of the numba compositor, counted for ``parksim bench rasterize`` and the stage table of
``parksim bench render``: the pairs it evaluates (16-pixel tile rows each ellipse reaches, per tile up to its last
contributor) against the pairs that change a pixel (alpha above the threshold, up to each pixel's last
contributor). The ratio says how much of the compositor's work is spent on pairs that blend nothing.
"""

from __future__ import annotations

import numba
import numpy as np

from ..render.rasterize import TILE
from ..render.rasterize import _kernels as kernels
from ..render.rasterize._kernels import _pair_alpha, _tile_box
from ..render.rasterize.tiles import TileBins, bin_gaussians

__all__ = ["rows_evaluated", "pairs_blended", "count_pairs", "count_binned"]


@numba.njit(cache=True)
def rows_evaluated(offsets, gauss_ids, packed, tiles_x, last, width, height):
    """Tile rows the forward kernel evaluates (``TILE`` pairs each), per tile up to its last contributor + 1.

    Args:
        offsets, gauss_ids, packed, tiles_x: the tile bins (``bin_gaussians``).
        last: ``(H, W)`` int64 index of each pixel's last contributor (the forward kernel's output).
        width, height: image size.

    Returns:
        The number of tile rows evaluated.
    """
    total = 0
    for tile in range(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(tile, tiles_x, width, height)
        stop = offsets[tile]
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                stop = max(stop, last[py, px] + 2)
        for k in range(offsets[tile], min(stop, offsets[tile + 1])):
            p = packed[gauss_ids[k]]
            total += max(0, min(y1, np.int64(p[11])) - max(y0, np.int64(p[10])) + 1)
    return total


@numba.njit(cache=True)
def pairs_blended(offsets, gauss_ids, packed, tiles_x, last, width, height):
    """Gaussian-pixel pairs with alpha above the threshold up to each pixel's last contributor (the blended ones).

    Args: as ``rows_evaluated``.

    Returns:
        The number of pairs blended.
    """
    total = 0
    for tile in range(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(tile, tiles_x, width, height)
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                for k in range(offsets[tile], last[py, px] + 1):
                    p = packed[gauss_ids[k]]
                    dx, dy = np.float32(px) - p[0], np.float32(py) - p[1]
                    power = np.float32(-0.5) * (p[2] * dx * dx + p[4] * dy * dy) - p[3] * dx * dy
                    total += int(_pair_alpha(p[5], power)[0] > 0.0)
    return total


def count_pairs(means2d: np.ndarray, conics: np.ndarray, colors: np.ndarray, opacities: np.ndarray,
                depths: np.ndarray, width: int, height: int) -> dict[str, int]:
    """Bin and composite one image, then count its pairs.

    Args:
        means2d: ``(N, 2)`` float32 pixel centres.
        conics: ``(N, 3)`` inverse 2D covariances (a, b, c).
        colors: ``(N, 3)``.
        opacities: ``(N,)``.
        depths: ``(N,)``.
        width, height: image size.

    Returns:
        ``intersections`` (tile-Gaussian pairs binned), ``evaluated`` and ``blended`` Gaussian-pixel pairs.
    """
    bins = bin_gaussians(means2d, conics, colors, opacities, depths, width, height)
    order = np.argsort(-np.diff(bins.offsets), kind="stable")
    planes = (np.empty((height, width, 3), np.float32), np.empty((height, width), np.float32),
              np.empty((height, width), np.float32), np.empty((height, width), np.int64))
    kernels.forward(bins.offsets, bins.gauss_ids, bins.packed, bins.tiles_x, order, numba.get_num_threads(),
                    width, height, *planes)
    return count_binned(bins, planes[3], width, height)


def count_binned(bins: TileBins, last: np.ndarray, width: int, height: int) -> dict[str, int]:
    """``count_pairs`` of an image already binned and composited.

    Args:
        bins: the image's tile bins.
        last: ``(H, W)`` int64 index of each pixel's last contributor.
        width, height: image size.

    Returns:
        As ``count_pairs``.
    """
    args = (bins.offsets, bins.gauss_ids, bins.packed, bins.tiles_x, last, width, height)
    return {"intersections": int(bins.gauss_ids.shape[0]), "evaluated": TILE * int(rows_evaluated(*args)),
            "blended": int(pairs_blended(*args))}
