"""Rotation matrices of the real SH bands that ParkSim (and 3DGS) colour Gaussians with.

Rotating a scene by an orthogonal ``R`` moves what a Gaussian shows along direction ``d`` to direction ``R d``,
so its coefficients must change to keep ``colour'(R d) = colour(d)``. Each band ``l`` spans a rotation-invariant
space of polynomials, so ``Y_l(R^T d) = Y_l(d) @ D_l`` holds exactly for a ``(2l+1)``-square ``D_l``; it is solved
here by least squares on fixed, well spread directions (exact up to float64 rounding, any sign and order
convention of ``render.sh.sh_basis`` included, reflections too).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from .render.sh import sh_basis

__all__ = ["sh_rotation", "rotate_sh"]

_DIRECTIONS = 64
"""Sample directions for the fit: 16 would determine degree 3; 64 keep every band's system well conditioned."""


def _fibonacci_sphere(n: int) -> Tensor:
    """``n`` unit directions ``[n, 3]`` (float64) spread evenly over the sphere."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt(1.0 - z * z)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=1)


def sh_rotation(R: np.ndarray | Tensor, degree: int) -> Tensor:
    """Block-diagonal float64 ``[K, K]`` (``K = (degree+1)^2``) with ``sh' = M @ sh`` for a scene turned by ``R``.

    Args:
        R: orthogonal ``(3, 3)`` (a rotation, or a reflection: ``det R = -1``).
        degree: SH degree 0..3.

    Returns:
        ``M`` such that ``sh_basis(R d) @ (M @ sh) == sh_basis(d) @ sh`` for every unit ``d``; band 0 is 1.
    """
    R = torch.as_tensor(R, dtype=torch.float64)
    dirs = _fibonacci_sphere(_DIRECTIONS)
    basis, turned = sh_basis(dirs, degree), sh_basis(dirs @ R, degree)   # rows of dirs @ R are R^T d
    M = torch.zeros(basis.shape[1], basis.shape[1], dtype=torch.float64)
    M[0, 0] = 1.0
    for band in range(1, degree + 1):
        b = slice(band * band, (band + 1) ** 2)
        # Y_l(R^T d) = Y_l(d) @ D_l; the colour at R d uses Y_l(d) = Y_l(R^T (R d)), so sh'_l = D_l @ sh_l
        M[b, b] = torch.linalg.lstsq(basis[:, b], turned[:, b]).solution
    return M


def rotate_sh(sh: Tensor, R: np.ndarray | Tensor) -> Tensor:
    """SH coefficients ``[N, K, 3]`` of Gaussians turned by the orthogonal ``R`` (float64 maths, ``sh``'s dtype)."""
    degree = math.isqrt(sh.shape[1]) - 1
    M = sh_rotation(R, degree).to(sh.device)
    return torch.einsum("ij,njc->nic", M, sh.to(torch.float64)).to(sh.dtype)
