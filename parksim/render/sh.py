"""View-dependent colour from real spherical harmonics, with the standard 3DGS constants."""

from __future__ import annotations

import torch
from torch import Tensor

from ..gaussians import SH_C0

__all__ = ["sh_basis", "eval_sh"]

_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Basis values ``[..., (degree+1)^2]`` for unit directions ``dirs[..., 3]`` (3DGS ordering and signs)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz, _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_C3[0] * y * (3 * xx - yy), _C3[1] * xy * z, _C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(sh: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """RGB ``[N, 3]`` from coefficients ``sh[N, K, 3]`` seen along unit ``dirs[N, 3]``.

    Computes basis . sh + 0.5, clamped at 0."""
    basis = sh_basis(dirs, degree)
    rgb = torch.einsum("nk,nkc->nc", basis, sh[:, : basis.shape[-1]])
    return torch.clamp_min(rgb + 0.5, 0.0)
