"""Fused CPU projection (numba) against the torch reference path: values, gradients, edge cases, dispatch."""

from __future__ import annotations

import math

import pytest
import torch

from parksim.camera import CameraModel, OpenCVFisheye, Pinhole, RadialPolyFisheye
from parksim.geometry import rotation_from_quaternion
from parksim.render.projection import Projected2D, UTParams, project_gaussians
from tolerances import f32_tol, f32_ulp

K = [0.05, -0.01, 0.002, -0.0005]


def cameras() -> dict[str, CameraModel]:
    """A 200 deg Kannala-Brandt lens, a 190 deg WoodScape-style lens and a 120 deg pinhole, all 640x480."""
    return {"opencv": OpenCVFisheye(640, 480, 120.0, 120.0, 319.5, 239.5, K, max_fov_deg=200.0),
            "radial": RadialPolyFisheye(640, 480, [110.0, 4.0, -3.0, 0.5], 2.0, -1.5, 1.01, max_fov_deg=190.0),
            "pinhole": Pinhole(640, 480, 300.0, 300.0, 319.5, 239.5, max_fov_deg=120.0)}


def _direction(theta_deg: float, phi_deg: float) -> list[float]:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]


def stress_rows() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means, quats, log_scales) float64 at every awkward spot of a 200 deg lens."""
    rows = [  # (position, log_scales, quat)
        ([0, 0, 5], [-2, -2, -2], [1, 0, 0, 0]),                          # on the optical axis, isotropic
        ([0, 0, 3], [-1, -1.5, -2], [0.9, 0.2, -0.3, 0.1]),                # on the axis, anisotropic
        ([1e-5, -1e-5, 4], [-2, -2.2, -2.4], [1, 0, 0, 0]),                # within axis_eps of the axis
        ([1.0, 0.0, 0.0], [-0.7, -1, -2], [1, 0.3, 0, 0]),                 # straddling the camera plane
        ([1.0, 0.2, -0.05], [-1, -1, -1], [1, 0, 0, 0]),                   # just behind the camera plane
        ([3 * v for v in _direction(85.0, 10)], [-1, -1.5, -2], [1, 1, 0, 0]),
        ([3 * v for v in _direction(92.0, 100)], [-1, -1.5, -2], [1, 0, 1, 0]),
        ([3 * v for v in _direction(99.5, 200)], [-0.5, -0.5, -0.5], [1, 0, 0, 1]),   # sigma points beyond
        ([3 * v for v in _direction(105.0, 300)], [0.0, 0.0, 0.0], [1, 0, 0, 0]),     # centre beyond
        ([0, 0, 4], [-1e3, -1e3, -1e3], [1, 0, 0, 0]),                      # zero scales
        ([0.5, 0.5, 4], [-88, -90, -100], [1, 0, 0, 0]),                    # denormal scales
        ([0.3, -0.2, 4], [-2, -2.5, -3], [0, 0, 0, 0]),                     # zero quaternion
        ([0, 0.1, 0.3], [4.6, 4.6, 4.6], [1, 0, 0, 0]),                     # 100 m wide, 0.3 m away
        ([0.2, 0.0, 0.1], [0.0, -3, -3], [0.7, 0.7, 0, 0]),                 # camera inside the Gaussian
        ([4 * v for v in _direction(80.0, 30)], [math.log(0.6), math.log(0.5), math.log(0.3)], [0.9, 0.2, -0.3, 0.1]),
        ([4 * v for v in _direction(75.0, 250)], [math.log(0.5)] * 3, [1, 0, 0, 0]),   # adaptive, isotropic (ties)
    ]
    means, log_scales, quats = (torch.tensor([r[i] for r in rows], dtype=torch.float64) for i in range(3))
    return means, quats, log_scales


def random_scene(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means, quats, log_scales) float64: all directions, 0.2-30 m, 1 mm-1 m scales, some adaptive-set ones."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    means = d / d.norm(dim=-1, keepdim=True) * (0.2 + 30 * torch.rand(n, 1, generator=g, dtype=torch.float64) ** 2)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    log_scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 7 - 7
    big = torch.rand(n, generator=g) < 0.1                 # 0.1-0.4 x their distance: the fifth-degree blend
    rel = 0.1 + 0.3 * torch.rand(n, 1, generator=g, dtype=torch.float64)
    log_scales[big] = torch.log(rel[big] * means[big].norm(dim=-1, keepdim=True)) - torch.rand(
        int(big.sum()), 3, generator=g, dtype=torch.float64) * torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    s = stress_rows()
    return tuple(torch.cat([a, b]) for a, b in zip(s, (means, quats, log_scales)))  # type: ignore[return-value]


def project(scene: tuple[torch.Tensor, ...], camera: CameraModel, dtype: torch.dtype, backend: str,
            R: torch.Tensor | None = None, grad: bool = False) -> tuple[Projected2D, tuple[torch.Tensor, ...]]:
    """Project ``scene`` cast to ``dtype``; returns the projection and its (leaf) inputs."""
    leaves = tuple(t.to(dtype).detach().requires_grad_(grad) for t in (*scene, *([] if R is None else [R])))
    rot = leaves[3] if R is not None else None
    return project_gaussians(leaves[0], (leaves[1], leaves[2], rot), camera, backend=backend), leaves


def rel_rows(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise difference relative to the row's largest magnitude."""
    return ((a.double() - b.double()).abs().amax(-1) / b.double().abs().amax(-1).clamp_min(1e-30))


