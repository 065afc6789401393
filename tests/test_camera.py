"""Camera models: OpenCV agreement below 90 deg, full-sphere round trips, gradients, edge cases."""

import math

import cv2
import numpy as np
import pytest
import torch

from parksim.camera import OpenCVFisheye, Pinhole, RadialPolyFisheye, camera_from_dict
from tolerances import f32_ulp

# The real sample's front camera (OpenCV fisheye calibration, 960x640).
K_SAMPLE = np.array([[302.45305983229298, 0.0, 496.64001463163459],
                     [0.0, 320.74618594392325, 331.19980984361649], [0.0, 0.0, 1.0]])
D_SAMPLE = np.array([-0.043735601598704078, 0.021692522970939803, -0.026388839028513571, 0.0084123126605702321])
# WoodScape's published front camera intrinsics.
WOODSCAPE_K = [339.749, -31.988, 48.275, -7.201]


def directions(max_deg: float, n: int, seed: int = 0, min_deg: float = 0.0) -> np.ndarray:
    """Unit rays spread over off-axis angles [min_deg, max_deg] and all azimuths."""
    rng = np.random.default_rng(seed)
    th = np.radians(rng.uniform(min_deg, max_deg, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def opencv_cam(max_fov_deg: float = 190.0) -> OpenCVFisheye:
    return OpenCVFisheye.from_K_D(K_SAMPLE, D_SAMPLE, (960, 640), max_fov_deg)


def woodscape_cam(max_fov_deg: float = 190.0) -> RadialPolyFisheye:
    return RadialPolyFisheye(1280, 966, WOODSCAPE_K, cx_offset=3.942, cy_offset=-3.093,
                             aspect_ratio=1.0, max_fov_deg=max_fov_deg)


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle between ray batches, accurate for tiny angles (atan2 of |cross| and dot)."""
    a = a / a.norm(dim=-1, keepdim=True)
    b = b / b.norm(dim=-1, keepdim=True)
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def test_opencv_fisheye_matches_cv2_below_85_deg():
    cam = opencv_cam()
    pts = directions(85.0, 5000) * np.random.default_rng(1).uniform(0.3, 30.0, (5000, 1))
    uv, valid = cam.project(torch.from_numpy(pts))
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), K_SAMPLE, D_SAMPLE)
    in_image = (ref[:, 0, 0] >= -0.5) & (ref[:, 0, 0] <= 959.5) & (ref[:, 0, 1] >= -0.5) & (ref[:, 0, 1] <= 639.5)
    assert np.abs(uv.numpy() - ref[:, 0]).max() < 1e-6
    assert np.array_equal(valid.numpy(), in_image)


@pytest.mark.parametrize("make", [opencv_cam, woodscape_cam], ids=["opencv", "woodscape"])
def test_round_trip_float64_up_to_100_deg(make):
    # A 190-deg-class lens whose calibration holds to 100 deg off the axis (max_fov_deg = 200).
    cam = make(max_fov_deg=200.0)
    rays = torch.from_numpy(directions(100.0, 20000, seed=2))
    uv, _ = cam.project(rays * 3.7)
    back = cam.unproject(uv)
    assert angle_between(back, rays).max() < 1e-9
    assert ((back.norm(dim=-1) - 1).abs() < 1e-12).all()


@pytest.mark.parametrize("make", [opencv_cam, woodscape_cam], ids=["opencv", "woodscape"])
def test_round_trip_float32_error_is_stated(make):
    # float32 round trip: stated bound 2e-6 rad (~4e-4 px at these focal lengths).
    cam = make(max_fov_deg=200.0)
    rays = torch.from_numpy(directions(100.0, 20000, seed=3))
    uv, _ = cam.project(rays.float())
    back = cam.unproject(uv)
    assert back.dtype == torch.float32
    assert angle_between(back.double(), rays).max() < 2e-6


def test_woodscape_matches_documented_formula():
    cam = woodscape_cam()
    pts = directions(95.0, 3000, seed=4) * 2.0
    x, y, z = pts.T
    chi = np.hypot(x, y)
    theta = np.pi / 2 - np.arctan2(z, chi)
    rho = sum(k * theta ** (i + 1) for i, k in enumerate(WOODSCAPE_K))
    u = rho * x / chi + 3.942 + 1280 / 2 - 0.5
    v = rho * y / chi * 1.0 + -3.093 + 966 / 2 - 0.5
    uv, _ = cam.project(torch.from_numpy(pts))
    assert np.abs(uv.numpy() - np.stack([u, v], -1)).max() < 1e-9


def test_pinhole_matches_cv2():
    cam = Pinhole(640, 480, 500.0, 510.0, 320.0, 240.0)
    pts = directions(60.0, 2000, seed=5) * 4.0
    uv, valid = cam.project(torch.from_numpy(pts))
    ref, _ = cv2.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3),
                               np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]]), np.zeros(5))
    assert np.abs(uv.numpy() - ref[:, 0]).max() < 1e-8
    back = cam.unproject(uv)
    assert angle_between(back, torch.from_numpy(pts)).max() < 1e-9


@pytest.mark.parametrize("make", [opencv_cam, woodscape_cam], ids=["opencv", "woodscape"])
def test_gradcheck_project_and_unproject(make):
    cam = make()
    cam.fx.requires_grad_(True)
    cam.k.requires_grad_(True)
    pts = torch.from_numpy(directions(94.0, 6, seed=6) * 2.0).requires_grad_(True)

    def proj(p, fx, k):
        cam.fx, cam.k = fx, k
        return cam.project(p)[0]

    assert torch.autograd.gradcheck(proj, (pts, cam.fx, cam.k))
    uv = cam.project(pts.detach())[0].detach().requires_grad_(True)

    def unproj(q, fx, k):
        cam.fx, cam.k = fx, k
        return cam.unproject(q)

    assert torch.autograd.gradcheck(unproj, (uv, cam.fx, cam.k))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("make", [opencv_cam, woodscape_cam], ids=["opencv", "woodscape"])
def test_optical_axis_is_exact_and_finite(make, dtype):
    cam = make()
    z = 2.5
    p = torch.tensor([[0.0, 0.0, z], [1e-30, 0.0, z], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]],
                     dtype=dtype, requires_grad=True)
    uv, valid = cam.project(p)
    assert valid.tolist() == [True, True, False, False]
    assert torch.isfinite(uv).all()
    cxy = torch.stack([cam.cx, cam.cy])   # the offset from it is exactly 0: the only error is cx, cy's own rounding
    assert ((uv[0].double() - cxy).abs() <= 0.5 * f32_ulp(cxy)).all()
    uv[0].sum().backward()
    # On the axis d u / d x = fx q(0) / z exactly (q(0) = 1 for Kannala-Brandt, k1 for WoodScape).
    dudx = float(cam.fx * cam.q(torch.zeros((), dtype=torch.float64), cam.k)) / z
    assert torch.isfinite(p.grad).all()
    assert abs(float(p.grad[0, 0]) - dudx) < 1e-4 * dudx
    centre = torch.tensor([[cam.cx, cam.cy]], dtype=dtype, requires_grad=True)
    ray = cam.unproject(centre)
    ray.sum().backward()
    assert torch.allclose(ray.double(), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert torch.isfinite(centre.grad).all()


def test_points_past_the_lens_are_invalid_and_not_mirrored():
    cam = opencv_cam(max_fov_deg=190.0)
    for deg in (96.0, 120.0, 170.0):
        th = math.radians(deg)
        p = torch.tensor([[math.sin(th), 0.0, math.cos(th)], [0.0, -math.sin(th), math.cos(th)]], dtype=torch.float64,
                         requires_grad=True)
        uv, valid = cam.project(p)
        assert not valid.any()
        assert uv[0, 0] > cam.cx and uv[1, 1] < cam.cy  # same side as the point, never mirrored
        uv.sum().backward()
        assert torch.isfinite(p.grad).all()
    # Between 90 and 95 deg the point is behind the image plane (z < 0) yet valid and on its own side.
    th = math.radians(93.0)
    uv, valid = cam.project(torch.tensor([[-math.sin(th), 0.0, math.cos(th)]], dtype=torch.float64))
    assert uv[0, 0] < cam.cx and valid.item() == (uv[0, 0] >= -0.5).item()


def test_fold_back_limits_the_valid_angle():
    # k1 = -0.4 makes rho(theta) = theta (1 - 0.4 theta^2) turn back at theta = sqrt(1/1.2) = 52.3 deg.
    cam = OpenCVFisheye(640, 480, 300.0, 300.0, 320.0, 240.0, [-0.4, 0.0, 0.0, 0.0], max_fov_deg=190)
    assert abs(cam.theta_max - math.sqrt(1 / 1.2)) < 1e-9
    th = cam.theta_max + 0.05
    _, valid = cam.project(torch.tensor([[math.sin(th), 0.0, math.cos(th)]], dtype=torch.float64))
    assert not valid.item()


def test_scaled_camera_maps_pixel_centres():
    cam = opencv_cam()
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (480, 320)
    pts = torch.from_numpy(directions(80.0, 100, seed=7))
    uv, _ = cam.project(pts)
    uv_half, _ = half.project(pts)
    assert torch.allclose(uv_half, (uv + 0.5) * 0.5 - 0.5, atol=1e-9)
    wood = woodscape_cam()
    assert torch.allclose(wood.scaled(0.5).project(pts)[0], (wood.project(pts)[0] + 0.5) * 0.5 - 0.5, atol=1e-9)


def test_dict_round_trip_and_bad_input():
    for cam in (opencv_cam(), woodscape_cam(), Pinhole(64, 48, 50.0, 50.0, 32.0, 24.0)):
        again = camera_from_dict(cam.to_dict())
        assert again.to_dict() == cam.to_dict()
    with pytest.raises(ValueError, match="unknown camera model 'kb8'"):
        camera_from_dict({"model": "kb8", "width": 10})
    with pytest.raises(ValueError, match="bad intrinsics"):
        camera_from_dict({"model": "pinhole", "width": 10, "height": 10, "fx": 1.0})
    with pytest.raises(ValueError, match="finite"):
        OpenCVFisheye(64, 48, float("nan"), 50.0, 32.0, 24.0, [0, 0, 0, 0])
    with pytest.raises(ValueError, match="4 distortion"):
        OpenCVFisheye(64, 48, 50.0, 50.0, 32.0, 24.0, [0, 0])
    with pytest.raises(ValueError, match="points\\[..., 3\\]"):
        opencv_cam().project(torch.zeros(5, 2))


# --- magnitudes: only a point's direction matters ------------------------------------------------------

def pinhole_cam() -> Pinhole:
    return Pinhole(640, 480, 300.0, 310.0, 319.5, 239.5, max_fov_deg=120.0)


LENSES = [opencv_cam, woodscape_cam, pinhole_cam]
LENS_IDS = ["opencv", "woodscape", "pinhole"]
MAX_ULPS = 8
"""Rounding allowed against a float64 reference, in ulps of the dtype at the largest magnitude compared: float32
projections of unit points are up to ~5 ulps off float64 (the lens' own rounding), float64 ones up to 6 (the
reference's own normalisation rounds the direction)."""


def ulp(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """np.spacing of ``dtype`` at |x|, as float64."""
    if dtype == torch.float32:
        return f32_ulp(x)
    return torch.from_numpy(np.asarray(np.spacing(x.detach().abs().double().numpy()), dtype=np.float64))


def magnitude_cases(dtype: torch.dtype) -> torch.Tensor:
    """Points ``[M, 3]`` in ``dtype``: 0 to 150 deg off the axis, two azimuths, from near the centre to float max."""
    rays = []
    for deg in (0.0, 10.0, 45.0, 89.0, 100.0, 150.0):
        for az in (30.0, 200.0):
            t, a = math.radians(deg), math.radians(az)
            rays.append([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])
    big = [1e155, 1e200, 1e300] if dtype == torch.float64 else []
    small = [1e-150] if dtype == torch.float64 else [1e-18]   # above the centre's sqrt(tiny)
    mags = [1.0, 1e10, 1e20, 1e30, *small, *big, torch.finfo(dtype).max]
    return torch.cat([(torch.tensor(rays, dtype=torch.float64) * m).to(dtype) for m in mags])


def unit_points(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Float64 unit points of ``p`` and ``m, n`` with ``|p| = m n`` (a product that may overflow float64)."""
    p = p.detach().double()
    m = p.abs().amax(-1, keepdim=True)
    n = (p / m).norm(dim=-1, keepdim=True)
    return p / m / n, m, n


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("make", LENSES, ids=LENS_IDS)
def test_any_magnitude_projects_as_its_unit_point(make, dtype):
    """Far points (up to float max) and near ones land where their unit point does, with the same validity;
    the gradient is the unit point's divided by |p|; ``theta_of`` agrees. Squaring |p| used to overflow:
    45 deg at 1e155 (float64) or 1e20 (float32) went to the principal point flagged valid."""
    cam = make()
    p = magnitude_cases(dtype).requires_grad_(True)
    unit, m, n = unit_points(p)
    unit.requires_grad_(True)
    uv, valid = cam.project(p)
    ref, ref_valid = cam.project(unit)
    w = torch.tensor([0.7, -1.3], dtype=torch.float64)
    (uv * w.to(dtype)).sum().backward()
    (ref * w).sum().backward()
    assert torch.equal(valid, ref_valid)
    assert ((uv.double() - ref).abs().amax(-1) <= MAX_ULPS * ulp(ref.detach().abs().amax(-1), dtype)).all()
    assert torch.isfinite(p.grad).all()
    # du/dp is homogeneous of degree -1; tolerance scaled at the gradient's largest component
    g = p.grad.double() * m * n
    assert ((g - unit.grad).abs().amax(-1) <= MAX_ULPS * ulp(unit.grad.abs().amax(-1), dtype)).all()
    theta, ref_theta = cam.theta_of(p.detach()), cam.theta_of(unit.detach())
    assert ((theta.double() - ref_theta).abs() <= MAX_ULPS * ulp(torch.full_like(ref_theta, math.pi), dtype)).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("make", LENSES, ids=LENS_IDS)
def test_infinite_or_nan_points_are_invalid_with_zero_gradient(make, dtype):
    """No direction to trust: NaN pixels, invalid, zero gradient. +inf z used to give the principal point, valid."""
    inf, nan = math.inf, math.nan
    p = torch.tensor([[0.0, 0.0, inf], [1.0, 2.0, inf], [inf, 0.0, 1.0], [-inf, 0.0, 0.0], [inf, -inf, 1.0],
                      [nan, 0.0, 1.0]], dtype=dtype, requires_grad=True)
    uv, valid = make().project(p)
    uv.sum().backward()
    assert not valid.any() and torch.isnan(uv).all()
    assert torch.equal(p.grad, torch.zeros_like(p))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("make", LENSES, ids=LENS_IDS)
def test_far_out_pixels_unproject_to_the_rim_ray_in_their_direction(make, dtype):
    """A pixel however far outside the valid circle gives the unit ray at theta_max in its own direction, with
    finite gradients; squaring its offset used to overflow (rho = inf: the ray (0, 0, cos theta_max))."""
    cam = make()
    fmax = torch.finfo(dtype).max
    radii = [1e4, 1e20, 1e30, fmax] + ([1e155, 1e300] if dtype == torch.float64 else [])
    az = torch.tensor([0.3, 2.0, 4.0], dtype=torch.float64)
    offsets = torch.cat([torch.stack([torch.cos(az), torch.sin(az)], -1) * r for r in radii])
    uv = (offsets + torch.stack([cam.cx, cam.cy])).to(dtype).requires_grad_(True)
    ray = cam.unproject(uv)
    ray.sum().backward()
    mx = (uv.detach().double() - torch.stack([cam.cx, cam.cy])) / torch.stack([cam.fx, cam.fy])
    d, _, _ = unit_points(torch.cat([mx, torch.zeros_like(mx[:, :1])], -1))
    t = torch.tensor(cam.theta_max, dtype=torch.float64)
    want = torch.cat([d[:, :2] * torch.sin(t), torch.cos(t).expand(len(d), 1)], -1)
    assert not cam.pixel_valid(uv.detach()).any()
    assert ((ray.double() - want).abs() <= MAX_ULPS * ulp(torch.ones(()), dtype)).all()
    assert torch.isfinite(uv.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("make", LENSES, ids=LENS_IDS)
def test_fused_kernel_lens_at_any_magnitude(make, dtype):
    """The numba kernels' branch-free lens (``_project_kernels._project``, float64 inside) agrees with itself at the
    unit point, Jacobian divided by |p|, up to float64 max; infinite coordinates give NaN (the footprint's NaN
    guard then drops the Gaussian). It used to overflow as ``project`` did."""
    import numba

    from parksim.render import _project_kernels as pk
    from parksim.render.project_fast import _MODEL_IDS, _lens

    @numba.njit
    def batch(model: int, lens: np.ndarray, axis_eps: float, tiny: float, pts: np.ndarray) -> np.ndarray:
        out = np.empty((pts.shape[0], 8))
        for i in range(pts.shape[0]):
            o = pk._project(model, lens, axis_eps, tiny, pts[i, 0], pts[i, 1], pts[i, 2])
            for k in range(8):
                out[i, k] = o[k]
        return out

    cam = make()
    args = (_MODEL_IDS[type(cam)], _lens(cam), math.sqrt(torch.finfo(dtype).eps), torch.finfo(dtype).tiny)
    p = magnitude_cases(dtype).double()
    if dtype == torch.float32:
        p = torch.cat([p, magnitude_cases(torch.float64)[-12:]])   # float64 max: the kernel's own range
    unit, m, n = unit_points(p)
    got, ref = torch.from_numpy(batch(*args, p.numpy())), torch.from_numpy(batch(*args, unit.numpy()))
    f64 = torch.float64
    assert ((got[:, :2] - ref[:, :2]).abs().amax(-1) <= MAX_ULPS * ulp(ref[:, :2].abs().amax(-1), f64)).all()
    jac, ref_jac = got[:, 2:] * m * n, ref[:, 2:]
    assert ((jac - ref_jac).abs().amax(-1) <= MAX_ULPS * ulp(ref_jac.abs().amax(-1), f64)).all()
    inf = torch.tensor([[0.0, 0.0, math.inf], [1.0, 2.0, math.inf], [-math.inf, 0.0, 0.0]], dtype=f64)
    assert torch.isnan(torch.from_numpy(batch(*args, inf.numpy()))[:, :2]).all()
