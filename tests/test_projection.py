"""Projection of 3D Gaussians: UT against Monte-Carlo, gradients, culling, and the edge cases of a 190+ deg lens."""

from __future__ import annotations

import math

import pytest
import torch

from parksim.camera import OpenCVFisheye, Pinhole
from parksim.geometry import rotation_from_quaternion
from parksim.render.projection import BLUR_PX2, UTParams, covariance_sqrt, project_gaussians

K = [0.05, -0.01, 0.002, -0.0005]


def fisheye(width: int = 640, height: int = 480, f: float = 120.0) -> OpenCVFisheye:
    """A 200 deg lens (theta_max = 100 deg) whose image circle fits inside the image."""
    return OpenCVFisheye(width, height, f, f, (width - 1) / 2, (height - 1) / 2, K, max_fov_deg=200.0)


def direction(theta_deg: float, phi_deg: float = 0.0) -> torch.Tensor:
    """Unit ray at ``theta`` off the optical axis, azimuth ``phi`` from +x (image right) towards +y (down)."""
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)], dtype=torch.float64)


def monte_carlo(mu, L, camera, n=20000, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = mu + torch.randn(n, 3, generator=g, dtype=torch.float64) @ L.T
    uv, _ = camera.project(x)
    return uv.mean(0), torch.cov(uv.T)


def as_abc(cov):
    return torch.stack([cov[0, 0], cov[0, 1], cov[1, 1]])


def raw_cov(p):
    """UT covariance without the 3DGS blur."""
    return p.cov2d - torch.tensor([BLUR_PX2, 0.0, BLUR_PX2], dtype=p.cov2d.dtype)


def one(theta_deg, dist, sigma, quat=(0.9, 0.2, -0.3, 0.1), phi=20.0):
    mu = (dist * direction(theta_deg, phi))[None]
    q = torch.tensor([quat], dtype=torch.float64)
    ls = torch.log(torch.tensor([[sigma, 0.6 * sigma, 0.3 * sigma]], dtype=torch.float64))
    return mu, q, ls


@pytest.mark.parametrize("theta", [0.0, 40.0, 80.0])
def test_ut_matches_monte_carlo(theta):
    cam = fisheye()
    mu, q, ls = one(theta, 5.0, 0.05 * 5.0)
    p = project_gaussians(mu, (q, ls, None), cam)
    m_ref, c_ref = monte_carlo(mu[0], covariance_sqrt(q, ls)[0], cam)
    assert (p.means2d[0] - m_ref).norm() < 0.3
    rel = (raw_cov(p)[0] - as_abc(c_ref)).norm() / as_abc(c_ref).norm()
    assert rel < 0.04


def test_fifth_degree_set_beats_7_point_ut_at_the_lens_edge():
    """A Gaussian 0.3 x its distance wide at 85 deg: the adaptive (19-point) set is closer to Monte-Carlo."""
    cam = fisheye()
    mu, q, ls = one(85.0, 4.0, 0.3 * 4.0)
    _, c_ref = monte_carlo(mu[0], covariance_sqrt(q, ls)[0], cam, n=200000)
    errs = {}
    for adaptive in (False, True):
        p = project_gaussians(mu, (q, ls, None), cam, ut_params=UTParams(adaptive=adaptive))
        errs[adaptive] = ((raw_cov(p)[0] - as_abc(c_ref)).norm() / as_abc(c_ref).norm()).item()
    assert errs[True] < 0.7 * errs[False]


def test_ewa_agrees_with_ut_for_small_gaussians_and_is_differentiable():
    cam = fisheye()
    mu, q, ls = one(50.0, 8.0, 0.01 * 8.0)
    mu.requires_grad_(True)
    ut = project_gaussians(mu, (q, ls, None), cam, method="ut")
    ewa = project_gaussians(mu, (q, ls, None), cam, method="ewa")
    assert (ut.means2d - ewa.means2d).norm() < 0.05
    torch.testing.assert_close(ewa.cov2d, ut.cov2d, rtol=0.02, atol=0.01)
    (g,) = torch.autograd.grad(ewa.conics.sum() + ewa.means2d.sum(), mu)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_covariance_matrix_input_equals_quaternion_input():
    cam = fisheye()
    mu = torch.stack([3 * direction(30, 10), 6 * direction(70, 200)])
    q = torch.tensor([[1.0, 0.3, 0.2, -0.1], [0.2, 0.9, 0.1, 0.4]], dtype=torch.float64)
    ls = torch.log(torch.tensor([[0.2, 0.1, 0.05], [0.4, 0.3, 0.1]], dtype=torch.float64))
    L = covariance_sqrt(q, ls)
    a = project_gaussians(mu, (q, ls, None), cam, method="ewa")
    b = project_gaussians(mu, L @ L.transpose(1, 2), cam, method="ewa")
    torch.testing.assert_close(a.means2d, b.means2d)
    torch.testing.assert_close(a.conics, b.conics, rtol=1e-5, atol=1e-8)
    # UT depends on the matrix square root (Cholesky here) only through higher-order terms.
    a = project_gaussians(mu, (q, ls, None), cam)
    b = project_gaussians(mu, L @ L.transpose(1, 2), cam)
    assert ((a.cov2d - b.cov2d).norm(dim=-1) / a.cov2d.norm(dim=-1)).max() < 0.03


def test_world_rotation_is_applied():
    """Passing R_cam_world rotates the covariance: same result as pre-rotated camera-frame quaternions."""
    cam = fisheye()
    mu, q, ls = one(30.0, 5.0, 0.3)
    R = rotation_from_quaternion(torch.tensor([0.8, 0.1, 0.5, -0.2], dtype=torch.float64))
    a = project_gaussians(mu, (q, ls, R), cam, method="ewa")
    L = covariance_sqrt(q, ls, R)
    b = project_gaussians(mu, L @ L.transpose(1, 2), cam, method="ewa")
    torch.testing.assert_close(a.conics, b.conics, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("adaptive_case", [False, True])
def test_gradcheck_ut(adaptive_case):
    cam = fisheye()
    if adaptive_case:   # large and near the edge: goes through the fifth-degree set
        mu = (4.0 * direction(80.0, 30.0))[None]
        ls = torch.log(torch.tensor([[0.6, 0.5, 0.3]], dtype=torch.float64))
    else:
        mu = torch.stack([5 * direction(25.0, 40.0), 3 * direction(60.0, 250.0)])
        ls = torch.log(torch.tensor([[0.2, 0.1, 0.05], [0.1, 0.08, 0.3]], dtype=torch.float64))
    q = torch.tensor([[0.9, 0.2, -0.3, 0.1]] * len(mu), dtype=torch.float64)

    def f(mu, q, ls):
        p = project_gaussians(mu, (q, ls, None), cam)
        assert len(p.index) == len(mu)
        return p.means2d, p.conics

    assert torch.autograd.gradcheck(f, (mu.requires_grad_(), q.requires_grad_(), ls.requires_grad_()))


def test_gradient_on_the_optical_axis_is_finite():
    cam = fisheye()
    mu = torch.tensor([[0.0, 0.0, 5.0]], dtype=torch.float64, requires_grad=True)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    ls = torch.full((1, 3), math.log(0.1), dtype=torch.float64, requires_grad=True)   # isotropic too
    p = project_gaussians(mu, (q, ls, None), cam)
    torch.testing.assert_close(p.means2d[0], torch.tensor([cam.cx, cam.cy], dtype=torch.float64))
    grads = torch.autograd.grad(p.means2d.sum() + p.conics.sum(), (mu, q, ls))
    assert all(torch.isfinite(g).all() for g in grads)
    assert torch.autograd.gradcheck(lambda m: project_gaussians(m, (q, ls, None), cam).conics, (mu,))


def _hard_cases() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gaussians (float32) at every awkward spot, each row a case."""
    rows = [  # (position, log_scales, quat)
        ((0, 0, 5), (-2, -2, -2), (1, 0, 0, 0)),                 # on the optical axis, isotropic
        ((1.0, 0.0, 0.0), (-0.7, -1, -2), (1, 0.3, 0, 0)),       # centre on the camera plane, straddling it
        ((1.0, 0.2, -0.05), (-1, -1, -1), (1, 0, 0, 0)),         # just behind the camera plane
        (tuple(3 * direction(85.0, 10)), (-1, -1.5, -2), (1, 1, 0, 0)),
        (tuple(3 * direction(92.0, 100)), (-1, -1.5, -2), (1, 0, 1, 0)),
        (tuple(3 * direction(99.5, 200)), (-0.5, -0.5, -0.5), (1, 0, 0, 1)),   # edge of the lens, sigma points beyond
        (tuple(3 * direction(105.0, 300)), (0.0, 0.0, 0.0), (1, 0, 0, 0)),    # centre beyond, cone reaches in
        ((0, 0, 4), (-1e3, -1e3, -1e3), (1, 0, 0, 0)),           # zero scales
        ((0.5, 0.5, 4), (-88, -90, -100), (1, 0, 0, 0)),         # denormal scales
        ((0.3, -0.2, 4), (-2, -2.5, -3), (0, 0, 0, 0)),          # zero quaternion
        ((0, 0.1, 0.3), (4.6, 4.6, 4.6), (1, 0, 0, 0)),          # 100 m wide, 0.3 m from the camera
        ((0.2, 0.0, 0.1), (0.0, -3, -3), (0.7, 0.7, 0, 0)),      # camera inside the Gaussian
    ]
    means, ls, quats = (torch.tensor([r[i] for r in rows], dtype=torch.float32) for i in range(3))
    return means, ls, quats


@pytest.mark.parametrize("method", ["ut", "ewa"])
@pytest.mark.parametrize("alpha", [1.0, 0.1])
def test_hard_cases_are_finite_in_value_and_gradient(method, alpha):
    cam = fisheye()
    means, ls, quats = (t.requires_grad_() for t in _hard_cases())
    p = project_gaussians(means, (quats, ls, None), cam, method=method, ut_params=UTParams(alpha=alpha))
    assert len(p.index) == len(means)           # none of these is culled
    for t in (p.means2d, p.conics, p.cov2d, p.depths, p.radii):
        assert torch.isfinite(t).all()
    a, b, c = p.conics.unbind(-1)
    assert (a > 0).all() and (a * c - b * b > 0).all()    # positive definite, also for alpha = 0.1
    assert (p.radii <= max(cam.width, cam.height)).all()   # huge footprints are capped
    loss = (p.means2d.sum() + p.conics.sum() + p.depths.sum())
    for g in torch.autograd.grad(loss, (means, ls, quats)):
        assert torch.isfinite(g).all()


@pytest.mark.parametrize("phi", [0.0, 90.0, 180.0, 270.0])
def test_95_deg_off_axis_lands_on_its_own_side(phi):
    """Behind the image plane (z < 0) the splat must stay on the side of its direction, not mirror."""
    cam = fisheye()
    d = direction(95.0, phi)
    p = project_gaussians((4 * d)[None].float(), (torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), -2.0), None), cam)
    assert p.valid.all()
    offset = p.means2d[0].double() - torch.tensor([cam.cx, cam.cy], dtype=torch.float64)
    assert offset.norm() > 0.8 * cam.rho_max * cam.fx
    assert torch.dot(offset / offset.norm(), d[:2] / d[:2].norm()) > 0.99


def test_straddling_camera_plane_lands_at_90_deg():
    cam = fisheye()
    mu = torch.tensor([[2.0, 0.0, 0.0]])
    p = project_gaussians(mu, (torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), math.log(0.5)), None), cam)
    assert p.valid.all() and p.means2d[0, 0] > cam.cx + 100
    m_ref, _ = monte_carlo(mu[0].double(), 0.5 * torch.eye(3, dtype=torch.float64), cam)
    assert (p.means2d[0] - m_ref).norm() < 2.0


def test_culling_by_angle_and_distance_not_by_z():
    cam = fisheye()
    ls = torch.full((6, 3), math.log(0.05))
    q = torch.tensor([[1.0, 0, 0, 0]] * 6)
    means = torch.stack([3 * direction(95.0), 3 * direction(101.0), 3 * direction(150.0),
                         0.01 * direction(10.0), 2000 * direction(10.0), 3 * direction(10.0)]).float()
    p = project_gaussians(means, (q, ls, None), cam)
    # 95 deg (z < 0) is seen; 101 deg is beyond 100 deg but its 3-sigma cone reaches inside;
    # 150 deg, closer than near and farther than far are culled.
    assert p.index.tolist() == [0, 1, 5]
    pin = Pinhole(64, 48, 30, 30, 31.5, 23.5)
    behind = torch.tensor([[0.0, 0.0, -3.0], [0.5, 0.0, 3.0]])
    assert project_gaussians(behind, (q[:2], ls[:2], None), pin).index.tolist() == [1]


def test_off_image_footprints_are_invalid():
    cam = OpenCVFisheye(64, 48, 40, 40, 31.5, 23.5, K, max_fov_deg=200.0)   # circle larger than the image
    means = torch.stack([5 * direction(0.0), 5 * direction(90.0, 90.0)]).float()
    p = project_gaussians(means, (torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), -3.0), None), cam)
    assert p.valid.tolist() == [True, False]


def test_max_radius_caps_the_footprint():
    cam = fisheye()
    p = project_gaussians(torch.tensor([[0.0, 0.0, 1.0]]), (torch.tensor([[1.0, 0, 0, 0]]),
                          torch.full((1, 3), 2.0), None), cam, max_radius=50.0)
    assert p.radii.item() <= 50.0
    assert p.cov2d[0, 0].item() == pytest.approx((50 / 3) ** 2, rel=1e-4)


def test_bad_method():
    with pytest.raises(ValueError, match="method"):
        project_gaussians(torch.zeros(1, 3), torch.eye(3)[None], fisheye(), method="linear")
