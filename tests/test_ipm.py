"""IPM on a synthetic four-fisheye AVM rig: blending weights, gradient locality, back-projection, errors."""

import math

import pytest
import torch

from parksim.camera import OpenCVFisheye
from parksim.geometry import make_transform
from parksim.ipm import IPM
from parksim.rig import BEVSpec, Rig, RigCamera


def look(yaw: float, pitch_down: float) -> torch.Tensor:
    """Rotation camera -> vehicle for a camera looking along ``yaw`` tilted down by ``pitch_down``."""
    fwd = torch.tensor([math.cos(yaw) * math.cos(pitch_down), math.sin(yaw) * math.cos(pitch_down),
                        -math.sin(pitch_down)], dtype=torch.float64)
    right = torch.tensor([math.sin(yaw), -math.cos(yaw), 0.0], dtype=torch.float64)
    down = torch.linalg.cross(fwd, right)
    return torch.stack([right, down, fwd], dim=1)


def avm_rig(w: int = 96, h: int = 72, bev_px: int = 80) -> Rig:
    """Front/rear bumper and two mirror fisheyes (190 deg), BEV 8 m x 8 m around the car centre."""
    def cam(name, yaw, pitch, xyz):
        model = OpenCVFisheye(w, h, w / 3.2, w / 3.2, (w - 1) / 2, (h - 1) / 2, [0.03, -0.01, 0.0, 0.0], 190.0)
        return RigCamera(name, model, make_transform(look(yaw, pitch), torch.tensor(xyz, dtype=torch.float64)))
    cams = {"front": cam("front", 0.0, math.radians(30), [3.6, 0.0, 0.6]),
            "rear": cam("rear", math.pi, math.radians(30), [-0.9, 0.0, 0.8]),
            "left": cam("left", math.pi / 2, math.radians(60), [2.0, 1.0, 1.0]),
            "right": cam("right", -math.pi / 2, math.radians(60), [2.0, -1.0, 1.0])}
    return Rig(cams, BEVSpec(bev_px, bev_px, 8.0 / bev_px, 1.35, 0.0, (-0.9, 3.6, -0.95, 0.95)))


@pytest.fixture(scope="module")
def rig():
    return avm_rig()


@pytest.fixture(scope="module")
def ipm(rig):
    return IPM(rig, dtype=torch.float64)


def test_weights_sum_to_one_where_seen_and_zero_under_the_car(rig, ipm):
    total = sum(ipm.weights.values())
    assert torch.allclose(total[ipm.mask], torch.ones((), dtype=torch.float64), atol=1e-12)
    assert (total[~ipm.mask] == 0).all()
    xy = rig.bev.pixel_to_ground(torch.tensor([[40.0, 40.0]]))  # BEV centre: under the car
    assert not ipm.mask[40, 40] and -0.9 <= float(xy[0, 0]) <= 3.6
    assert ipm.mask.float().mean() > 0.7                          # four fisheyes see most of the ground
    for w in ipm.weights.values():
        assert (w >= 0).all() and (w <= 1).all()


def max_weight_step(ipm: IPM) -> float:
    """Largest weight change between neighbouring BEV pixels, away from the car's edge."""
    inner = ipm.mask.clone()
    inner[1:] &= ipm.mask[:-1]
    inner[:-1] &= ipm.mask[1:]
    inner[:, 1:] &= ipm.mask[:, :-1]
    inner[:, :-1] &= ipm.mask[:, 1:]
    steps = []
    for w in ipm.weights.values():
        steps.append((w[1:] - w[:-1]).abs()[inner[1:] & inner[:-1]].max())
        steps.append((w[:, 1:] - w[:, :-1]).abs()[inner[:, 1:] & inner[:, :-1]].max())
    return float(max(steps))


def test_blend_has_no_hard_seams(ipm):
    # Continuous weights: halving the BEV pixel size about halves the largest step (a hard seam would not shrink).
    coarse = max_weight_step(ipm)
    fine = max_weight_step(IPM(avm_rig(bev_px=160), dtype=torch.float64))
    assert coarse < 0.5
    assert fine < 0.65 * coarse


def bilinear_support(coords: torch.Tensor, weight: torch.Tensor, w: int, h: int) -> torch.Tensor:
    """Fisheye pixels touched by bilinear taps at ``coords`` where ``weight > 0``."""
    mask = torch.zeros(h, w, dtype=torch.bool)
    c = coords[weight > 0]
    for du in (0, 1):
        for dv in (0, 1):
            u = (c[:, 0].floor() + du).long()
            v = (c[:, 1].floor() + dv).long()
            ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
            mask[v[ok], u[ok]] = True
    return mask


