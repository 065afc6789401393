"""``parksim bench gpu`` and the GPU options of the serving suites, as far as a machine without CUDA can check them:
the refusals (at once, one line, nothing written), the options ``--quick`` fills in, and the mapping of a rig onto
gsplat's fisheye model that the 3DGUT reference renders with. On a CUDA machine the suite runs end to end."""

from __future__ import annotations

import math
import sys
import types
from pathlib import Path

import pytest
import torch

from parksim.bench.cases import bev_rig, case
from parksim.bench.common import Timing
from parksim.bench.gut import gut_cameras, require_gut
from parksim.bench.record import Record, read_record
from parksim.bench.suites.gpu import GPUOptions, _batch_figures, _case_figures, _issue_size
from parksim.camera import RadialPolyFisheye
from parksim.cli import build_parser, main
from parksim.commands.options import options_from_args
from parksim.geometry import as_pose
from parksim.rig import Rig, RigCamera
from parksim.synth.rig import avm_rig

NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device: the suites run (see the CUDA test)")


def gpu_options(*argv: str) -> GPUOptions:
    """``parksim bench gpu ARGV`` parsed as the command does it."""
    args = build_parser().parse_args(["bench", "gpu", *argv])
    return options_from_args(GPUOptions, args, quick=args.quick)


def test_quick_is_the_small_preset_and_flags_win():
    full, quick = gpu_options(), gpu_options("--quick")
    assert (full.gaussians_b, full.gaussians_large, full.width_b, full.bev_px) == (200_000, 1_000_000, 640, 512)
    assert (full.batch_poses, full.width_batch, full.repeats, full.gut) == (64, 320, 11, True)
    assert (quick.gaussians_b, quick.gaussians_large, quick.batch_poses, quick.width_batch, quick.repeats) == (
        4_000, 8_000, 4, 80, 1)
    given = gpu_options("--quick", "--no-gut", "--batch-poses", "8", "--repeats", "3")
    assert (given.gut, given.batch_poses, given.repeats, given.width_batch) == (False, 8, 3, 80)


