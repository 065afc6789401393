"""The device projection kernels for NVIDIA GPUs (numba-cuda): thin launch wrappers around ``_device_bodies``.

One thread per (view, Gaussian) in the forward, one per Gaussian in the backward; scratch lives in thread-local
arrays. Compiled on first use for the GPU at hand and cached on disk next to the module (``cache=True``), so only the
first render after install waits for the compile (see ``docs/gpu.md``). Importing this module needs numba-cuda (the
``cuda`` extra); nothing imports it on a CPU-only path.
"""

from __future__ import annotations

import numpy as np

from . import _device_bodies as body
from ._numba_cuda import cuda
from ._project_kernels import N_UT

__all__ = ["views_forward", "views_backward", "THREADS"]

THREADS = 128
"""Threads per block of both kernels (local arrays make them register- and spill-heavy: small blocks occupy best)."""

_N_FIFTH, _N_BASIS = body.N_FIFTH, body.N_BASIS


@cuda.jit(cache=True)
def views_forward(means, quats, log_scales, sh, sh_degree, rots, trans, centres, models, lenses, opts,  # noqa: ANN001
                  z7, wm7, wc7, z19, wm19, wc19, out_means, out_conics, out_colors, out_depths, out_drawn):
    """``_device_bodies.view_forward`` for item ``i``: view ``i // N``, Gaussian ``i % N`` (coalesced reads)."""
    i = cuda.grid(1)
    n = means.shape[0]
    if i >= n * rots.shape[0]:
        return
    v = i // n
    q, s = cuda.local.array(5, np.float64), cuda.local.array(3, np.float64)
    R, L = cuda.local.array((3, 3), np.float64), cuda.local.array((3, 3), np.float64)
    uv7, uv19 = cuda.local.array((N_UT, 8), np.float64), cuda.local.array((_N_FIFTH, 8), np.float64)
    mom, basis = cuda.local.array((3, 5), np.float64), cuda.local.array(_N_BASIS, np.float64)
    body.view_forward(v, i - v * n, means, quats, log_scales, sh, sh_degree, rots, trans, centres, models, lenses,
                      opts, z7, wm7, wc7, z19, wm19, wc19, q, s, R, L, uv7, uv19, mom, basis, out_means, out_conics,
                      out_colors, out_depths, out_drawn)


@cuda.jit(cache=True)
def views_backward(means, quats, log_scales, sh, sh_degree, rots, trans, centres, models, lenses, opts,  # noqa: ANN001
                   z7, wm7, wc7, z19, wm19, wc19, drawn, g_means2d, g_conics, g_colors, g_depths, pose,
                   grad_means, grad_quats, grad_log_scales, grad_sh, grad_pose):
    """``_device_bodies.gaussian_backward`` for Gaussian ``i`` over every view."""
    g = cuda.grid(1)
    if g >= means.shape[0]:
        return
    q, s = cuda.local.array(5, np.float64), cuda.local.array(3, np.float64)
    R, L = cuda.local.array((3, 3), np.float64), cuda.local.array((3, 3), np.float64)
    uv7, uv19 = cuda.local.array((N_UT, 8), np.float64), cuda.local.array((_N_FIFTH, 8), np.float64)
    mom, basis = cuda.local.array((3, 5), np.float64), cuda.local.array(_N_BASIS, np.float64)
    g_basis, g_mu = cuda.local.array(_N_BASIS, np.float64), cuda.local.array(3, np.float64)
    g_L, G = cuda.local.array((3, 3), np.float64), cuda.local.array((3, 3), np.float64)
    gq, gls = cuda.local.array((1, 4), np.float64), cuda.local.array((1, 3), np.float64)
    grot, acc = cuda.local.array(9, np.float64), cuda.local.array(10, np.float64)
    for k in range(_N_BASIS):
        g_basis[k] = 0.0
    body.gaussian_backward(g, means, quats, log_scales, sh, sh_degree, rots, trans, centres, models, lenses, opts,
                           z7, wm7, wc7, z19, wm19, wc19, drawn, g_means2d, g_conics, g_colors, g_depths, pose, q, s,
                           R, L, uv7, uv19, mom, basis, g_basis, g_mu, g_L, G, gq, gls, grot, acc, grad_means,
                           grad_quats, grad_log_scales, grad_sh, grad_pose)
