"""Stability under extreme but valid inputs (hypothesis): finiteness everywhere, float32 vs float64 agreement.

Inputs drawn: points on the optical axis, at and next to the camera centre, behind it, in the 85-100 deg
band of a 190 deg lens and beyond the lens; scales from 1e-8 to 1e3; degenerate quaternions; opacities
at 0 and 1; constant and empty-mask images through the losses; ego poses at and past the scene's edge.
CI runs ``EXAMPLES`` per property; ``parksim bench stress`` sets ``PARKSIM_STRESS_EXAMPLES`` to run many
more through this same code. The long soaks are benchmarks (``parksim bench soak-*``), not tests.
"""

import math
import os

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from parksim.camera import OpenCVFisheye, RadialPolyFisheye
from parksim.render.projection import UTParams, project_gaussians
from parksim.render.rasterize import rasterize


def max_abs(t: torch.Tensor) -> float:
    """Largest magnitude, 0 for an empty tensor."""
    return float(t.detach().abs().max()) if t.numel() else 0.0

EXAMPLES = int(os.environ.get("PARKSIM_STRESS_EXAMPLES", "40"))
"""Examples per property: CI's default, raised by ``parksim bench stress``."""
SETTINGS = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def cameras():
    return [OpenCVFisheye(160, 120, 50.0, 50.0, 79.5, 59.5, [0.05, -0.01, 0.002, -0.0002], max_fov_deg=190.0),
            RadialPolyFisheye(160, 120, [50.0, -2.0, 3.0, -0.5], 0.3, -0.2, 1.0, max_fov_deg=190.0)]


camera_index = st.integers(0, 1)
angle_deg = st.one_of(st.just(0.0), st.floats(0, 85), st.floats(85, 100), st.floats(100, 180))
distance = st.one_of(st.just(0.0), st.floats(1e-8, 1e-3), st.floats(1e-3, 1e3))
azimuth = st.floats(0, 2 * math.pi)


def point(theta_deg: float, phi: float, r: float) -> list[float]:
    t = math.radians(theta_deg)
    return [r * math.sin(t) * math.cos(phi), r * math.sin(t) * math.sin(phi), r * math.cos(t)]


@SETTINGS
@given(st.lists(st.tuples(angle_deg, azimuth, distance), min_size=1, max_size=32), camera_index)
def test_camera_project_is_finite_and_float32_agrees(pts, ci):
    cam = cameras()[ci]
    p64 = torch.tensor([point(*p) for p in pts], dtype=torch.float64)
    p32 = p64.float().requires_grad_(True)
    uv32, valid32 = cam.project(p32)
    uv32.sum().backward()
    assert torch.isfinite(uv32).all() and torch.isfinite(p32.grad).all()
    uv64, valid64 = cam.project(p64)
    both = valid32 & valid64
    # float32 keeps ~7 digits of the ray direction: < 0.01 px at these focal lengths.
    assert max_abs(uv32.double()[both] - uv64[both]) < 1e-2
    rays = cam.unproject(uv32.detach())
    assert torch.isfinite(rays).all()
    assert ((rays.norm(dim=-1) - 1).abs() < 1e-5).all()


@SETTINGS
@given(st.lists(st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)), min_size=1, max_size=32), camera_index)
def test_unproject_any_pixel_is_a_unit_ray(uvs, ci):
    cam = cameras()[ci]
    uv = torch.tensor(uvs, dtype=torch.float32, requires_grad=True)
    rays = cam.unproject(uv)
    rays.sum().backward()
    assert torch.isfinite(rays).all() and torch.isfinite(uv.grad).all()
    assert ((rays.norm(dim=-1) - 1).abs() < 1e-5).all()