@NO_CUDA
def test_gpu_refuses_a_machine_without_cuda(tmp_path, capsys):
    assert main(["bench", "gpu", "--quick", "--quiet", "--work", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("parksim bench: error: no CUDA device: ") and err.count("\n") == 1
    assert not (tmp_path / "data").exists() and not (tmp_path / "results").exists()   # refused before any work


@NO_CUDA
@pytest.mark.parametrize("suite", ["server", "env"])
@pytest.mark.parametrize("device, why", [("cuda", "device 'cuda': no CUDA device here"),
                                         ("gpu", "device 'gpu': not one of auto, cpu, cuda, cuda:N")])
def test_serving_suites_refuse_a_device_at_once(tmp_path, capsys, suite, device, why):
    assert main(["bench", suite, "--quick", "--quiet", "--device", device, "--work", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"parksim bench: error: {why}") and err.count("\n") == 1
    assert not any(tmp_path.iterdir())   # no bundle made, no server started, no record


def test_the_issue_goals_apply_at_its_sizes_only():
    """Case (b) against 3DGUT carries the issue's goal at 4 x 640x480 + 512 BEV (by Gaussians and pass), the batch
    at 64 x 4 x 320x240 + BEV; smaller presets (--quick) carry none."""
    rig = bev_rig(avm_rig(640, 480, 600), 512)
    t = Timing(1.0, 1.0, 1)
    goals = {}
    for width, n, backward in [(640, 200_000, False), (640, 200_000, True), (640, 1_000_000, True),
                               (640, 4_000, False), (320, 200_000, False)]:
        c = case("b", "case (b)", n, width, rig, None, True, backward=backward)
        (_, vs_gut) = _case_figures(c, t, t, t, _issue_size(c, rig, 640, 480))
        assert vs_gut.reference_label.startswith("gsplat 3DGUT") and vs_gut.target.endswith("against gsplat 3DGUT")
        goals[width, n, backward] = vs_gut.goal
    assert goals == {(640, 200_000, False): "<= 3 ms", (640, 200_000, True): "<= 8 ms",
                     (640, 1_000_000, True): "<= 20 ms", (640, 4_000, False): None, (320, 200_000, False): None}
    batch = case("batch", "render_batch", 200_000, 320, rig, None, True)
    assert _issue_size(batch, rig, 320, 240) and not _issue_size(batch, bev_rig(avm_rig(), 256), 320, 240)
    (_, steps) = _batch_figures("64 poses x ...", 64, Timing(100.0, 90.0, 1), t, True)
    assert (steps.value, steps.unit, steps.goal, steps.better) == (640.0, "steps/s", ">= 500 steps/s", "higher")


def gsplat_fisheye(cams, points: torch.Tensor) -> torch.Tensor:
    """Pixels ``(C, P, 2)`` of world points ``(C, P, 3)`` by gsplat's fisheye model as its CUDA code states it
    (``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``, ``u = fx theta_d x / r + cx``), moved back to ParkSim's
    pixel centres (gsplat's are at ``j + 0.5``)."""
    V, K, k = cams.viewmats.double(), cams.Ks.double(), cams.radial.double()
    p = torch.einsum("cij,cpj->cpi", V[:, :3, :3], points) + V[:, None, :3, 3]
    r = p[..., :2].norm(dim=-1)
    theta = torch.atan2(r, p[..., 2])
    t2 = theta ** 2
    poly = 1 + t2 * (k[:, None, 0] + t2 * (k[:, None, 1] + t2 * (k[:, None, 2] + t2 * k[:, None, 3])))
    xy = (theta * poly / r)[..., None] * p[..., :2]
    return xy * K[:, None, [0, 1], [0, 1]] + K[:, None, [0, 1], [2, 2]] - 0.5


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_gut_cameras_put_every_point_where_the_rig_projects_it(scale):
    """The 3DGUT reference sees the scene through the rig's own lenses: each camera's viewmat, Ks and k1..k4 put a
    point where ParkSim's model puts it, within float32 rounding, at the size render() renders at that scale."""
    rig, pose = avm_rig(640, 480, 512), (12.0, -0.4, 0.3)
    cams = gut_cameras(rig, rig.names, scale, pose)
    assert cams.names == tuple(rig.names) and (cams.width, cams.height) == (round(640 * scale), round(480 * scale))
    assert all(t.dtype == torch.float32 and t.is_contiguous() for t in (cams.viewmats, cams.Ks, cams.radial))
    g = torch.Generator().manual_seed(0)
    theta = torch.rand(len(rig.names), 200, generator=g, dtype=torch.float64) * math.radians(80)
    phi = torch.rand(len(rig.names), 200, generator=g, dtype=torch.float64) * 2 * math.pi
    depth = 0.5 + 9.5 * torch.rand(len(rig.names), 200, generator=g, dtype=torch.float64)
    ray = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()], -1)
    want, world = [], []
    for c, name in enumerate(rig.names):
        cam = rig.cameras[name]
        model = cam.model if scale == 1.0 else cam.model.scaled(scale)
        T_world_camera = as_pose(pose) @ cam.T_vehicle_camera
        local = depth[c, :, None] * ray[c]
        world.append(local @ T_world_camera[:3, :3].T + T_world_camera[:3, 3])
        uv, valid = model.project(local)
        assert valid.float().mean() > 0.5
        want.append(uv)
    got = gsplat_fisheye(cams, torch.stack(world))
    assert (got - torch.stack(want)).abs().max() < 2e-3


def test_gut_cameras_refuse_a_lens_gsplat_lacks():
    rig = avm_rig(640, 480, 512)
    front = rig.cameras["front"]
    cams = {**rig.cameras, "front": RigCamera("front", RadialPolyFisheye(640, 480, [330.0, 0.0, 0.0, 0.0]),
                                               front.T_vehicle_camera)}
    with pytest.raises(ValueError, match=r"OpenCV's \(Kannala-Brandt\), the rig has RadialPolyFisheye; pass --no-gut"):
        gut_cameras(Rig(cams, rig.bev), rig.names, 1.0, (0.0, 0.0, 0.0))


def test_require_gut_names_what_is_missing(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)   # not installed
    with pytest.raises(ValueError, match=r"^gsplat is not installed \(pip install 'parksim\[cuda\]'\)$"):
        require_gut()
    old = types.ModuleType("gsplat")   # a gsplat before 1.5: rasterization without with_ut
    old.__version__ = "1.4.0"
    old.rasterization = lambda means, quats, scales, opacities, colors, viewmats, Ks, width, height: None
    monkeypatch.setitem(sys.modules, "gsplat", old)
    with pytest.raises(ValueError, match=r"^gsplat 1\.4\.0 has no 3DGUT .*; pass --no-gut$"):
        require_gut()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (benchmarks/gpu_check.sh)")
def test_gpu_suite_on_cuda_times_parksim_beside_the_cpu_path_and_3dgut(tiny_data: Path, tmp_path: Path):
    pytest.importorskip("gsplat")
    results = tmp_path / "results"
    assert main(["bench", "gpu", "--dataset", str(tiny_data), "--quick", "--quiet", "--work", str(tmp_path / "w"),
                 "--results", str(results)]) == 0
    (path,) = results.glob("gpu/*.json")
    record: Record = read_record(path)
    assert record.machine.gpu == torch.cuda.get_device_name(0)
    timed = [f for f in record.figures if f.unit == "ms"]
    assert all(math.isfinite(f.value) and f.value > 0 and f.cpu and f.reference for f in timed)
    assert sum(f.target.endswith("against the CPU path") for f in timed) == 6
    assert sum(f.target.endswith("against gsplat 3DGUT") for f in timed) == 4
    assert sum(f.target.endswith("one render_batch on CUDA") for f in timed) == 1
    agreement = [f for f in record.figures if "agreement" in f.target]
    assert len(agreement) == 4 and all(f.value >= (45.0 if f.unit == "dB" else 99.9) for f in agreement)