@pytest.mark.parametrize("name", ["opencv", "radial", "pinhole"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_matches_torch_path(name, dtype):
    cam = cameras()[name]
    scene = random_scene(3000, seed=1)
    fused, _ = project(scene, cam, dtype, "fused")
    torch_same, _ = project(scene, cam, dtype, "torch")
    ref, _ = project(scene, cam, torch.float64, "torch")
    assert torch.equal(fused.index, torch_same.index) and torch.equal(fused.index, ref.index)
    for t in (fused.means2d, fused.conics, fused.cov2d, fused.depths, fused.radii):
        assert torch.isfinite(t).all()
    if dtype == torch.float64:
        assert (fused.means2d - ref.means2d).abs().max() <= 1e-9
        assert rel_rows(fused.conics, ref.conics).max() <= 1e-9
        assert rel_rows(fused.cov2d, ref.cov2d).max() <= 1e-9
        torch.testing.assert_close(fused.depths, ref.depths, rtol=1e-6, atol=0.0)
    else:
        # Compared with the exact (float64) torch path: the kernel computes in float64, so its float32
        # outputs differ only by the float32 rounding of its inputs and of its outputs, counted in ulps:
        # - means2d: x and z rounded (together 2^-23 of |u - cx|, about one ulp of the largest |uv|) and the
        #   output once (half an ulp): 1.5 ulps (1.46 on AMD, 1.6 on Intel); torch's float32 path reaches 2.2.
        # - conics, cov2d (of each row's largest entry): a log-scale near -7 rounds its variance by 4 ulps, the
        #   UT sums 7 or 19 sigma-point outer products, and the 2x2 inverse multiplies by the footprint's
        #   condition number (to ~120 here): up to 70 ulps; torch's float32 path is 300-3600 ulps off.
        # - depths: z (or |p|) rounded once in, once out: 1.3 ulps measured.
        assert (fused.means2d.double() - ref.means2d).abs().max() <= f32_tol(ref.means2d, ulps=2)
        for got, want in ((fused.conics, ref.conics), (fused.cov2d, ref.cov2d)):
            assert ((got.double() - want).abs() <= f32_tol(want, ulps=256, dim=-1)).all()
        assert ((fused.depths.double() - ref.depths).abs() <= 4 * f32_ulp(ref.depths)).all()
    # radii are ceil()s: rounding may move one by a pixel, at the cap (ceil(3 sqrt((cap / 3)^2))) or rarely
    differ = fused.radii != torch_same.radii
    assert (fused.radii - torch_same.radii).abs().max() <= 1
    assert (differ & (torch_same.radii < max(cam.width, cam.height))).float().mean() < 1e-3
    same_r = fused.radii == torch_same.radii
    assert torch.equal(fused.valid[same_r], torch_same.valid[same_r])


@pytest.mark.parametrize("name", ["opencv", "radial", "pinhole"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_match_float64_autograd(name, dtype):
    cam = cameras()[name]
    scene = random_scene(1500, seed=2)
    R = rotation_from_quaternion(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64))
    fused, leaves = project(scene, cam, dtype, "fused", R, grad=True)
    ref, ref_leaves = project(scene, cam, torch.float64, "torch", R, grad=True)
    assert torch.equal(fused.index, ref.index)
    g = torch.Generator().manual_seed(3)
    w = [torch.randn(t.shape, generator=g, dtype=torch.float64)
         for t in (ref.means2d, ref.conics, ref.cov2d, ref.depths)]

    def loss(p: Projected2D) -> torch.Tensor:
        # conics scaled by the squared footprint so that no term dominates
        outs = (p.means2d, p.conics * ref.cov2d[:, :1].detach().to(p.conics.dtype), p.cov2d, p.depths)
        return sum((o * wi.to(o.dtype)).sum() for o, wi in zip(outs, w))

    grads = torch.autograd.grad(loss(fused), leaves)
    ref_grads = torch.autograd.grad(loss(ref), ref_leaves)
    for name_, gf, gr in zip(("means", "quats", "log_scales", "R"), grads, ref_grads):
        assert torch.isfinite(gf).all(), name_
        err = (gf.double() - gr).norm(dim=-1) / gr.norm(dim=-1).clamp_min(1e-6 * gr.norm(dim=-1).max())
        assert err.max() <= 1e-3, (name_, err.max().item())


def test_rows_without_incoming_gradient_are_skipped():
    """The backward skips rows whose every incoming gradient is 0 (Gaussians drawn nowhere): their gradients
    stay exactly 0, while a row with any nonzero component (one conic entry, or the depth alone) still gets the
    gradient that the float64 torch path gives it."""
    cam = cameras()["opencv"]
    scene = random_scene(800, seed=4)
    fused, leaves = project(scene, cam, torch.float64, "fused", grad=True)
    ref, ref_leaves = project(scene, cam, torch.float64, "torch", grad=True)
    g = torch.Generator().manual_seed(5)
    w = [torch.randn(t.shape, generator=g, dtype=torch.float64) * (torch.rand(t.shape, generator=g) < 0.15)
         for t in (ref.means2d, ref.conics, ref.depths)]
    scale = ref.cov2d[:, :1].detach()   # conics scaled by the squared footprint, as above

    def loss(p: Projected2D) -> torch.Tensor:
        return sum((o * wi).sum() for o, wi in zip((p.means2d, p.conics * scale, p.depths), w))

    grads, ref_grads = torch.autograd.grad(loss(fused), leaves), torch.autograd.grad(loss(ref), ref_leaves)
    nowhere = torch.stack([wi.reshape(len(wi), -1).abs().sum(-1) for wi in w]).sum(0) == 0
    assert 0.2 < nowhere.float().mean() < 0.8
    for gf, gr in zip(grads, ref_grads):
        assert not gf[fused.index[nowhere]].any()
        kept = fused.index[~nowhere]
        clear = gr[kept].norm(dim=-1) > 1e-6 * gr.norm(dim=-1).max()
        assert clear.float().mean() > 0.5
        assert gf[kept][clear].any(dim=-1).all()   # none of them skipped
        err = (gf[kept] - gr[kept]).norm(dim=-1) / gr[kept].norm(dim=-1).clamp_min(1e-6 * gr.norm(dim=-1).max())
        assert err.median() <= 1e-9


def test_stress_rows_finite_and_differentiable_in_float32():
    cam = cameras()["opencv"]
    p, leaves = project(stress_rows(), cam, torch.float32, "fused", grad=True)
    assert len(p.index) == len(leaves[0])
    for t in (p.means2d, p.conics, p.cov2d, p.depths, p.radii):
        assert torch.isfinite(t).all()
    a, b, c = p.conics.unbind(-1)
    assert (a > 0).all() and (a * c - b * b > 0).all()
    for g in torch.autograd.grad(p.means2d.sum() + p.conics.sum() + p.depths.sum(), leaves):
        assert torch.isfinite(g).all()


def test_gradcheck_with_world_rotation_and_adaptive_set():
    cam = cameras()["opencv"]
    means = torch.tensor([[4 * v for v in _direction(80.0, 30)], [2.0, 1.0, 3.0], [1.0, 0.2, -0.05]],
                         dtype=torch.float64, requires_grad=True)
    quats = torch.tensor([[0.9, 0.2, -0.3, 0.1], [0.3, 0.1, 0.9, -0.2], [1, 0.2, 0, 0]], dtype=torch.float64,
                         requires_grad=True)
    ls = torch.log(torch.tensor([[0.6, 0.5, 0.3], [0.2, 0.1, 0.05], [0.3, 0.2, 0.1]], dtype=torch.float64)
                   ).requires_grad_()
    R = rotation_from_quaternion(torch.tensor([0.8, 0.1, 0.5, -0.2], dtype=torch.float64)).requires_grad_()

    def f(m, q, s, r):
        p = project_gaussians(m, (q, s, r), cam, backend="fused")
        return p.means2d, p.conics, p.cov2d, p.depths

    assert torch.autograd.gradcheck(f, (means, quats, ls, R))


def test_dispatch():
    cam = cameras()["opencv"]
    means, quats, ls = (t.float() for t in stress_rows())
    cov = rotation_from_quaternion(quats) @ torch.diag_embed(torch.exp(2 * ls)) @ rotation_from_quaternion(quats).mT
    with pytest.raises(ValueError, match="fused"):
        project_gaussians(means, cov, cam, backend="fused")
    with pytest.raises(ValueError, match="fused"):
        project_gaussians(means, (quats, ls, None), cam, method="ewa", backend="fused")
    with pytest.raises(ValueError, match="fused"):
        project_gaussians(means, (quats.double(), ls, None), cam, backend="fused")
    with pytest.raises(ValueError, match="backend"):
        project_gaussians(means, (quats, ls, None), cam, backend="cuda")
    auto = project_gaussians(means, (quats, ls, None), cam)
    fused = project_gaussians(means, (quats, ls, None), cam, backend="fused")
    assert torch.equal(auto.means2d, fused.means2d) and torch.equal(auto.conics, fused.conics)
    # intrinsics being optimised: the torch path (it differentiates them) serves "auto"
    trainable = OpenCVFisheye(640, 480, torch.tensor(120.0, dtype=torch.float64, requires_grad=True), 120.0,
                              319.5, 239.5, K, max_fov_deg=200.0)
    p = project_gaussians(means, (quats, ls, None), trainable)
    assert p.means2d.grad_fn is not None and "ProjectUT" not in type(p.means2d.grad_fn).__name__


def test_ut_params_are_honoured():
    cam = cameras()["opencv"]
    scene = random_scene(500, seed=4)
    for params in (UTParams(alpha=0.5, beta=2.0, kappa=1.0), UTParams(adaptive=False)):
        a = project_gaussians(scene[0], (scene[1], scene[2], None), cam, ut_params=params, backend="fused")
        b = project_gaussians(scene[0], (scene[1], scene[2], None), cam, ut_params=params, backend="torch")
        assert (a.means2d - b.means2d).abs().max() <= 1e-9
        assert rel_rows(a.conics, b.conics).max() <= 1e-9


def test_kernel_atan2_matches_libm_everywhere():
    """The kernels' polynomial atan2 (every sigma point calls it) agrees with libm over all directions r >= 0."""
    import numba
    import numpy as np

    from parksim.render._project_kernels import _atan2

    @numba.njit
    def batch(r: np.ndarray, z: np.ndarray) -> np.ndarray:
        out = np.empty_like(r)
        for i in range(r.shape[0]):
            out[i] = _atan2(r[i], z[i])
        return out

    angles = np.linspace(0.0, math.pi, 400_001)
    radius = np.exp(np.random.default_rng(0).uniform(-30, 30, angles.shape))
    r, z = np.abs(radius * np.sin(angles)), radius * np.cos(angles)
    edges = np.array([0.0, 1.0, 1.0, 1e-300, 5.0, math.tan(math.pi / 8)]), np.array([1.0, 0.0, -1.0, -1.0, 5.0, 1.0])
    r, z = np.concatenate([r, edges[0]]), np.concatenate([z, edges[1]])
    assert np.abs(batch(r, z) - np.arctan2(r, z)).max() < 2e-14
    assert batch(np.zeros(1), np.zeros(1))[0] == 0.0
