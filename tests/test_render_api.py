"""render(): cameras, poses, scale, BEV, and end-to-end differentiability (camera -> IPM -> BEV)."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

import parksim.render.api as api
from parksim.camera import OpenCVFisheye
from parksim.gaussians import GaussianScene
from parksim.geometry import make_transform, pose_from_xy_yaw
from parksim.render import RenderResult, render
from parksim.rig import BEVSpec, Rig, RigCamera

# camera x, y, z (right, down, forward) in vehicle axes (x forward, y left, z up), looking forward
_R_FRONT = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
_R_YAW_PI = torch.tensor([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def tiny_rig(width: int = 32, height: int = 24) -> Rig:
    """Front and rear 190 deg fisheyes 1 m up, 16x16 px BEV at 0.5 m/px."""
    def cam(name: str, R: torch.Tensor, x: float) -> RigCamera:
        model = OpenCVFisheye(width, height, 6.0, 6.0, (width - 1) / 2, (height - 1) / 2, [0.02, 0.0, 0.0, 0.0])
        return RigCamera(name, model, make_transform(R, torch.tensor([x, 0.0, 1.0], dtype=torch.float64)))
    return Rig({"front": cam("front", _R_FRONT, 2.0), "rear": cam("rear", _R_YAW_PI @ _R_FRONT, -1.0)},
               BEVSpec(width=16, height=16, m_per_px=0.5))


def ground_scene(n: int = 12, dtype: torch.dtype = torch.float32, seed: int = 0) -> GaussianScene:
    """Flat Gaussians on the ground in front of and behind the car."""
    g = torch.Generator().manual_seed(seed)
    x = torch.cat([torch.rand(n // 2, generator=g) * 3 + 3.0, -torch.rand(n - n // 2, generator=g) * 3 - 2.0])
    y = torch.rand(n, generator=g) * 3 - 1.5
    means = torch.stack([x, y, torch.zeros(n)], dim=-1)
    log_scales = torch.log(torch.tensor([0.5, 0.5, 0.05])).expand(n, 3).clone()
    sh = torch.rand(n, 4, 3, generator=g) - 0.5
    return GaussianScene(means, torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).clone(), log_scales,
                         torch.full((n,), 1.5), sh, sh_degree=1).to(dtype)


def test_render_shapes_and_ranges():
    rig = tiny_rig()
    out = render(ground_scene(), rig, (0.0, 0.0, 0.0), backend="torch")
    assert isinstance(out, RenderResult) and out.bev is None
    assert set(out.images) == {"front", "rear"}
    for name in rig.names:
        img, a, d = out.images[name], out.alpha[name], out.depth[name]
        assert img.shape == (24, 32, 3) and a.shape == (24, 32) and d.shape == (24, 32)
        assert img.dtype == torch.float32 and 0 <= img.min() and img.max() <= 1
        assert a.max() > 0.5                                  # something is seen by every camera
        hit = a > 0.5
        assert (d[hit] > 0.5).all() and (d[hit] < 10).all()  # metres along the ray


def test_only_requested_cameras_are_projected(monkeypatch):
    calls = []
    original = api.project_gaussians

    def spy(means_cam, cov, camera, **kw):
        calls.append(camera)
        return original(means_cam, cov, camera, **kw)

    monkeypatch.setattr(api, "project_gaussians", spy)
    rig = tiny_rig()
    out = render(ground_scene(), rig, (0.0, 0.0, 0.0), cameras=["rear"], backend="torch")
    assert list(out.images) == ["rear"] and calls == [rig.cameras["rear"].model]
    with pytest.raises(KeyError, match="left"):
        render(ground_scene(), rig, (0.0, 0.0, 0.0), cameras=["left"])


def test_pose_forms_agree_and_pose_moves_the_view():
    rig, scene = tiny_rig(), ground_scene()
    a = render(scene, rig, (1.0, -0.5, 0.3), cameras=["front"], backend="torch").images["front"]
    b = render(scene, rig, pose_from_xy_yaw(1.0, -0.5, 0.3), cameras=["front"], backend="torch").images["front"]
    torch.testing.assert_close(a, b)
    c = render(scene, rig, (0.0, 0.0, math.pi), cameras=["front"], backend="torch").images["front"]
    rear = render(scene, rig, (-1.0, 0.0, 0.0), cameras=["rear"], backend="torch").images["rear"]
    assert (a - c).abs().max() > 0.05
    torch.testing.assert_close(c, rear, atol=1e-4, rtol=0)   # turned around = the rear camera, 3 m further back


def test_scale_and_background():
    rig = tiny_rig()
    out = render(ground_scene(), rig, (0.0, 0.0, 0.0), scale=0.5, backend="torch")
    assert out.images["front"].shape == (12, 16, 3)
    empty = render(ground_scene(), rig, (500.0, 0.0, 0.0), bg=(0.2, 0.4, 0.6), backend="torch")
    torch.testing.assert_close(empty.images["front"], torch.tensor([0.2, 0.4, 0.6]).expand(24, 32, 3))
    assert (empty.depth["front"] == 0).all()


def test_bev_only_when_asked_and_cached():
    rig = tiny_rig()
    out = render(ground_scene(), rig, (0.0, 0.0, 0.0), bev=True, backend="torch")
    assert out.bev.shape == (16, 16, 3) and torch.isfinite(out.bev).all() and out.bev.max() > 0.05
    view = api._rig_view(rig, 1.0, ("front", "rear"))
    ipm = view.ipm
    render(ground_scene(), rig, (0.0, 0.0, 0.0), bev=True, backend="torch")
    assert api._rig_view(rig, 1.0, ("front", "rear")).ipm is ipm


def test_opaque_and_hard_scenes_stay_finite():
    scene = ground_scene()
    scene.opacity_logits = torch.full_like(scene.opacity_logits, 60.0)   # opacity -> 1
    scene.quats[0] = 0.0                                                    # zero quaternion
    scene.log_scales[1] = 5.0                                               # huge
    scene.log_scales[2] = -100.0                                            # zero scale
    out = render(scene, tiny_rig(), (0.0, 0.0, 0.0), bev=True, backend="torch")
    for t in [*out.images.values(), *out.alpha.values(), *out.depth.values(), out.bev]:
        assert torch.isfinite(t).all()


def test_render_is_differentiable_to_the_bev():
    """Float64, torch backend: the gradient of a BEV loss wrt the means matches finite differences."""
    rig = tiny_rig()
    scene = ground_scene(n=6, dtype=torch.float64)
    weights = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def loss(means: torch.Tensor) -> torch.Tensor:
        s = GaussianScene(means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh, scene.sh_degree)
        return (render(s, rig, (0.0, 0.0, 0.0), bev=True, backend="torch").bev * weights).sum()

    means = scene.means.clone().requires_grad_()
    (grad,) = torch.autograd.grad(loss(means), means)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    eps = 1e-6
    for i, k in [(0, 0), (1, 1), (4, 0), (3, 2)]:
        d = torch.zeros_like(means)
        d[i, k] = eps
        fd = (loss(scene.means + d) - loss(scene.means - d)) / (2 * eps)
        assert grad[i, k].item() == pytest.approx(fd.item(), rel=1e-4, abs=1e-7)


def _sh3_scene(n: int, dtype: torch.dtype) -> GaussianScene:
    """``ground_scene`` with degree-3 colours, a Gaussian at a camera centre and one behind the front camera."""
    s = ground_scene(n=n, dtype=dtype)
    sh = torch.rand(n, 16, 3, generator=torch.Generator().manual_seed(3), dtype=dtype) - 0.5
    means = s.means.clone()
    means[0] = torch.tensor([2.0, 0.0, 1.0], dtype=dtype)      # the front camera's centre
    means[1] = torch.tensor([1.5, 0.3, 1.2], dtype=dtype)      # just behind the front camera's image plane
    return GaussianScene(means, s.quats, s.log_scales, s.opacity_logits, sh, sh_degree=3)


def test_one_pass_inference_matches_the_differentiable_path():
    """Plain tensors take the one-pass kernel (all cameras, SH in the kernel); it equals the autograd path."""
    rig, pose = tiny_rig(64, 48), (0.3, -0.2, 0.1)
    scene = _sh3_scene(40, torch.float64)
    cams = [rig.cameras[n] for n in rig.names]
    assert api._fast_path(scene, pose, cams, "ut", "auto")
    bg = (0.2, 0.5, 0.9)   # seen behind partly transparent pixels and outside the lens circle
    fast = render(scene, rig, pose, bev=True, bg=bg)
    leaves = [t.clone().requires_grad_() for t in (scene.means, scene.quats, scene.log_scales, scene.opacity_logits,
                                                   scene.sh)]
    grad_scene = GaussianScene(*leaves, sh_degree=3)
    assert not api._fast_path(grad_scene, pose, cams, "ut", "auto")
    ref = render(grad_scene, rig, pose, bev=True, bg=bg)
    assert fast.bev is not None and float(fast.alpha["front"].max()) > 0.5
    partial = (fast.alpha["front"] > 0.01) & (fast.alpha["front"] < 0.99)
    assert bool(partial.any()) and float(fast.alpha["front"].min()) == 0.0
    for name in rig.names:
        torch.testing.assert_close(fast.images[name], ref.images[name].detach(), atol=1e-5, rtol=0)
        torch.testing.assert_close(fast.alpha[name], ref.alpha[name].detach(), atol=1e-5, rtol=0)
        torch.testing.assert_close(fast.depth[name], ref.depth[name].detach(), atol=1e-4, rtol=0)
    torch.testing.assert_close(fast.bev, ref.bev.detach(), atol=1e-5, rtol=0)
    with torch.no_grad():   # no_grad takes the one-pass kernel even for leaves that require grad
        assert api._fast_path(grad_scene, pose, cams, "ut", "auto")
        torch.testing.assert_close(render(grad_scene, rig, pose, bg=bg).images["rear"], fast.images["rear"])


def test_one_pass_inference_hard_scene_stays_finite():
    scene = _sh3_scene(12, torch.float32)
    scene.opacity_logits = torch.full_like(scene.opacity_logits, 60.0)
    scene.quats[2] = 0.0
    scene.log_scales[3] = 5.0
    scene.log_scales[4] = -100.0
    scene.log_scales[5, 2] = -104.0                                         # denormal scale
    out = render(scene, tiny_rig(), (0.0, 0.0, 0.0), bev=True)
    for t in [*out.images.values(), *out.alpha.values(), *out.depth.values(), out.bev]:
        assert torch.isfinite(t).all()


def test_inference_scratch_memory_never_leaks_into_results():
    """The inference path reuses per-thread scratch memory: earlier results must stay intact, and renders on
    several threads at once must equal the same renders one after another."""
    rig, scene = tiny_rig(64, 48), ground_scene(40)
    poses = [(0.0, 0.0, 0.0), (0.8, -0.4, 0.5), (-0.5, 0.3, -0.7), (0.2, 0.6, 2.0)]
    with torch.no_grad():
        first = [render(scene, rig, p, bev=True) for p in poses]
        kept = [{k: v.clone() for k, v in r.images.items()} for r in first]
        again = render(scene, rig, poses[1], bev=True)                  # writes over the scratch once more
        for r, copy in zip(first, kept):
            assert all(torch.equal(r.images[k], copy[k]) for k in copy)
        assert all(torch.equal(again.images[k], first[1].images[k]) for k in rig.names)
        assert not torch.equal(first[0].images["front"], first[1].images["front"])
        with ThreadPoolExecutor(max_workers=4) as pool:
            parallel = list(pool.map(lambda p: render(scene, rig, p, bev=True), poses * 3))
    for r, ref in zip(parallel, first * 3):
        assert all(torch.equal(r.images[k], ref.images[k]) and torch.equal(r.depth[k], ref.depth[k])
                   for k in rig.names)
        assert torch.equal(r.bev, ref.bev)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the gsplat backend needs CUDA")
def test_render_on_cuda_matches_cpu() -> None:
    """The whole render() on CUDA (torch UT projection + gsplat) gives the CPU path's views, BEV and gradients.

    Tolerance 1e-3 in [0, 1] colour (a quarter of 1/255): both run float32 with different operation orders,
    and no Gaussian here reaches gsplat's 0.999 alpha clamp (opacity 0.82).
    """
    pytest.importorskip("gsplat")
    rig, pose = tiny_rig(64, 48), (0.3, -0.2, 0.1)
    cpu_scene, gpu_scene = ground_scene(40, seed=3), ground_scene(40, seed=3).to(device="cuda")
    with torch.no_grad():
        cpu = render(cpu_scene, rig, pose, bev=True, backend="numba")
        gpu = render(gpu_scene, rig, pose, bev=True, backend="gsplat")
    for name in rig.names:
        for want, got in ((cpu.images[name], gpu.images[name]), (cpu.alpha[name], gpu.alpha[name])):
            assert got.device.type == "cuda" and (got.cpu() - want).abs().max() <= 1e-3
    assert (gpu.bev.cpu() - cpu.bev).abs().max() <= 1e-3
    grads = []
    for scene, backend in ((cpu_scene, "numba"), (gpu_scene, "gsplat")):
        means = scene.means.detach().clone().requires_grad_(True)
        out = render(GaussianScene(means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh,
                                   sh_degree=scene.sh_degree), rig, pose, bev=True, backend=backend)
        out.bev.sum().backward()
        grads.append(means.grad.cpu())
    assert torch.isfinite(grads[1]).all()
    assert (grads[1] - grads[0]).abs().max() <= 1e-2 * grads[0].abs().max()
