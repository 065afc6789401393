"""The GPU projection kernels, checked without a GPU: their bodies on numba's CPU target against the float64 torch
reference (values and gradients, every built-in lens model, several views at once), and their CUDA build compiled to
PTX for an H100 (sm_90) when numba-cuda and NVVM are installed, which proves that the device code compiles."""

from __future__ import annotations

import math
import sys

import pytest
import torch
from test_ocam import variant
from test_project_fast import cameras, random_scene

from parksim.camera import CameraModel, OCamFisheye
from parksim.geometry import make_transform, rotation_from_quaternion
from parksim.render.project_device import project_views_device, view_transforms
from parksim.render.projection import FAR_M, NEAR_M, UTParams, fused_config, project_gaussians
from parksim.render.view_colors import view_colors_torch
from tolerances import f32_tol, f32_ulp

SH_DEGREE = 3


def views(n_views: int = 3) -> torch.Tensor:
    """``[V, 4, 4]`` float64 camera-to-world poses around the origin (the scene is centred on the first)."""
    out = [torch.eye(4, dtype=torch.float64)]
    for k in range(1, n_views):
        q = torch.tensor([1.0, 0.3 * k, -0.2, 0.4 * k], dtype=torch.float64)
        out.append(make_transform(rotation_from_quaternion(q), torch.tensor([0.5 * k, -0.3, 0.2 * k],
                                                                                dtype=torch.float64)))
    return torch.stack(out)


def scene(n: int, seed: int) -> tuple[torch.Tensor, ...]:
    """(means, quats, log_scales, sh) float64: ``random_scene``'s awkward rows plus degree-3 SH."""
    means, quats, log_scales = random_scene(n, seed)
    g = torch.Generator().manual_seed(seed + 100)
    sh = torch.randn(len(means), 16, 3, generator=g, dtype=torch.float64) * 0.3
    return means, quats, log_scales, sh


LENSES = ["opencv", "radial", "pinhole", "ocam_invpol", "ocam_both", "ocam_ss"]
"""The built-in models; OCam defined by its world2cam series (invpol), and by cam2world (ss) with its radius solved
by Newton from invpol (both) or from a straight line (ss alone)."""


def lens(name: str) -> CameraModel:
    """``test_project_fast.cameras()``'s lenses, and ``test_ocam``'s OCamCalib lens (``ocam_<variant>``)."""
    return variant(name.removeprefix("ocam_")) if name.startswith("ocam_") else cameras()[name]


def configs(cam: CameraModel, n_views: int, method: str = "ut") -> list:
    return [fused_config(UTParams(), NEAR_M, FAR_M, float(max(cam.width, cam.height)), ewa=method == "ewa")] * n_views


def reference(leaves: tuple[torch.Tensor, ...], T: torch.Tensor, cam: CameraModel, method: str = "ut"
              ) -> list[dict[str, torch.Tensor]]:
    """Per view, the float64 torch path: ``index`` of the drawn Gaussians and their means2d, conics, colours,
    depths (differentiable in the leaves and ``T``)."""
    means, quats, log_scales, sh = leaves
    rots, trans, centres = view_transforms(T)
    out = []
    for v in range(T.shape[0]):
        p = project_gaussians(means @ rots[v].T + trans[v], (quats, log_scales, rots[v]), cam, method=method,
                              backend="torch")
        keep = p.valid.nonzero().squeeze(1)
        index = p.index[keep]
        out.append({"index": index, "means2d": p.means2d[keep], "conics": p.conics[keep], "depths": p.depths[keep],
                    "colors": view_colors_torch(sh, means, index, centres[v], SH_DEGREE)})
    return out