opacity = st.one_of(st.sampled_from([0.0, 1.0]), st.floats(0.0, 1.0))
gaussian = st.tuples(
    angle_deg, azimuth, distance,
    st.floats(math.log(1e-8), math.log(1e3)),                       # log-scale
    st.one_of(st.just((0.0, 0.0, 0.0, 0.0)),                          # degenerate quaternion
              st.tuples(*[st.floats(-1, 1)] * 4)),
)


@SETTINGS
@given(st.lists(gaussian, min_size=1, max_size=24), camera_index, st.sampled_from(["auto", "torch"]))
def test_projection_is_finite_with_finite_gradients(gs, ci, backend):
    cam = cameras()[ci]
    means = torch.tensor([point(a, p, r) for a, p, r, _, _ in gs], dtype=torch.float32, requires_grad=True)
    log_scales = torch.tensor([[s, s - 1.0, s + 0.5] for *_, s, _ in gs], dtype=torch.float32, requires_grad=True)
    quats = torch.tensor([q for *_, q in gs], dtype=torch.float32, requires_grad=True)
    R = torch.eye(3)
    out = project_gaussians(means, (quats, log_scales, R), cam, ut_params=UTParams(), backend=backend)
    for t in (out.means2d, out.conics, out.depths):
        assert torch.isfinite(t).all()
    if out.valid.any():
        v = out.valid
        assert (out.conics[v][:, 0] > 0).all() and (out.conics[v][:, 2] > 0).all()
        det = out.conics[v][:, 0] * out.conics[v][:, 2] - out.conics[v][:, 1] ** 2
        assert (det > 0).all()
        (out.means2d[v].sum() + out.conics[v].sum()).backward()
        for t in (means, log_scales, quats):
            assert t.grad is None or torch.isfinite(t.grad).all()


@SETTINGS
@given(st.integers(0, 40), st.floats(-3, 3), opacity, st.sampled_from([1e-6, 1e-2, 1.0, 1e2, 1e6]),
       st.integers(0, 2**31 - 1))
def test_rasterizer_is_finite_and_matches_the_reference(m, log_size, opacity, conic_scale, seed):
    g = torch.Generator().manual_seed(seed)
    w, h = 24, 20
    means = (torch.rand(m, 2, generator=g) * torch.tensor([w + 10.0, h + 10.0]) - 5).requires_grad_(True)
    a = torch.rand(m, generator=g) + 0.1
    c = torch.rand(m, generator=g) + 0.1
    b = (torch.rand(m, generator=g) - 0.5) * torch.sqrt(a * c)
    conics = (torch.stack([a, b, c], -1) * conic_scale * math.exp(-log_size)).requires_grad_(True)
    colors = torch.rand(m, 3, generator=g).requires_grad_(True)
    opac = torch.full((m,), opacity).requires_grad_(True)
    depths = torch.rand(m, generator=g) * 10 + 0.1
    rgb, alpha, depth = rasterize(means, conics, colors, opac, depths, w, h, backend="numba")
    (rgb.sum() + alpha.sum()).backward()
    for t in (rgb, alpha, depth, means.grad, conics.grad, colors.grad, opac.grad):
        assert t is None or torch.isfinite(t).all()
    # Same precision as the kernel: at opacity 1 two splats land exactly on the T_MIN early stop
    # (0.01 * 0.01 = 1e-4), which float32 and float64 round to opposite sides.
    ref = rasterize(means.detach(), conics.detach(), colors.detach(), opac.detach(), depths, w, h, backend="torch")
    assert max_abs(rgb - ref[0]) < 1e-4
    assert max_abs(alpha - ref[1]) < 1e-4


@pytest.fixture(scope="module")
def tiny_ipm():
    from test_ipm import avm_rig

    from parksim.ipm import IPM

    rig = avm_rig(w=48, h=36, bev_px=40)
    return rig, IPM(rig)


