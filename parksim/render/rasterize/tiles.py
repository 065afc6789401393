"""Tile binning for the CPU rasterizer: which Gaussians touch which 16x16 tile, in depth order per tile.

Each Gaussian's tiles come from the exact alpha-threshold ellipse, tile row by tile row (not a 3-sigma
square), written in parallel into the Gaussian's own slots. A counting sort then visits Gaussians in
ascending depth (radix-sorted) and buckets their slots by tile, so per-tile lists come out sorted by
(tile, depth) in O(intersections). The kernels read one packed 64-byte row per Gaussian (one cache line
instead of six scattered arrays); rows of culled Gaussians are never read and stay uninitialised.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from ..scratch import Allocator, fresh
from .constants import ALPHA_MIN, TILE
from .ellipse import half_height, pixel_range, threshold_q, x_span

__all__ = ["bin_gaussians", "TileBins", "PACKED", "MAX_PER_TILE"]

PACKED = 16
"""Columns of a packed Gaussian row: mean x, y; conic a, b, c; opacity; r, g, b; depth; first, last pixel row."""
MAX_PER_TILE = 1 << 24
"""Kernels keep ranks within a tile as float32, exact below this."""


class TileBins(NamedTuple):
    """Per-tile Gaussian lists: tile t owns gauss_ids[offsets[t]:offsets[t + 1]], front to back."""

    offsets: np.ndarray  # [n_tiles + 1] int64
    gauss_ids: np.ndarray  # [n_intersections] int32
    packed: np.ndarray  # [M, PACKED] float32, see PACKED
    starts: np.ndarray  # [M + 1] int64: Gaussian g owns slots starts[g]:starts[g + 1] (Gaussian-major) ...
    slot_of: np.ndarray  # [n_intersections] int64: ... and this maps a position in gauss_ids to its slot
    tiles_x: int
    tiles_y: int


@numba.njit(inline="always", cache=True)
def _tile_row_cols(mx, my, a, b, c, q, ty, width, height) -> tuple[int, int]:
    """Range of tile columns the ellipse touches within tile row ty (empty when first > last)."""
    y0 = ty * TILE
    y1 = min(y0 + TILE, height) - 1
    dx_lo, dx_hi = x_span(a, b, c, q, y0 - my, y1 - my)
    px_lo, px_hi = pixel_range(mx, dx_lo, dx_hi, 0, width - 1)
    if px_lo > px_hi:
        return 1, 0
    return px_lo // TILE, px_hi // TILE


@numba.njit(inline="always", cache=True)
def _params(means, conics, opacities, g) -> tuple[float, float, float, float, float, float]:
    """Mean x, y, conic a, b, c and alpha-threshold q of Gaussian g in float64 (q only valid if drawable)."""
    o = np.float64(opacities[g])
    q = threshold_q(max(o, ALPHA_MIN))
    return (np.float64(means[g, 0]), np.float64(means[g, 1]),
            np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2]), q)


@numba.njit(parallel=True, nogil=True, cache=True)
def _count_and_pack(means, conics, colors, opacities, depths, width, height, tiles_x, packed, counts, first_tile):
    """Per Gaussian: the packed row, the number of tiles its ellipse touches (0 if culled) and the first one."""
    for g in numba.prange(means.shape[0]):
        counts[g] = 0
        o = np.float64(opacities[g])
        if not o >= ALPHA_MIN:   # most rows in a multi-camera batch: not drawn in this image
            continue
        mx, my, a, b, c, q = _params(means, conics, opacities, g)
        det = a * c - b * b
        finite = np.isfinite(det) and np.isfinite(o) and np.isfinite(mx) and np.isfinite(my)
        if not (finite and a > 0.0 and det > 0.0):
            continue
        h = half_height(a, b, c, q)
        py_lo, py_hi = pixel_range(my, -h, h, 0, height - 1)
        n = 0
        if py_lo <= py_hi:
            for ty in range(py_lo // TILE, py_hi // TILE + 1):
                tx_lo, tx_hi = _tile_row_cols(mx, my, a, b, c, q, ty, width, height)
                if n == 0 and tx_lo <= tx_hi:
                    first_tile[g] = ty * tiles_x + tx_lo
                n += max(0, tx_hi - tx_lo + 1)
        counts[g] = n
        row = packed[g]
        row[0], row[1], row[2], row[3], row[4] = means[g, 0], means[g, 1], conics[g, 0], conics[g, 1], conics[g, 2]
        row[5], row[6], row[7], row[8], row[9] = opacities[g], colors[g, 0], colors[g, 1], colors[g, 2], depths[g]
        row[10], row[11] = py_lo, py_hi


@numba.njit(parallel=True, nogil=True, cache=True)
def _fill_tiles(starts, means, conics, opacities, width, height, tiles_x, first_tile, tile_of_slot):
    """Write the tile id of every (Gaussian, tile) intersection into the Gaussian's slots."""
    for g in numba.prange(means.shape[0]):
        if starts[g + 1] - starts[g] <= 1:   # none, or the one tile the count found (most Gaussians)
            if starts[g + 1] > starts[g]:
                tile_of_slot[starts[g]] = first_tile[g]
            continue
        mx, my, a, b, c, q = _params(means, conics, opacities, g)
        h = half_height(a, b, c, q)
        py_lo, py_hi = pixel_range(my, -h, h, 0, height - 1)
        k = starts[g]
        for ty in range(py_lo // TILE, py_hi // TILE + 1):
            tx_lo, tx_hi = _tile_row_cols(mx, my, a, b, c, q, ty, width, height)
            for tx in range(tx_lo, tx_hi + 1):
                tile_of_slot[k] = ty * tiles_x + tx
                k += 1


@numba.njit(nogil=True, cache=True)
def _bucket_by_tile(order, starts, tile_of_slot, n_tiles, offsets, gauss_ids, slot_of):
    """Counting sort of intersections by tile, visiting Gaussians in depth order so tile lists come out sorted."""
    for k in range(tile_of_slot.shape[0]):
        offsets[tile_of_slot[k] + 1] += 1
    for t in range(n_tiles):
        offsets[t + 1] += offsets[t]
    cursor = offsets[:-1].copy()
    for g in order:
        for k in range(starts[g], starts[g + 1]):
            t = tile_of_slot[k]
            gauss_ids[cursor[t]] = g
            slot_of[cursor[t]] = k
            cursor[t] += 1


@numba.njit(nogil=True, cache=True)
def _depth_order(depths, counts) -> np.ndarray:
    """Indices of Gaussians with counts > 0 by ascending depth, ties by index: LSD radix sort on float bits."""
    idx = np.flatnonzero(counts > 0).astype(np.int32)
    keys = np.empty(idx.shape[0], np.uint32)
    for j in range(idx.shape[0]):
        bits = np.uint32(np.float32(depths[idx[j]]).view(np.uint32))
        keys[j] = ~bits if bits >> np.uint32(31) else bits | np.uint32(0x80000000)  # order-preserving map
    tmp_idx = np.empty_like(idx)
    tmp_keys = np.empty_like(keys)
    for shift in range(0, 32, 8):
        hist = np.zeros(257, np.int64)
        for j in range(keys.shape[0]):
            hist[((keys[j] >> np.uint32(shift)) & np.uint32(255)) + 1] += 1
        for d in range(256):
            hist[d + 1] += hist[d]
        for j in range(keys.shape[0]):
            d = (keys[j] >> np.uint32(shift)) & np.uint32(255)
            tmp_idx[hist[d]] = idx[j]
            tmp_keys[hist[d]] = keys[j]
            hist[d] += 1
        idx, tmp_idx = tmp_idx, idx
        keys, tmp_keys = tmp_keys, keys
    return idx


def bin_gaussians(means2d: np.ndarray, conics: np.ndarray, colors: np.ndarray, opacities: np.ndarray,
                  depths: np.ndarray, width: int, height: int, alloc: Allocator = fresh) -> TileBins:
    """Bin float32 Gaussians into 16x16 tiles; culled Gaussians (see reference.gaussian_is_drawable) get none.

    ``alloc`` gives the bins' arrays: new ones by default, or reused scratch memory (``parksim.render.scratch``)
    for callers that drop the bins at once (inference), never for a backward pass.
    """
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    m = means2d.shape[0]
    packed = alloc("bins.packed", (m, PACKED), np.float32)
    counts = alloc("bins.counts", (m,), np.int64)
    first_tile = alloc("bins.first_tile", (m,), np.int32)
    _count_and_pack(means2d, conics, colors, opacities, depths, width, height, tiles_x, packed, counts, first_tile)
    starts = alloc("bins.starts", (m + 1,), np.int64)
    starts[0] = 0
    np.cumsum(counts, out=starts[1:])
    n_isect = int(starts[-1])
    tile_of_slot = alloc("bins.tile_of_slot", (n_isect,), np.int32)
    _fill_tiles(starts, means2d, conics, opacities, width, height, tiles_x, first_tile, tile_of_slot)
    order = _depth_order(depths, counts)
    offsets = alloc("bins.offsets", (tiles_x * tiles_y + 1,), np.int64)
    offsets[:] = 0
    gauss_ids = alloc("bins.gauss_ids", (n_isect,), np.int32)
    slot_of = alloc("bins.slot_of", (n_isect,), np.int64)
    _bucket_by_tile(order, starts, tile_of_slot, tiles_x * tiles_y, offsets, gauss_ids, slot_of)
    if np.diff(offsets).max(initial=0) >= MAX_PER_TILE:
        raise ValueError(f"more than {MAX_PER_TILE} Gaussians in one tile")
    return TileBins(offsets, gauss_ids, packed, starts, slot_of, tiles_x, tiles_y)