def test_gradient_reaches_only_the_pixels_the_bev_sees(rig, ipm):
    images = {n: torch.rand(rig.cameras[n].model.height, rig.cameras[n].model.width, 3, dtype=torch.float64,
                            requires_grad=True) for n in rig.names}
    region = torch.zeros(rig.bev.height, rig.bev.width, dtype=torch.bool)
    region[5:20, 30:50] = True  # ground 4.5-6 m ahead of the rear axle
    bev = ipm(images)
    (bev[region] ** 2).sum().backward()
    touched = 0
    for n in rig.names:
        m = rig.cameras[n].model
        weight = torch.where(region, ipm.weights[n], torch.zeros(()))
        support = bilinear_support(ipm.pixel_coords[n], weight, m.width, m.height)
        grad_nonzero = images[n].grad.abs().sum(-1) > 0
        assert not (grad_nonzero & ~support).any(), n
        touched += int(grad_nonzero.sum())
    assert images["rear"].grad.abs().sum() == 0       # the rear camera does not see ahead of the car
    assert images["front"].grad.abs().sum() > 0
    assert touched > 50


def test_to_cameras_round_trip_on_a_smooth_map(rig, ipm):
    xy = rig.bev.pixel_to_ground(torch.stack(torch.meshgrid(torch.arange(80.0), torch.arange(80.0), indexing="xy"),
                                             -1).double())
    f = torch.stack([torch.sin(xy[..., 0] / 2), torch.cos(xy[..., 1] / 3), 0.1 * xy[..., 0]], -1)
    cams = ipm.to_cameras(f)
    for n, img in cams.items():
        m = rig.cameras[n].model
        assert img.shape == (m.height, m.width, 3)
    # The top rows of the side cameras see the sky or walls: their rays miss the ground -> 0.
    assert (cams["left"][0] == 0).all()
    again = ipm(cams)
    # Compare where every camera that contributes also back-projected (its pixel saw the BEV).
    inner = ipm.mask.clone()
    inner[:4] = inner[-4:] = False
    inner[:, :4] = inner[:, -4:] = False
    err = (again - f).abs().amax(-1)[inner]
    assert err.median() < 0.01 and err.quantile(0.95) < 0.05


def test_batched_and_single_channel_inputs(rig, ipm):
    imgs = {n: torch.rand(2, rig.cameras[n].model.height, rig.cameras[n].model.width, 1, dtype=torch.float64)
            for n in rig.names}
    batched = ipm(imgs)
    assert batched.shape == (2, 80, 80, 1)
    single = ipm({n: v[1, ..., 0] for n, v in imgs.items()})
    assert single.shape == (80, 80)
    assert torch.allclose(single, batched[1, ..., 0])


def test_bad_inputs_give_clear_errors(rig, ipm):
    imgs = {n: torch.rand(rig.cameras[n].model.height, rig.cameras[n].model.width, 3) for n in rig.names}
    with pytest.raises(ValueError, match="missing \\['rear'\\]"):
        ipm({n: v for n, v in imgs.items() if n != "rear"})
    imgs["left"] = torch.rand(10, 12, 3)
    with pytest.raises(ValueError, match="camera 'left' is 12x10 \\(WxH\\) but the rig says 96x72"):
        ipm(imgs)
    with pytest.raises(ValueError, match="unknown cameras \\['top'\\]"):
        IPM(rig, cameras=["front", "top"])
    with pytest.raises(ValueError, match="BEV map is 3x3"):
        ipm.to_cameras(torch.zeros(3, 3))


def test_inference_gather_equals_the_grid_sample_path(rig, ipm):
    """Without gradients the BEV is a numba gather over precomputed taps; it must equal grid_sample's blend,
    image borders (zero padding) included."""
    g = torch.Generator().manual_seed(3)
    for channels in (3, 1):
        images = {n: torch.rand(72, 96, channels, generator=g) for n in rig.names}
        assert ipm._gather_applies(images)
        fast = ipm(images)
        leaves = {n: img.clone().requires_grad_() for n, img in images.items()}
        assert not ipm._gather_applies(leaves)
        ref = ipm(leaves).detach()
        assert fast.shape == ref.shape == (80, 80, channels)
        torch.testing.assert_close(fast, ref, atol=2e-6, rtol=0)
        assert float(fast.abs().max()) > 0.5
        with torch.no_grad():                                   # no_grad takes the gather even for leaves
            assert ipm._gather_applies(leaves)
            torch.testing.assert_close(ipm(leaves), fast, atol=0, rtol=0)