@settings(max_examples=max(1, EXAMPLES * 3 // 8), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fill=st.sampled_from([0.0, 1.0, 1e-30, 0.5]), seed=st.integers(0, 2**31 - 1))
def test_ipm_is_finite_for_constant_and_random_images(fill, seed, tiny_ipm):
    rig, ipm = tiny_ipm
    g = torch.Generator().manual_seed(seed)
    imgs = {n: (torch.rand(36, 48, 3, generator=g) if fill == 0.5 else torch.full((36, 48, 3), fill)
                ).requires_grad_(True) for n in rig.names}
    bev = ipm(imgs)
    bev.sum().backward()
    assert torch.isfinite(bev).all()
    assert all(torch.isfinite(v.grad).all() for v in imgs.values())
    if fill != 0.5:
        # A constant image maps to the same constant wherever a camera sees the ground.
        assert np.allclose(bev[ipm.mask].detach().numpy(), fill, rtol=1e-5, atol=1e-30)


image_fill = st.one_of(st.sampled_from([0.0, 1.0, 1e-30]), st.none())   # None: random pixels
mask_kind = st.sampled_from(["empty", "one pixel", "random", "full"])


def image(fill: float | None, h: int, w: int, g: torch.Generator) -> torch.Tensor:
    """A [1, 3, H, W] float64 image: constant ``fill`` or uniform random."""
    return torch.rand(1, 3, h, w, generator=g, dtype=torch.float64) if fill is None else \
        torch.full((1, 3, h, w), fill, dtype=torch.float64)


def mask(kind: str, h: int, w: int, g: torch.Generator) -> torch.Tensor:
    """A [1, 1, H, W] float64 mask of valid pixels."""
    m = torch.zeros(1, 1, h, w, dtype=torch.float64)
    if kind == "one pixel":
        m[..., h // 2, w // 2] = 1
    elif kind == "random":
        m = (torch.rand(1, 1, h, w, generator=g) < 0.5).double()
    elif kind == "full":
        m += 1
    return m


@SETTINGS
@given(image_fill, image_fill, mask_kind, st.floats(0.0, 1.0), st.integers(6, 24), st.integers(6, 24),
       st.integers(0, 2**31 - 1))
def test_losses_are_finite_with_finite_gradients_and_float32_agrees(pred_fill, gt_fill, mask_of, lam, h, w, seed):
    from parksim.recon.losses import photometric_loss

    g = torch.Generator().manual_seed(seed)
    pred64, gt64, m64 = image(pred_fill, h, w, g), image(gt_fill, h, w, g), mask(mask_of, h, w, g)
    pred32 = pred64.float().requires_grad_(True)
    loss32 = photometric_loss(pred32, gt64.float(), m64.float(), lam)
    loss32.backward()
    assert torch.isfinite(loss32) and torch.isfinite(pred32.grad).all()
    pred64.requires_grad_(True)
    loss64 = photometric_loss(pred64, gt64, m64, lam)
    loss64.backward()
    # SSIM's local variances cancel in float32 (var = E[x^2] - E[x]^2 ~ 1e-7 absolute error, over C2 = 9e-4).
    assert abs(loss32.item() - loss64.item()) < 1e-3
    assert max_abs(pred32.grad.double() - pred64.grad) < 1e-3 * max(1.0, max_abs(pred64.grad))


@pytest.fixture(scope="module")
def tiny_rig():
    from test_ipm import avm_rig

    return avm_rig(w=32, h=24, bev_px=16)


SCENE_BOX = ((0.0, -3.0, 0.0), (10.0, 3.0, 2.5))
"""The stress scene's Gaussians lie in this box (metres); poses are drawn on and past its edges."""
edge_coordinate = st.one_of(st.sampled_from([0.0, 1.0]), st.floats(-0.5, 1.5))   # fraction of the box's side
render_gaussian = st.tuples(st.floats(0, 1), st.floats(0, 1), st.floats(0, 1),
                            st.floats(math.log(1e-8), math.log(1e3)), opacity,
                            st.one_of(st.just((0.0, 0.0, 0.0, 0.0)), st.tuples(*[st.floats(-1, 1)] * 4)))


@settings(max_examples=max(1, EXAMPLES // 2), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(gs=st.lists(render_gaussian, min_size=1, max_size=12), fx=edge_coordinate, fy=edge_coordinate,
       yaw=st.floats(-math.pi, math.pi), method=st.sampled_from(["ut", "ewa"]))
def test_render_at_the_scene_edge_is_finite_with_finite_gradients(gs, fx, fy, yaw, method, tiny_rig):
    from parksim.gaussians import GaussianScene
    from parksim.geometry import pose_from_xy_yaw
    from parksim.render import render
    from parksim.render.rasterize import ALPHA_MAX

    lo, hi = torch.tensor(SCENE_BOX[0]), torch.tensor(SCENE_BOX[1])
    means = lo + torch.tensor([g[:3] for g in gs]) * (hi - lo)
    log_scales = torch.tensor([[s, s - 1.0, s + 0.5] for *_, s, _, _ in gs])
    # Opacity exactly 0 or 1 is logit -inf or +inf: clamp to the float32 logits of the nearest representable values.
    opacities = torch.tensor([o for *_, o, _ in gs]).clamp(1e-7, 1 - 1e-7)
    quats = torch.tensor([q for *_, q in gs])
    sh = torch.rand(len(gs), 4, 3, generator=torch.Generator().manual_seed(len(gs)))
    params = [t.requires_grad_(True) for t in (means, quats, log_scales, torch.logit(opacities), sh)]
    scene = GaussianScene(*params, sh_degree=1)
    x, y = (SCENE_BOX[0][i] + f * (SCENE_BOX[1][i] - SCENE_BOX[0][i]) for i, f in ((0, fx), (1, fy)))
    out = render(scene, tiny_rig, pose_from_xy_yaw(x, y, yaw), bev=True, method=method)
    for name in tiny_rig.names:
        assert torch.isfinite(out.images[name]).all() and torch.isfinite(out.depth[name]).all()
        assert ((out.alpha[name] >= 0) & (out.alpha[name] <= 1 + 1e-6)).all()
    assert torch.isfinite(out.bev).all()
    (sum(img.sum() for img in out.images.values()) + out.bev.sum()).backward()
    for t in params:
        assert t.grad is None or torch.isfinite(t.grad).all()
    # float64 agreement where the float32 render is defined (the limits were found by `parksim bench stress`):
    # - the compositing order: Gaussians at the same distance from a camera (coincident ones) are blended in an
    #   unspecified order, which differs between float32 and float64 (1e-2 apart for two opaque ones);
    # - the early stop: two splats at the ALPHA_MAX clamp leave exactly T_MIN, which float32 and float64 round
    #   to opposite sides (as in the rasterizer test above; 5.5e-3 apart for two opaque Gaussians);
    # - EWA linearises the lens at the mean: for a Gaussian wider than its distance to a camera it is
    #   ill-conditioned, and float32 parts from float64 (0.6 % for sigma 55 m seen from 3 m).
    T_world_vehicle = pose_from_xy_yaw(x, y, yaw)
    centres = torch.stack([(T_world_vehicle @ c.T_vehicle_camera)[:3, 3] for c in tiny_rig.cameras.values()]).float()
    distance = torch.cdist(means.detach(), centres)
    ordered = bool((distance.sort(dim=0).values.diff(dim=0) > 1e-3).all()) and int((opacities >= ALPHA_MAX).sum()) < 2
    linearisable = bool((log_scales.detach().max(dim=1).values.exp() < 0.5 * distance.min(dim=1).values).all())
    if ordered and (method == "ut" or linearisable):
        with torch.no_grad():
            ref = render(scene.to(torch.float64), tiny_rig, T_world_vehicle, method=method, backend="torch")
        for name in tiny_rig.names:
            assert max_abs(out.images[name].double() - ref.images[name]) < 1e-3
