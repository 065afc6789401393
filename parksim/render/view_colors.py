"""The differentiable path's colour step: SH colours of a camera's visible Gaussians along its view directions.

On the CPU it runs the numba kernels of ``_sh_kernels`` inside one autograd Function (measured: the torch
version's batched products and their backward were the largest torch cost of a training step); elsewhere
(CUDA) it runs ``sh.eval_sh`` on the gathered rows, which is also the float64 reference the tests use.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from . import _sh_kernels as kernels
from .project_fast import _np
from .sh import eval_sh

__all__ = ["view_colors", "view_colors_torch"]


def view_colors_torch(sh: Tensor, means: Tensor, keep: Tensor, centre: Tensor, degree: int) -> Tensor:
    """``view_colors`` in torch ops (any device): gather, normalise the view directions, ``eval_sh``."""
    dirs = means.index_select(0, keep) - centre
    # A Gaussian centred exactly on the camera has no view direction: any unit vector does.
    unit = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(kernels.TINY_DISTANCE)
    return eval_sh(sh.index_select(0, keep), unit, degree)


class _ViewColors(torch.autograd.Function):
    """CPU colours by the numba kernels; the backward writes full-size gradients for sh and means directly."""

    @staticmethod
    def forward(ctx: Any, sh: Tensor, means: Tensor, keep: Tensor, centre: Tensor, degree: int) -> Tensor:
        keep_np, means_np = _np(keep).astype(np.int64, copy=False), _np(means)
        rgb = np.empty((keep_np.shape[0], 3), means_np.dtype)
        kernels.colors_forward(keep_np, means_np, _np(centre), _np(sh), degree, rgb)
        ctx.degree = degree
        out = torch.from_numpy(rgb)
        ctx.save_for_backward(sh, means, keep, centre, out)
        return out

    @staticmethod
    def backward(ctx: Any, grad_rgb: Tensor) -> tuple[Tensor | None, ...]:
        sh, means, keep, centre, rgb = ctx.saved_tensors
        grad_sh = np.zeros(tuple(sh.shape), _np(sh).dtype)
        grad_means = np.zeros(tuple(means.shape), _np(means).dtype)
        kernels.colors_backward(_np(keep).astype(np.int64, copy=False), _np(means), _np(centre), _np(sh),
                                ctx.degree, _np(rgb), _np(grad_rgb.to(rgb.dtype)), grad_sh, grad_means)
        g_means = torch.from_numpy(grad_means)
        # the centre moves every view offset against the means: minus their gradient's sum (rows not kept are 0)
        grad_centre = -g_means.sum(0) if ctx.needs_input_grad[3] else None
        return torch.from_numpy(grad_sh), g_means, None, grad_centre, None


def view_colors(sh: Tensor, means: Tensor, keep: Tensor, centre: Tensor, degree: int) -> Tensor:
    """RGB ``[M, 3]`` of Gaussians ``keep`` (unique indices) seen from camera centre ``centre`` (world frame).

    ``max(basis(d) . sh[keep] + 0.5, 0)`` with ``d`` the unit direction from the centre to each mean;
    differentiable in ``sh [N, K, 3]``, ``means [N, 3]`` and ``centre [3]``.
    """
    if means.device.type != "cpu":
        return view_colors_torch(sh, means, keep, centre, degree)
    return _ViewColors.apply(sh, means, keep, centre, degree)
