"""Photometric loss of 3DGS, (1 - lambda) L1 + lambda D-SSIM, averaged over a mask of valid pixels.

Images are ``[B, 3, H, W]`` in [0, 1]; masks ``[B, 1, H, W]`` (1 = scene pixel). Averaging only over
valid pixels keeps black lens corners and the ego car from pulling Gaussians towards them.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from . import _ssim_kernels as kernels

__all__ = ["masked_mean", "ssim_map", "l1_loss", "dssim_loss", "dssim_torch", "photometric_loss", "sum_terms",
           "SSIM_WINDOW"]

SSIM_WINDOW = 11
"""Gaussian window of SSIM (the 3DGS and kornia default), sigma 1.5."""
_SSIM_SIGMA = 1.5
_C1, _C2 = 0.01 ** 2, 0.03 ** 2


def _gaussian_window() -> Tensor:
    x = torch.arange(SSIM_WINDOW, dtype=torch.float32) - SSIM_WINDOW // 2
    g = torch.exp(-x * x / (2 * _SSIM_SIGMA ** 2))
    return g / g.sum()


_WINDOW = _gaussian_window()
_DEVICE_WINDOWS: dict[tuple[torch.device, torch.dtype], Tensor] = {}


def _window_like(x: Tensor) -> Tensor:
    """The SSIM taps in ``x``'s dtype on its device: converted on each call on the CPU as ever, copied once to a GPU
    (a host-to-device copy in every step would wait for the GPU)."""
    if x.device.type == "cpu":
        return _WINDOW.to(x)
    key = (x.device, x.dtype)
    if key not in _DEVICE_WINDOWS:
        _DEVICE_WINDOWS[key] = _WINDOW.to(x)
    return _DEVICE_WINDOWS[key]


def masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Mean of ``values [B, C, H, W]`` over pixels where ``mask [B, 1, H, W]`` is set (weights allowed)."""
    weight = mask.expand_as(values)
    return (values * weight).sum() / weight.sum().clamp(min=1.0)


def ssim_map(pred: Tensor, gt: Tensor) -> Tensor:
    """Per-pixel SSIM ``[B, C, H, W]``, 11x11 Gaussian window, reflect padding: ``kornia.metrics.ssim``'s values.

    The five local moments are filtered in one grouped separable convolution (2-3x faster on the CPU
    than kornia's five filter calls, which dominated an iteration).
    """
    c = pred.shape[1]
    stack = torch.cat([pred, gt, pred * pred, gt * gt, pred * gt], dim=1)
    n, w = stack.shape[1], _window_like(pred)
    r = SSIM_WINDOW // 2
    stack = F.pad(stack, (r, r, r, r), mode="reflect")
    stack = F.conv2d(stack, w.view(1, 1, 1, -1).expand(n, 1, 1, -1), groups=n)
    mu_p, mu_g, pp, gg, pg = F.conv2d(stack, w.view(1, 1, -1, 1).expand(n, 1, -1, 1), groups=n).split(c, dim=1)
    var_p, var_g, cov = pp - mu_p * mu_p, gg - mu_g * mu_g, pg - mu_p * mu_g
    return ((2 * mu_p * mu_g + _C1) * (2 * cov + _C2)) / ((mu_p * mu_p + mu_g * mu_g + _C1) * (var_p + var_g + _C2))


def l1_loss(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """Masked mean absolute error."""
    return masked_mean((pred - gt).abs(), mask)


class _DSSIM(torch.autograd.Function):
    """Masked D-SSIM by the numba kernels, differentiable in the prediction (the training case)."""

    @staticmethod
    def forward(ctx: Any, pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
        b, c, h, w = pred.shape
        planes = [np.ascontiguousarray(t.detach().reshape(b * c, h, w).numpy()) for t in (pred, gt.to(pred))]
        dtype = planes[0].dtype
        taps, consts = _WINDOW.numpy().astype(dtype), np.array([2.0, _C1, _C2], dtype)
        moments, ssim = np.empty((b * c, 5, h, w), dtype), np.empty((b * c, h, w), dtype)
        kernels.dssim_forward(planes[0], planes[1], taps, consts, moments, ssim)
        weight = mask.detach().to(pred).expand(b, c, h, w)
        denom = weight.sum().clamp(min=1.0)
        ctx.state = (planes, taps, consts, moments, ssim, weight, denom)
        return 1.0 - (torch.from_numpy(ssim).view(b, c, h, w) * weight).sum() / denom

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        planes, taps, consts, moments, ssim, weight, denom = ctx.state
        grad_ssim = np.ascontiguousarray((-grad * weight / denom).reshape(ssim.shape).numpy())
        grad_pred = np.empty_like(planes[0])
        kernels.dssim_backward(planes[0], planes[1], taps, consts, moments, ssim, grad_ssim, grad_pred)
        return torch.from_numpy(grad_pred).view(weight.shape), None, None


def dssim_torch(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """Masked 1 - SSIM in torch operations only: on any device, differentiable in every input.

    ``dssim_loss``'s path off the CPU (the GPU trainer's D-SSIM) and wherever the numba kernels do not apply.

    Args:
        pred: ``[B, C, H, W]`` rendered images in [0, 1].
        gt: ``[B, C, H, W]`` targets, same device.
        mask: ``[B, 1, H, W]`` pixel weights (1 = scene pixel), same device.

    Returns:
        A scalar tensor on the images' device.
    """
    return 1.0 - masked_mean(ssim_map(pred, gt), mask)


def dssim_loss(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """Masked 1 - SSIM (the D-SSIM term of 3DGS).

    On the CPU, with a gradient wanted in ``pred`` only, the numba kernels compute it (a fused forward and an
    adjoint blur in the backward; 3x faster than torch's convolutions); otherwise (CUDA, a gradient in ``gt``,
    images too small to reflect-pad, which torch then reports), and as the tests' reference, ``dssim_torch``.
    """
    fused = (pred.device.type == "cpu" and pred.dtype in (torch.float32, torch.float64)
             and not gt.requires_grad and not mask.requires_grad and min(pred.shape[-2:]) > SSIM_WINDOW // 2)
    if fused:
        return _DSSIM.apply(pred, gt, mask)
    return dssim_torch(pred, gt, mask)


def photometric_loss(pred: Tensor, gt: Tensor, mask: Tensor, ssim_lambda: float) -> Tensor:
    """The paper's L_rgb: (1 - lambda) L1 + lambda D-SSIM, lambda = 0.2 by default."""
    return (1.0 - ssim_lambda) * l1_loss(pred, gt, mask) + ssim_lambda * dssim_loss(pred, gt, mask)


def sum_terms(terms: Iterable[Tensor]) -> Tensor:
    """Sum of one or more loss tensors, added left to right as ``sum()`` would, but typed ``Tensor`` (not ``| int``)."""
    return functools.reduce(operator.add, terms)
