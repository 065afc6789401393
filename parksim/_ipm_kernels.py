"""Numba kernel of the IPM's inference path: each BEV pixel's bilinear taps, gathered and blended (no autograd).

``IPM`` precomputes, per camera, the four neighbouring pixels of every tap and their bilinear weights times
the camera's blend weight (zero for a neighbour outside the image: ``grid_sample``'s zero padding), so a
BEV is a sparse gather-sum; training keeps the differentiable ``grid_sample`` path it is tested against.
"""

from __future__ import annotations

from .kernel_cache import configure

configure()  # before the kernel below: its cache must match this source

import numba  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["blend_taps"]


@numba.njit(parallel=True, nogil=True, fastmath=True, cache=True)
def blend_taps(image: np.ndarray, rows: np.ndarray, idx: np.ndarray, w: np.ndarray, out: np.ndarray) -> None:
    """``out[rows[t]] += sum_j w[t, j] * image[idx[t, j]]`` for one camera's taps (``rows`` are distinct).

    ``image`` is the camera's ``[H * W, C]`` pixels, ``out`` the BEV's ``[H * W, C]`` accumulator.
    """
    for t in numba.prange(rows.shape[0]):
        r = rows[t]
        for ch in range(image.shape[1]):
            acc = np.float32(0.0)
            for j in range(4):
                acc += w[t, j] * image[idx[t, j], ch]
            out[r, ch] += acc
