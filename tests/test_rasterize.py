"""Rasterizer backends against the dense float64 torch reference: forward values, gradients, edge cases."""

from __future__ import annotations

import math

import pytest
import torch

from parksim.render.rasterize import ALPHA_MIN, T_MIN, rasterize, rasterize_reference, resolve_backend

W, H = 37, 29  # not multiples of the 16-pixel tile


def make_scene(n: int, seed: int, sigma: tuple[float, float] = (0.5, 6.0), opacity: tuple[float, float] = (0.05, 1.0),
               margin: float = 8.0, center: tuple[float, float] | None = None,
               spread: float = 0.0, aspect: tuple[float, float] = (0.3, 1.0)) -> list[torch.Tensor]:
    """Random anisotropic screen-space Gaussians as float64 tensors: means, conics, colors, opacities, depths."""
    g = torch.Generator().manual_seed(seed)

    def uniform(lo: float, hi: float, *shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=torch.float64) * (hi - lo) + lo

    if center is None:
        means = torch.stack([uniform(-margin, W + margin, n), uniform(-margin, H + margin, n)], -1)
    else:
        means = torch.tensor(center, dtype=torch.float64) + uniform(-spread, spread, n, 2)
    s1 = torch.exp(uniform(math.log(sigma[0]), math.log(sigma[1]), n))
    s2 = s1 * uniform(*aspect, n)
    theta = uniform(0.0, math.pi, n)
    cos, sin = torch.cos(theta), torch.sin(theta)
    i1, i2 = 1.0 / s1**2, 1.0 / s2**2
    conics = torch.stack([cos**2 * i1 + sin**2 * i2, cos * sin * (i1 - i2), sin**2 * i1 + cos**2 * i2], -1)
    colors = uniform(0.0, 1.0, n, 3)
    opacities = uniform(*opacity, n)
    depths = uniform(1.0, 3.0, n)
    # Round to float32 once so both sides see the same numbers.
    return [t.float().double() for t in (means, conics, colors, opacities, depths)]


SCENES = {
    "random": dict(n=300, seed=0),
    "tiny_subpixel": dict(n=400, seed=1, sigma=(0.15, 0.8)),
    "huge": dict(n=12, seed=2, sigma=(20.0, 80.0), opacity=(0.05, 0.5)),
    "opaque_early_stop": dict(n=300, seed=3, sigma=(3.0, 10.0), opacity=(0.9, 1.0)),
    "off_screen": dict(n=200, seed=4, margin=40.0),
    "overlapping": dict(n=400, seed=5, sigma=(1.0, 4.0), opacity=(0.02, 0.3), center=(18.0, 14.0), spread=3.0),
    "needles": dict(n=200, seed=6, sigma=(1.0, 30.0), aspect=(0.05, 0.2)),   # thinner: float32 conics lose digits
}


def reference64(scene: list[torch.Tensor], bg: torch.Tensor | None = None):
    """Forward outputs and the inputs (as leaves) of the float64 reference."""
    leaves = [t.clone().requires_grad_(i < 4) for i, t in enumerate(scene)]
    return rasterize_reference(*leaves, W, H, bg=bg), leaves


def numba32(scene: list[torch.Tensor], bg: torch.Tensor | None = None):
    """Forward outputs and the float32 leaves of the numba backend."""
    leaves = [t.float().requires_grad_(i < 4) for i, t in enumerate(scene)]
    return rasterize(*leaves, W, H, backend="numba", bg=None if bg is None else bg.float()), leaves


def loss_weights(seed: int) -> list[torch.Tensor]:
    """Fixed random weights so the loss touches rgb, alpha and depth."""
    g = torch.Generator().manual_seed(100 + seed)
    return [torch.randn(H, W, 3, generator=g, dtype=torch.float64), torch.randn(H, W, generator=g, dtype=torch.float64),
            torch.randn(H, W, generator=g, dtype=torch.float64)]


def weighted_loss(outputs, weights) -> torch.Tensor:
    """sum of outputs * weights over rgb, alpha and depth."""
    return sum((o.double() * w).sum() for o, w in zip(outputs, weights))


@pytest.mark.parametrize("name", list(SCENES))
@pytest.mark.parametrize("with_bg", [False, True])
def test_numba_matches_reference(name: str, with_bg: bool) -> None:
    scene = make_scene(**SCENES[name])
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64) if with_bg else None
    ref_out, ref_leaves = reference64(scene, bg)
    out, leaves = numba32(scene, bg)
    for got, want in zip(out, ref_out):
        assert got.dtype == torch.float32
        assert torch.isfinite(got).all()
        assert (got.double() - want).abs().max().item() <= 1e-5

    weights = loss_weights(SCENES[name]["seed"])
    weighted_loss(ref_out, weights).backward()
    weighted_loss(out, weights).backward()
    for label, got, want in zip(("means2d", "conics", "colors", "opacities"), leaves, ref_leaves):
        assert torch.isfinite(got.grad).all(), label
        scale = want.grad.abs().max().item()
        err = (got.grad.double() - want.grad).abs().max().item()
        assert err <= 1e-3 * scale + 1e-9, f"{label}: max error {err:.3g} vs max |grad| {scale:.3g}"


