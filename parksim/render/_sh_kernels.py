"""Numba kernels for view-dependent colour: the real SH basis, and a camera's colours with their gradients.

The differentiable path's colour step (gather the visible Gaussians' SH, view directions, basis, a
[M, K] x [M, K, 3] contraction) cost more in torch than the projection kernels themselves: small batched
matrix products and a dozen elementwise ops, each with its own backward. Here each Gaussian is one loop
iteration, and the backward writes straight into the full-size gradients (no gather, no scatter-add).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..gaussians import SH_C0
from .sh import _C1, _C2, _C3

__all__ = ["sh_basis", "colors_forward", "colors_backward", "TINY_DISTANCE"]

TINY_DISTANCE = 1e-12
"""View distances are clamped here: a Gaussian centred on the camera gets some direction, never a NaN."""


@numba.njit(inline="always", cache=True)
def sh_basis(degree: int, x: float, y: float, z: float, basis: np.ndarray) -> int:
    """Real SH basis of unit direction ``(x, y, z)`` up to ``degree`` into ``basis``; returns its length."""
    basis[0] = SH_C0
    if degree < 1:
        return 1
    basis[1], basis[2], basis[3] = -_C1 * y, _C1 * z, -_C1 * x
    if degree < 2:
        return 4
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    basis[4], basis[5], basis[6] = _C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy)
    basis[7], basis[8] = _C2[3] * xz, _C2[4] * (xx - yy)
    if degree < 3:
        return 9
    basis[9], basis[10] = _C3[0] * y * (3 * xx - yy), _C3[1] * xy * z
    basis[11], basis[12] = _C3[2] * y * (4 * zz - xx - yy), _C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
    basis[13], basis[14] = _C3[4] * x * (4 * zz - xx - yy), _C3[5] * z * (xx - yy)
    basis[15] = _C3[6] * x * (xx - 3 * yy)
    return 16


@numba.njit(inline="always", cache=True)
def _basis_vjp(degree: int, x: float, y: float, z: float, g: np.ndarray) -> tuple[float, float, float]:
    """sum_k g[k] d basis_k / d(x, y, z), the direction's components taken as independent (as autograd does)."""
    gx, gy, gz = -_C1 * g[3], -_C1 * g[1], _C1 * g[2]
    if degree < 2:
        return gx, gy, gz
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    a, b, c, d, e = _C2[0] * g[4], _C2[1] * g[5], _C2[2] * g[6], _C2[3] * g[7], _C2[4] * g[8]
    gx += a * y - 2 * c * x + d * z + 2 * e * x
    gy += a * x + b * z - 2 * c * y - 2 * e * y
    gz += b * y + 4 * c * z + d * x
    if degree < 3:
        return gx, gy, gz
    h9, h10, h11, h12 = _C3[0] * g[9], _C3[1] * g[10], _C3[2] * g[11], _C3[3] * g[12]
    h13, h14, h15 = _C3[4] * g[13], _C3[5] * g[14], _C3[6] * g[15]
    gx += (6 * h9 * xy + h10 * yz - 2 * h11 * xy - 6 * h12 * xz + h13 * (4 * zz - 3 * xx - yy)
           + 2 * h14 * xz + h15 * (3 * xx - 3 * yy))
    gy += (h9 * (3 * xx - 3 * yy) + h10 * xz + h11 * (4 * zz - xx - 3 * yy) - 6 * h12 * yz - 2 * h13 * xy
           - 2 * h14 * yz - 6 * h15 * xy)
    gz += h10 * xy + 8 * h11 * yz + h12 * (6 * zz - 3 * xx - 3 * yy) + 8 * h13 * xz + h14 * (xx - yy)
    return gx, gy, gz


@numba.njit(inline="always", cache=True)
def _view(means: np.ndarray, g: int, centre: np.ndarray) -> tuple[float, float, float, float]:
    """Offset of Gaussian g from the camera centre and its clamped length."""
    vx, vy, vz = means[g, 0] - centre[0], means[g, 1] - centre[1], means[g, 2] - centre[2]
    return vx, vy, vz, max(math.sqrt(vx * vx + vy * vy + vz * vz), TINY_DISTANCE)


CHUNK = 4096
"""Gaussians per parallel work item (the basis buffers are allocated once per chunk, not per Gaussian)."""


@numba.njit(parallel=True, cache=True)
def colors_forward(keep: np.ndarray, means: np.ndarray, centre: np.ndarray, sh: np.ndarray, degree: int,
                   rgb: np.ndarray) -> None:
    """rgb[i] = max(basis(d_i) . sh[keep[i]] + 0.5, 0), d_i the unit direction from ``centre`` to the Gaussian."""
    for chunk in numba.prange((keep.shape[0] + CHUNK - 1) // CHUNK):
        basis = np.empty(16, means.dtype)
        for i in range(chunk * CHUNK, min(keep.shape[0], (chunk + 1) * CHUNK)):
            g = keep[i]
            vx, vy, vz, n = _view(means, g, centre)
            k_used = sh_basis(degree, vx / n, vy / n, vz / n, basis)
            r, gr, b = 0.5, 0.5, 0.5
            for k in range(k_used):
                r += basis[k] * sh[g, k, 0]
                gr += basis[k] * sh[g, k, 1]
                b += basis[k] * sh[g, k, 2]
            rgb[i, 0], rgb[i, 1], rgb[i, 2] = max(r, 0.0), max(gr, 0.0), max(b, 0.0)


@numba.njit(parallel=True, cache=True)
def colors_backward(keep: np.ndarray, means: np.ndarray, centre: np.ndarray, sh: np.ndarray, degree: int,
                    rgb: np.ndarray, grad_rgb: np.ndarray, grad_sh: np.ndarray, grad_means: np.ndarray) -> None:
    """Gradients of ``colors_forward`` into rows keep[i] of zeroed grad_sh and grad_means (keep is unique)."""
    for chunk in numba.prange((keep.shape[0] + CHUNK - 1) // CHUNK):
        basis = np.empty(16, means.dtype)
        g_basis = np.zeros(16, means.dtype)   # entries past the degree's basis stay 0
        for i in range(chunk * CHUNK, min(keep.shape[0], (chunk + 1) * CHUNK)):
            g = keep[i]
            vx, vy, vz, n = _view(means, g, centre)
            x, y, z = vx / n, vy / n, vz / n
            k_used = sh_basis(degree, x, y, z, basis)
            # clamped at 0 (an unclamped exact 0 too) passes no gradient
            g0 = grad_rgb[i, 0] if rgb[i, 0] > 0.0 else 0.0
            g1 = grad_rgb[i, 1] if rgb[i, 1] > 0.0 else 0.0
            g2 = grad_rgb[i, 2] if rgb[i, 2] > 0.0 else 0.0
            for k in range(k_used):
                grad_sh[g, k, 0], grad_sh[g, k, 1], grad_sh[g, k, 2] = basis[k] * g0, basis[k] * g1, basis[k] * g2
                g_basis[k] = sh[g, k, 0] * g0 + sh[g, k, 1] * g1 + sh[g, k, 2] * g2
            gx, gy, gz = _basis_vjp(degree, x, y, z, g_basis) if degree > 0 else (0.0, 0.0, 0.0)
            radial = x * gx + y * gy + z * gz if n > TINY_DISTANCE else 0.0   # the clamped length passes none
            gx, gy, gz = (gx - x * radial) / n, (gy - y * radial) / n, (gz - z * radial) / n
            grad_means[g, 0], grad_means[g, 1], grad_means[g, 2] = gx, gy, gz
