"""Each Gaussian's largest blending weight in one image: max over pixels of alpha * T, for scene compaction.

A separate pass over the forward kernel's tile bins, so a plain render pays nothing for it. Compositing
is the forward's (front to back, same thresholds, early stop), without colours. The Gaussian at which a
pixel stops (it would push T below T_MIN) is counted with the weight alpha * T it would have had: it ends
the pixel, so dropping it would let later Gaussians in and change the image.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from ..project_fast import keep_torch_threads
from ._kernels import _pair_alpha, _start_tile, _tile_box
from .constants import T_MIN, TILE
from .cpu import _f32, _heaviest_first
from .tiles import bin_gaussians

__all__ = ["max_weights"]

_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)
_HALF = np.float32(0.5)


@numba.njit(inline="always", fastmath=True, error_model="numpy", cache=True)
def _weight_row(state, i0, dx0, dy, a, b, c, o, t_min, weights) -> np.float32:
    """Composite one Gaussian over a tile row, writing its TILE weights; returns how many pixels stopped.

    state rows: transmittance, alive flag. The max over the row is taken by the caller: a reduction
    inside this loop keeps LLVM from vectorising it (measured 4x slower).
    """
    p0 = -_HALF * c * dy * dy
    p1 = -b * dy
    p2 = -_HALF * a
    stopped = _ZERO
    for j in range(TILE):
        i = np.uint64(i0) + np.uint64(j)
        dx = dx0 + np.float32(j)
        alpha, _ = _pair_alpha(o, p0 + dx * (p1 + dx * p2))
        t = state[0, i]
        alive = state[1, i]
        w = alpha * t * alive
        stop = t * (_ONE - alpha) < t_min
        weights[j] = w
        state[0, i] = t if stop else t - w
        stopped += alive if stop else _ZERO
        state[1, i] = _ZERO if stop else alive
    return stopped


@numba.njit(fastmath=True, error_model="numpy", cache=True)
def _weights_tile(tile, offsets, gauss_ids, packed, tiles_x, width, height, t_min, state, row_live, weights, best):
    """Composite one tile front to back, raising best[g] to each Gaussian's largest weight in it."""
    x0, y0, x1, y1 = _tile_box(tile, tiles_x, width, height)
    alive = _start_tile(state, row_live, x0, y0, x1, y1)
    for k in range(offsets[tile], offsets[tile + 1]):
        g = gauss_ids[k]
        p = packed[g]
        top = best[g]
        for py in range(max(y0, np.int64(p[10])), min(y1, np.int64(p[11])) + 1):
            if row_live[py - y0] < _HALF:
                continue
            stopped = _weight_row(state, (py - y0) * TILE, np.float32(x0) - p[0], np.float32(py) - p[1],
                                  p[2], p[3], p[4], p[5], t_min, weights)
            for j in range(TILE):
                top = max(top, weights[j])
            row_live[py - y0] -= stopped
            alive -= stopped
        best[g] = top
        if alive < _HALF:
            break


@numba.njit(parallel=True, fastmath=True, error_model="numpy", cache=True)
def _max_weights(offsets, gauss_ids, packed, tiles_x, tile_order, width, height, t_min, best):
    """All tiles dealt over best.shape[0] threads, each raising its own row of best [n_workers, M]."""
    n_workers = best.shape[0]
    for worker in numba.prange(n_workers):
        state = np.empty((2, TILE * TILE), np.float32)
        row_live = np.empty(TILE, np.float32)
        weights = np.empty(TILE, np.float32)
        for j in range(worker, tile_order.shape[0], n_workers):
            _weights_tile(tile_order[j], offsets, gauss_ids, packed, tiles_x, width, height, t_min, state,
                          row_live, weights, best[worker])


def max_weights(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, width: int, height: int,
                t_min: float = T_MIN) -> Tensor:
    """[M] float32: each Gaussian's largest blending weight alpha * T over the image's pixels (0 if none).

    Same inputs and compositing as ``rasterize(..., backend="numba")``; culled Gaussians get 0.
    """
    m = means2d.shape[0]
    best = np.zeros((numba.get_num_threads(), m), np.float32)
    with keep_torch_threads():
        bins = bin_gaussians(_f32(means2d), _f32(conics), np.zeros((m, 3), np.float32), _f32(opacities),
                             _f32(depths), width, height)
        _max_weights(bins.offsets, bins.gauss_ids, bins.packed, bins.tiles_x, _heaviest_first(bins), width, height,
                     np.float32(t_min), best)
    return torch.from_numpy(best.max(axis=0, initial=0.0))