def test_depth_gradient_matches_reference() -> None:
    scene = make_scene(**SCENES["random"])
    leaves = [t.float().requires_grad_() for t in scene]
    ref_depths = scene[4].clone().requires_grad_()
    ref_out = rasterize_reference(*scene[:4], ref_depths, W, H)
    out = rasterize(*leaves, W, H, backend="numba")
    ref_out[2].sum().backward()
    out[2].sum().backward()
    err = (leaves[4].grad.double() - ref_depths.grad).abs().max().item()
    assert err <= 1e-3 * ref_depths.grad.abs().max().item()


def test_early_termination_is_active() -> None:
    scene = make_scene(**SCENES["opaque_early_stop"])
    ref_rgb, ref_alpha, _ = rasterize_reference(*scene, W, H)
    alpha = rasterize(*[t.float() for t in scene], W, H, backend="numba")[1]
    saturated = ref_alpha > 1.0 - 2 * T_MIN
    assert saturated.float().mean() > 0.5  # most pixels stopped early
    assert (alpha.double() <= 1.0 - T_MIN + 1e-6).all()  # never composited past the stop
    assert (alpha.double() - ref_alpha).abs().max() <= 1e-5


def test_empty_and_culled_inputs() -> None:
    empty = [torch.zeros(0, 2), torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0)]
    for backend in ("torch", "numba"):
        rgb, alpha, depth = rasterize(*empty, W, H, backend=backend, bg=torch.tensor([1.0, 0.0, 0.5]))
        assert rgb.shape == (H, W, 3) and alpha.shape == (H, W) and depth.shape == (H, W)
        assert torch.equal(rgb, torch.tensor([1.0, 0.0, 0.5]).expand(H, W, 3))
        assert alpha.abs().max() == 0 and depth.abs().max() == 0
    # Non positive definite conic and sub-threshold opacity are culled by both backends.
    means = torch.tensor([[10.0, 10.0], [20.0, 12.0]])
    conics = torch.tensor([[0.1, 0.5, 0.1], [0.1, 0.0, 0.1]])
    opacities = torch.tensor([0.9, 0.5 * ALPHA_MIN])
    args = (means, conics, torch.rand(2, 3), opacities, torch.ones(2), W, H)
    for backend in ("torch", "numba"):
        rgb, alpha, _ = rasterize(*args, backend=backend)
        assert alpha.abs().max() == 0 and torch.isfinite(rgb).all()


def test_backward_with_no_contribution_is_zero() -> None:
    scene = [t.float().requires_grad_(i < 4) for i, t in enumerate(make_scene(50, seed=7))]
    with torch.no_grad():
        scene[0] += 1000.0  # everything far off screen
    out = rasterize(*scene, W, H, backend="numba")
    weighted_loss(out, loss_weights(0)).backward()
    for leaf in scene[:4]:
        assert leaf.grad is not None and leaf.grad.abs().max() == 0


def test_backend_selection_and_validation() -> None:
    assert resolve_backend("auto", torch.device("cpu")) == "numba"
    assert resolve_backend("torch", torch.device("cpu")) == "torch"
    with pytest.raises(ValueError):
        resolve_backend("opengl", torch.device("cpu"))
    scene = [t.float() for t in make_scene(5, seed=8)]
    with pytest.raises(ValueError):
        rasterize(scene[0], scene[1][:, :2], *scene[2:], W, H)
    rgb_auto = rasterize(*scene, W, H)[0]
    rgb_numba = rasterize(*scene, W, H, backend="numba")[0]
    assert torch.equal(rgb_auto, rgb_numba)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat backend needs CUDA")
def test_gsplat_matches_numba() -> None:
    pytest.importorskip("gsplat")
    scene = [t.float() for t in make_scene(**SCENES["random"])]
    cpu = rasterize(*scene, W, H, backend="numba")
    gpu = rasterize(*[t.cuda() for t in scene], W, H, backend="gsplat")
    for got, want in zip(gpu, cpu):
        assert (got.cpu() - want).abs().max() <= 1e-3


def _image(seed: int, width: int, height: int, n: int):
    """A random float32 compositor input (``cpu.Image``) of ``n`` Gaussians spread over a width x height image."""
    import numpy as np

    from parksim.render.rasterize.cpu import Image

    scene = make_scene(n, seed, sigma=(0.5, 12.0))
    scene[0] = scene[0] * torch.tensor([width / W, height / H], dtype=torch.float64)
    return Image(*(np.ascontiguousarray(t.float().numpy()) for t in scene), width, height)


def test_composite_many_equals_one_image_at_a_time() -> None:
    """Images composited side by side, one per worker thread, give bit for bit what each image composited alone
    over all threads gives (sizes differ, and are not multiples of the tile)."""
    import numba

    from parksim.render.rasterize.cpu import composite, composite_many

    images = [_image(10 + k, w, h, n) for k, (w, h, n) in enumerate([(130, 97, 4000), (64, 48, 300),
                                                                        (161, 120, 6000), (33, 17, 50)])]
    previous = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        got = composite_many(images, lambda k, *planes: (k, *(p.copy() for p in planes)))
    finally:
        numba.set_num_threads(previous)
    for k, image in enumerate(images):
        ref = composite(*image)[2:5]
        assert got[k][0] == k
        assert all(mine.shape == r.shape and (mine == r).all() for mine, r in zip(got[k][1:], ref))
