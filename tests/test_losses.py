"""The numba D-SSIM loss (``parksim.recon.losses._DSSIM``) against the torch ``ssim_map`` path in float64."""

from __future__ import annotations

import pytest
import torch

from parksim.recon.losses import _DSSIM, SSIM_WINDOW, dssim_loss, masked_mean, ssim_map


def _reference(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return 1.0 - masked_mean(ssim_map(pred, gt), mask)


def _case(b: int, h: int, w: int, dtype: torch.dtype, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images in [0, 1] and a mask with soft weights and zeros (as the ego-car and lens masks give)."""
    g = torch.Generator().manual_seed(seed)
    pred, gt = torch.rand(b, 3, h, w, generator=g, dtype=torch.float64), torch.rand(b, 3, h, w, generator=g,
                                                                                       dtype=torch.float64)
    mask = torch.rand(b, 1, h, w, generator=g, dtype=torch.float64)
    mask[mask < 0.3] = 0.0
    return pred.to(dtype), gt.to(dtype), mask.to(dtype)


def _value_and_grad(fn, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> tuple[float, torch.Tensor]:
    leaf = pred.detach().clone().requires_grad_()
    loss = fn(leaf, gt, mask)
    loss.backward()
    return float(loss.detach()), leaf.grad


@pytest.mark.parametrize("b,h,w", [(1, 6, 6), (1, 24, 31), (2, 40, 29), (1, 13, 64)])
def test_matches_torch_in_float64(b: int, h: int, w: int) -> None:
    pred, gt, mask = _case(b, h, w, torch.float64, h * w)
    got, got_grad = _value_and_grad(_DSSIM.apply, pred, gt, mask)
    want, want_grad = _value_and_grad(_reference, pred, gt, mask)
    # sums of ~10^2-10^3 terms in another order: a few hundred float64 ulp of the magnitudes compared
    eps = torch.finfo(torch.float64).eps
    assert abs(got - want) <= 256 * eps * max(1.0, abs(want))
    assert (got_grad - want_grad).abs().max().item() <= 256 * eps * want_grad.abs().max().item()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_float32_within_its_rounding(device: str) -> None:
    """``dssim_loss`` in float32 (the numba kernels on the CPU, torch's convolutions on CUDA) against float64."""
    pred, gt, mask = _case(1, 48, 64, torch.float64, 1)
    want, want_grad = _value_and_grad(_reference, pred, gt, mask)
    got, got_grad = _value_and_grad(dssim_loss, *(t.float().to(device) for t in (pred, gt, mask)))
    assert got_grad.dtype == torch.float32 and got_grad.device.type == device and torch.isfinite(got_grad).all()
    # measured over 5 seeds on the CPU: value within 0.5 float32 eps of float64, gradient within 5 eps of its
    # largest entry (torch's own float32 path: the same); the bound leaves room for other hosts' rounding.
    eps = torch.finfo(torch.float32).eps
    assert abs(got - want) <= 64 * eps
    assert (got_grad.cpu().double() - want_grad).abs().max().item() <= 64 * eps * want_grad.abs().max().item()


def test_dispatch_keeps_torch_where_the_kernels_do_not_apply() -> None:
    pred, gt, mask = _case(1, 20, 20, torch.float64, 2)
    gt.requires_grad_()
    loss = dssim_loss(pred.requires_grad_(), gt, mask)   # a gradient in gt: the torch path
    loss.backward()
    assert gt.grad is not None and pred.grad is not None
    small = torch.rand(1, 3, SSIM_WINDOW // 2, 9)
    with pytest.raises(RuntimeError):   # too small to reflect-pad: torch's own error, not a wrong number
        dssim_loss(small, small, torch.ones(1, 1, SSIM_WINDOW // 2, 9))