@pytest.mark.parametrize("method", ["ut", "ewa"])
@pytest.mark.parametrize("name", LENSES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_matches_float64_torch_path(name, dtype, method):
    cam, T = lens(name), views()
    data = scene(2000, seed=11)
    got = project_views_device(*(t.to(dtype) for t in data), SH_DEGREE, T, [cam] * len(T),
                               configs(cam, len(T), method))
    ref = reference(data, T, cam, method)
    for t in got:
        assert torch.isfinite(t.double()).all()
    for v, r in enumerate(ref):
        drawn = got.drawn[v].nonzero().squeeze(1)
        # the drawn sets agree but for footprints whose 3-sigma box touches the image border within rounding
        assert len(set(drawn.tolist()) ^ set(r["index"].tolist())) <= max(2, len(r["index"]) // 500)
        both = torch.tensor(sorted(set(drawn.tolist()) & set(r["index"].tolist())), dtype=torch.long)
        assert len(both) > 100
        rows = torch.searchsorted(r["index"], both)
        undrawn = ~got.drawn[v]
        for key in ("means2d", "conics", "colors"):
            assert not getattr(got, key)[v][undrawn].any()
        want = {k: r[k][rows] for k in ("means2d", "conics", "colors", "depths")}
        have = {k: getattr(got, k)[v][both].double() for k in want}
        if dtype == torch.float64:
            assert (have["means2d"] - want["means2d"]).abs().max() <= 1e-9
            # EWA's conic comes from the lens Jacobian, here analytic and in torch by forward-mode AD: two roundings
            # of a derivative, which differ most on the rim (behind the lens, r << |p|): 5.6e-9 seen there
            bound = 1e-9 if method == "ut" else 2e-8
            assert ((have["conics"] - want["conics"]).abs() <= bound * want["conics"].abs().amax(-1, True)).all()
            torch.testing.assert_close(have["colors"], want["colors"], rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(have["depths"], want["depths"], rtol=1e-12, atol=0.0)
        else:
            # float64 arithmetic inside: the float32 rounding of the inputs and the output, as the fused CPU
            # kernel's test derives (test_project_fast.test_forward_matches_torch_path)
            assert (have["means2d"] - want["means2d"]).abs().max() <= f32_tol(want["means2d"], ulps=2)
            assert ((have["conics"] - want["conics"]).abs() <= f32_tol(want["conics"], ulps=256, dim=-1)).all()
            # colours: 16 SH terms of float32-rounded coefficients (each |c| <= ~1.5) and directions
            assert ((have["colors"] - want["colors"]).abs() <= f32_tol(want["colors"], ulps=64) + 1e-6).all()
            assert ((have["depths"] - want["depths"]).abs() <= 4 * f32_ulp(want["depths"])).all()


GRADIENT_CASES = [(name, dtype, "ut") for name in LENSES for dtype in (torch.float32, torch.float64)] + [
    (name, torch.float64, "ewa") for name in ("opencv", "radial", "pinhole", "ocam_invpol")] + [
    ("opencv", torch.float32, "ewa")]
"""Every lens in both dtypes for the UT; EWA (whose Hessian-vector products are central differences) on each model
family in float64 and on the fisheye in float32. Not OCam by ss: the torch reference's Jacobian of the solved radius
is exact but its derivative is not (one Newton step under autograd gives first derivatives only)."""


@pytest.mark.parametrize("name, dtype, method", GRADIENT_CASES)
def test_gradients_match_float64_autograd(name, dtype, method):
    """Gradients of the means, quaternions, log-scales, SH and the views' poses against float64 autograd through the
    torch path (for EWA, through its forward-mode Jacobian), for a random linear loss on the rows both draw."""
    cam, T = lens(name), views()
    data = scene(800, seed=12)
    leaves = tuple(t.to(dtype).detach().requires_grad_() for t in data)
    T_leaf = T.to(dtype).detach().requires_grad_()
    got = project_views_device(*leaves, SH_DEGREE, T_leaf, [cam] * len(T), configs(cam, len(T), method))
    ref_leaves = tuple(t.detach().requires_grad_() for t in data)
    T_ref = T.detach().requires_grad_()
    ref = reference(ref_leaves, T_ref, cam, method)
    # EWA on the rim (centre past theta_max) has a rank-1 Jacobian: blurred, the footprint's small eigenvalue sits
    # exactly on the clamp's floor, a kink whose two one-sided gradients are both valid; compared within the lens
    rots, trans, _ = view_transforms(T)
    g = torch.Generator().manual_seed(13)
    loss = loss_ref = 0.0
    for v, r in enumerate(ref):
        both = torch.tensor(sorted(set(got.drawn[v].nonzero().squeeze(1).tolist()) & set(r["index"].tolist())),
                            dtype=torch.long)
        if method == "ewa":
            centre = data[0][both] @ rots[v].T + trans[v]
            both = both[torch.atan2(centre[:, :2].norm(dim=-1), centre[:, 2]) < cam.theta_max - 1e-4]
        rows = torch.searchsorted(r["index"], both)
        scale = 1.0 / r["conics"][rows][:, :1].detach()   # conics scaled by the squared footprint: no term dominates
        for key, weight in (("means2d", 1.0), ("conics", scale), ("colors", 100.0), ("depths", 10.0)):
            w = torch.randn(r[key][rows].shape, generator=g, dtype=torch.float64) * weight
            loss = loss + (getattr(got, key)[v][both] * w.to(dtype)).sum()
            loss_ref = loss_ref + (r[key][rows] * w).sum()
    grads = torch.autograd.grad(loss, (*leaves, T_leaf))
    ref_grads = torch.autograd.grad(loss_ref, (*ref_leaves, T_ref))
    bound = 1e-7 if dtype == torch.float64 else 1e-3
    for label, gf, gr in zip(("means", "quats", "log_scales", "sh", "pose"), grads, ref_grads):
        assert torch.isfinite(gf).all(), label
        gf, gr = gf.double().flatten(1), gr.flatten(1)
        err = (gf - gr).norm(dim=-1) / gr.norm(dim=-1).clamp_min(1e-6 * gr.norm(dim=-1).max())
        assert err.max() <= bound, (label, err.max().item())


def test_gradcheck_small_scene_two_views():
    """torch's finite-difference gradcheck of every output w.r.t. every input, two views, the adaptive set included."""
    cam = cameras()["opencv"]
    d = [math.radians(80.0), math.radians(30.0)]
    means = torch.tensor([[4 * math.sin(d[0]) * math.cos(d[1]), 4 * math.sin(d[0]) * math.sin(d[1]),
                           4 * math.cos(d[0])], [2.0, 1.0, 3.0], [1.0, 0.2, -0.05]], dtype=torch.float64)
    quats = torch.tensor([[0.9, 0.2, -0.3, 0.1], [0.3, 0.1, 0.9, -0.2], [1, 0.2, 0, 0]], dtype=torch.float64)
    ls = torch.log(torch.tensor([[0.6, 0.5, 0.3], [0.2, 0.1, 0.05], [0.3, 0.2, 0.1]], dtype=torch.float64))
    sh = torch.randn(3, 16, 3, generator=torch.Generator().manual_seed(14), dtype=torch.float64) * 0.3
    T = views(2)
    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, ls, sh, T))

    def f(m, q, s, c, t):
        out = project_views_device(m, q, s, c, SH_DEGREE, t, [cam, cam], configs(cam, 2))
        return out.means2d, out.conics, out.colors, out.depths

    assert torch.autograd.gradcheck(f, inputs)


def test_refuses_mismatched_views_and_unsupported_lens():
    cam, T = cameras()["opencv"], views(2)
    data = scene(10, seed=15)
    with pytest.raises(ValueError, match="2 poses, 1 cameras"):
        project_views_device(*data, SH_DEGREE, T, [cam], configs(cam, 1))
    ocam = OCamFisheye(640, 480, 239.5, 319.5, invpol=torch.tensor([300.0, 150.0, 10.0], requires_grad=True))
    with pytest.raises(ValueError, match="no device kernel for \\['OCamFisheye'"):
        project_views_device(*data, SH_DEGREE, T, [ocam, ocam], configs(cam, 2))


@pytest.mark.parametrize("kernel", ["views_forward", "views_backward"])
def test_cuda_kernels_compile_to_ptx(kernel, monkeypatch):
    """The CUDA kernels compile for an H100 (sm_90) with the float32 Gaussians the renderer passes: numba-cuda
    lowers every helper the bodies call (a helper that uses something the CUDA target lacks fails here, not on
    the user's GPU). Needs numba-cuda and NVVM (the test extra installs both); no GPU: numba-cuda asks the current
    device for its compute capability when it compiles a called device function, so the test answers (9, 0)."""
    pytest.importorskip("numba_cuda")
    from types import SimpleNamespace

    from numba import types

    from parksim.render import _cuda_kernels
    from parksim.render._numba_cuda import cuda

    cuda_dispatcher = sys.modules["numba.cuda.dispatcher"]
    monkeypatch.setattr(cuda_dispatcher, "get_current_device", lambda: SimpleNamespace(compute_capability=(9, 0)))
    f32, f64, i64 = types.float32, types.float64, types.int64
    a = types.Array
    common = (a(f32, 2, "C"), a(f32, 2, "C"), a(f32, 2, "C"), a(f32, 3, "C"), i64, a(f64, 3, "C"),
              a(f64, 2, "C"), a(f64, 2, "C"), a(i64, 1, "C"), a(f64, 2, "C"), a(f64, 2, "C"), a(f64, 2, "C"),
              a(f64, 1, "C"), a(f64, 1, "C"), a(f64, 2, "C"), a(f64, 1, "C"), a(f64, 1, "C"))
    if kernel == "views_forward":
        sig = (*common, a(f32, 3, "C"), a(f32, 3, "C"), a(f32, 3, "C"), a(f32, 2, "C"), a(types.uint8, 2, "C"))
    else:
        sig = (*common, a(types.uint8, 2, "C"), a(f32, 3, "C"), a(f32, 3, "C"), a(f32, 3, "C"), a(f32, 2, "C"),
               types.boolean, a(f32, 2, "C"), a(f32, 2, "C"), a(f32, 2, "C"), a(f32, 3, "C"), a(f64, 3, "C"))
    try:
        ptx, _ = cuda.compile_ptx(getattr(_cuda_kernels, kernel).py_func, sig, cc=(9, 0))
    except Exception as err:   # no NVVM library: numba-cuda installed without the toolkit
        if "nvvm" in str(err).lower() or "libnvrtc" in str(err).lower():
            pytest.skip(f"no NVVM/NVRTC: {err}")
        raise
    assert ".target sm_90" in ptx and ".entry" in ptx


def test_render_with_device_kernels_equals_the_cpu_paths():
    """render(projector="device") (what a CUDA scene runs, here on the kernels' CPU target): images, alpha, depth and
    BEV as the default CPU inference path, and gradients of every scene tensor as the CPU autograd path."""
    from test_render_api import ground_scene, tiny_rig

    from parksim.gaussians import GaussianScene
    from parksim.render import render

    rig, pose = tiny_rig(64, 48), (0.2, 0.1, 0.3)
    plain = ground_scene(40)
    a, b = render(plain, rig, pose, bev=True), render(plain, rig, pose, bev=True, projector="device")
    for name in rig.names:
        assert a.alpha[name].max() > 0.9
        for x, y in ((a.images[name], b.images[name]), (a.alpha[name], b.alpha[name]), (a.depth[name], b.depth[name])):
            assert (x - y).abs().max() <= f32_tol(x, ulps=8)
    assert (a.bev - b.bev).abs().max() <= f32_tol(a.bev, ulps=8)

    ramp = torch.linspace(0, 1, 64, dtype=torch.float64)[None, :, None]
    base = ground_scene(40, dtype=torch.float64)

    def grads(projector: str) -> tuple[torch.Tensor, ...]:
        leaves = [t.detach().clone().requires_grad_() for t in
                  (base.means, base.quats, base.log_scales, base.opacity_logits, base.sh)]
        out = render(GaussianScene(*leaves, sh_degree=1), rig, pose, bev=True, projector=projector)
        loss = out.bev.sum() + sum((out.images[n] * ramp).sum() + out.depth[n].sum() for n in rig.names)
        return torch.autograd.grad(loss, leaves)

    for label, x, y in zip(("means", "quats", "log_scales", "opacity", "sh"), grads("auto"), grads("device")):
        assert x.abs().max() > 0, label
        assert (x - y).norm() <= 1e-9 * x.norm(), label


def test_render_device_projector_serves_ewa_and_refuses_bad_names():
    """EWA through the device kernels renders what the torch EWA path renders (views, alpha, depth, BEV), both in
    float64 (in float32 the torch path rounds its forward-mode Jacobian, the kernels work in float64)."""
    from test_render_api import ground_scene, tiny_rig

    from parksim.render import render

    rig, pose, scene = tiny_rig(), (0.3, -0.2, 0.1), ground_scene(40, dtype=torch.float64)
    a = render(scene, rig, pose, bev=True, method="ewa")
    b = render(scene, rig, pose, bev=True, method="ewa", projector="device")
    for name in rig.names:
        assert a.alpha[name].max() > 0.9
        for x, y in ((a.images[name], b.images[name]), (a.alpha[name], b.alpha[name]), (a.depth[name], b.depth[name])):
            assert (x - y).abs().max() <= 1e-9 * max(float(x.abs().max()), 1.0)
    assert (a.bev - b.bev).abs().max() <= 1e-9
    with pytest.raises(ValueError, match="method must be 'ut' or 'ewa'"):
        render(scene, rig, (0.0, 0.0, 0.0), method="taylor", projector="device")
    with pytest.raises(ValueError, match="projector must be one of"):
        render(ground_scene(), tiny_rig(), (0.0, 0.0, 0.0), projector="gpu")


@pytest.mark.parametrize("projector", ["auto", "device"])
def test_render_batch_equals_render_at_each_pose(projector):
    """B poses in one call (one projection pass over B x C views) give what render gives at each pose."""
    from test_render_api import ground_scene, tiny_rig

    from parksim.render import render, render_batch

    rig, scene_ = tiny_rig(48, 32), ground_scene(30)
    poses = [(0.0, 0.0, 0.0), (0.5, -0.3, 0.4), (-1.0, 0.2, 3.0)]
    batch = render_batch(scene_, rig, poses, bev=True, projector=projector)
    assert len(batch) == len(poses)
    for pose, got in zip(poses, batch):
        want = render(scene_, rig, pose, bev=True, projector=projector)
        for name in rig.names:
            assert torch.equal(got.images[name], want.images[name])
            assert torch.equal(got.depth[name], want.depth[name])
        assert torch.equal(got.bev, want.bev)
    assert not torch.equal(batch[0].images["front"], batch[1].images["front"])


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (benchmarks/gpu_check.sh)")


@needs_cuda
@pytest.mark.parametrize("name", ["opencv", "radial", "pinhole"])
def test_cuda_kernels_equal_their_cpu_target(name):
    """On a GPU: the numba-cuda build gives the CPU target's values and gradients (float32 in and out, float64
    inside; only the GPU's fused multiply-adds and libdevice's transcendentals round differently)."""
    cam, T = cameras()[name], views()
    data = [t.to(torch.float32) for t in scene(20_000, seed=16)]
    out = {}
    for device in ("cpu", "cuda"):
        leaves = [t.to(device).requires_grad_() for t in data]
        T_leaf = T.to(device).requires_grad_()
        got = project_views_device(*leaves, SH_DEGREE, T_leaf, [cam] * len(T), configs(cam, len(T)))
        w = torch.Generator().manual_seed(17)
        loss = sum((o * torch.randn(o.shape, generator=w).to(device)).sum() for o in got[:4])
        out[device] = ([t.detach().cpu() for t in got], [g.cpu() for g in torch.autograd.grad(loss, [*leaves, T_leaf])])
    (cpu, g_cpu), (gpu, g_gpu) = out["cpu"], out["cuda"]
    drawn = cpu[4] & gpu[4]
    assert (cpu[4] ^ gpu[4]).sum() <= max(2, int(drawn.sum()) // 1000)   # footprints at the image border
    for label, a, b in zip(("means2d", "conics", "colors", "depths"), cpu[:4], gpu[:4]):
        assert ((a[drawn] - b[drawn]).abs() <= f32_tol(a[drawn], ulps=8, dim=-1 if a.dim() == 3 else None)).all(), \
            label
    for label, a, b in zip(("means", "quats", "log_scales", "sh", "pose"), g_cpu, g_gpu):
        a, b = a.double().flatten(1), b.double().flatten(1)
        err = (a - b).norm(dim=-1) / a.norm(dim=-1).clamp_min(1e-6 * a.norm(dim=-1).max())
        assert torch.quantile(err, 0.999) <= 1e-3, label


@needs_cuda
def test_render_on_cuda_uses_the_device_kernels_and_matches_cpu():
    """render() of a CUDA scene (device kernels + gsplat) against the CPU path: >= 45 dB and 99.9 % of pixels within
    1/255 per view (the tolerance of `parksim bench gpu`), the BEV too; render_batch on CUDA equals render."""
    pytest.importorskip("gsplat")
    from test_render_api import ground_scene, tiny_rig

    from parksim.render import render, render_batch

    rig, pose = tiny_rig(64, 48), (0.3, -0.2, 0.1)
    cpu_scene, gpu_scene = ground_scene(40, seed=3), ground_scene(40, seed=3).to(device="cuda")
    with torch.no_grad():
        cpu = render(cpu_scene, rig, pose, bev=True)
        gpu = render(gpu_scene, rig, pose, bev=True)
        batch = render_batch(gpu_scene, rig, [pose, (0.0, 0.0, 0.0)], bev=True)
    for want, got in [(cpu.images[n], gpu.images[n]) for n in rig.names] + [(cpu.bev, gpu.bev)]:
        diff = (got.cpu().double() - want.double()).abs()
        assert -10 * torch.log10(diff.pow(2).mean().clamp_min(1e-20)) >= 45.0
        assert (diff <= 1 / 255).all(-1).float().mean() >= 0.999
    for name in rig.names:
        assert (batch[0].images[name] - gpu.images[name]).abs().max() <= 1e-6


def test_gpu_memory_bound_and_refusal_through_the_server():
    """A render bounded past the GPU's memory is refused before it starts: 413 when it can never fit, 503 with
    Retry-After when not now; the bound grows with views, Gaussians and pixels."""
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from parksim.render.device_memory import (
        BYTES_PER_VIEW_GAUSSIAN,
        BYTES_PER_VIEW_PIXEL,
        check_device_memory,
        memory_verdict,
        render_bytes,
    )
    from parksim.server.app import _install_errors

    assert render_bytes(200_000, 4, 640 * 480) == 4 * (200_000 * BYTES_PER_VIEW_GAUSSIAN
                                                       + 640 * 480 * BYTES_PER_VIEW_PIXEL)
    assert render_bytes(200_000, 8, 640 * 480) == 2 * render_bytes(200_000, 4, 640 * 480)
    check_device_memory(torch.device("cpu"), 10**18)   # the CPU path is never refused here
    app = FastAPI()
    _install_errors(app)

    gib, card = 2**30, "NVIDIA H100 80GB HBM3"
    needed = render_bytes(1_000_000, 64 * 4, 320 * 240)   # 64 poses x 4 cameras of a 1e6 scene: 63 GiB
    assert memory_verdict(needed, available=79 * gib, total=80 * gib, card=card) is None
    assert memory_verdict(needed, available=20 * gib, total=80 * gib, card=card).never is False
    assert memory_verdict(needed, available=20 * gib, total=24 * gib, card=card).never is True

    @app.get("/render/{gib_total}")
    def refused(gib_total: int) -> None:
        raise memory_verdict(needed, available=20 * gib, total=gib_total * gib, card=card)

    client = TestClient(app)
    r = client.get("/render/24")
    assert r.status_code == 413 and f"{card} has 24.0 GiB" in r.json()["detail"]
    r = client.get("/render/80")
    assert r.status_code == 503 and r.headers["retry-after"] == "1" and "20.0 GiB is free now" in r.json()["detail"]


def test_an_empty_scene_renders_background_through_the_device_kernels():
    from test_render_api import ground_scene, tiny_rig

    from parksim.render import render

    empty = ground_scene(4).subset(torch.zeros(0, dtype=torch.long))
    out = render(empty, tiny_rig(), (0.0, 0.0, 0.0), projector="device", bev=True, bg=(0.0, 0.0, 0.0))
    for name in ("front", "rear"):
        assert not out.images[name].any() and not out.alpha[name].any() and not out.depth[name].any()
