"""The numba colour step (``render.view_colors``) against its torch version in float64."""

from __future__ import annotations

import pytest
import torch

from parksim.render.view_colors import _ViewColors, view_colors, view_colors_torch

N, M, K = 300, 200, 16


def _inputs(dtype: torch.dtype, seed: int, on_centre: bool = True
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """SH with some colours clamped at 0, means around the centre (one exactly on it), unique keep rows."""
    g = torch.Generator().manual_seed(seed)
    sh = torch.randn(N, K, 3, generator=g, dtype=torch.float64) * 2.0
    means = torch.randn(N, 3, generator=g, dtype=torch.float64) * 3.0
    centre = torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64)
    keep = torch.randperm(N, generator=g)[:M]
    if on_centre:   # a Gaussian on the camera: some direction, no NaN
        means[keep[0]] = centre
    return sh.to(dtype), means.to(dtype), keep, centre.to(dtype)


def _grads(fn, sh: torch.Tensor, means: torch.Tensor, keep: torch.Tensor, centre: torch.Tensor, degree: int,
           weights: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Colours and the gradients of (colours * weights).sum() in sh, means and centre."""
    leaves = [t.detach().clone().requires_grad_() for t in (sh, means, centre)]
    rgb = fn(leaves[0], leaves[1], keep, leaves[2], degree)
    (rgb.double() * weights).sum().backward()
    # degree 0 has no direction in torch's graph: no gradient there means zero
    return (rgb.detach(), *(torch.zeros_like(t) if t.grad is None else t.grad for t in leaves))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_matches_torch_in_float64(degree: int) -> None:
    sh, means, keep, centre = _inputs(torch.float64, degree)
    weights = torch.randn(M, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    got = _grads(_ViewColors.apply, sh, means, keep, centre, degree, weights)
    want = _grads(view_colors_torch, sh, means, keep, centre, degree, weights)
    assert (want[0] == 0).any() and (want[0] > 0).any()   # the clamp is exercised
    for name, a, b in zip(("rgb", "sh", "means", "centre"), got, want):
        assert torch.isfinite(a).all(), name
        # float64 summation order differs: allow a few ulp of the largest magnitude compared
        tol = 64 * torch.finfo(torch.float64).eps * max(1.0, b.abs().max().item())
        assert (a - b).abs().max().item() <= tol, name


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


# On the CPU, float32 inputs are rounded once, then the kernel sums in float64 and rounds once more: measured
# within 2 eps of the largest magnitude compared over seeds; 16 eps leaves room for other hosts' rounding.
# On CUDA the torch path sums the 16 SH terms (and the normalisation's gradient) in float32: each partial sum
# rounds, which adds up to 16 more eps of the largest term; 64 eps bounds both.
@pytest.mark.parametrize("device,ulps", [("cpu", 16), pytest.param("cuda", 64, marks=CUDA)])
def test_float32_within_its_rounding_of_float64(device: str, ulps: int) -> None:
    sh, means, keep, centre = _inputs(torch.float64, 5, on_centre=False)
    weights = torch.randn(M, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    want = _grads(view_colors_torch, sh, means, keep, centre, 3, weights)
    sh32, means32, centre32 = (t.float().to(device) for t in (sh, means, centre))
    got = _grads(view_colors, sh32, means32, keep.to(device), centre32, 3, weights.to(device))
    assert got[0].dtype == torch.float32 and got[0].device.type == device
    eps = torch.finfo(torch.float32).eps
    for name, a, b in zip(("rgb", "sh", "means", "centre"), got, want):
        assert torch.isfinite(a).all(), name
        assert (a.cpu().double() - b).abs().max().item() <= ulps * eps * max(1.0, b.abs().max().item()), name


def test_gradient_only_on_kept_rows() -> None:
    sh, means, keep, centre = _inputs(torch.float32, 1)
    _, g_sh, g_means, _ = _grads(view_colors, sh, means, keep, centre, 3, torch.ones(M, 3, dtype=torch.float64))
    others = torch.ones(N, dtype=torch.bool)
    others[keep] = False
    assert (g_sh[others] == 0).all() and (g_means[others] == 0).all()
    assert (g_sh[keep].abs().sum((1, 2)) > 0).any()
