"""render() on a CUDA GPU (torch UT projection + gsplat rasterizer) beside the CPU path on the same machine:
the speed issue's cases (a) and (b) and a 1e6-Gaussian scene, and how far the GPU images are from the CPU ones.

Scenes are ``parksim.bench.scenes.garage_scene`` (as ``bench_render.py``) and, with ``--bundle``, a trained
bundle. Timings are medians of ``--repeats`` after a warm-up, the CPU and GPU closures called alternately; a
GPU closure ends with ``torch.cuda.synchronize()``, so its wall time is the whole call as a user sees it.
Agreement, per view: max and mean |GPU - CPU| over the pixels, and PSNR of the GPU image against the CPU one.
The tolerance was set before any GPU run: PSNR >= 45 dB and 99.9 % of pixels within 1/255 in every view.

    python benchmarks/bench_gpu.py --dataset data/scene1_320 --bundle scenes/s1_320 --out benchmarks/RESULTS_gpu.md
"""

from __future__ import annotations

import argparse
import datetime
import math
import platform
import sys
from collections.abc import Callable
from pathlib import Path

import numba
import torch
from bench_render import CAMERA, Case, Stack, load_pose, render_case

from parksim.bench.common import cpu_model, time_medians
from parksim.bench.scenes import garage_scene
from parksim.gaussians import GaussianScene
from parksim.render.api import render
from parksim.rig import Rig

TOLERANCE_PSNR_DB = 45.0
TOLERANCE_SHARE = 0.999


def closure(scene: GaussianScene, rig: Rig, pose: torch.Tensor, case: Case, backend: str) -> Callable[[], None]:
    """Render the case once on the scene's device (and back-propagate a fixed weighted sum when asked)."""
    cuda = scene.means.device.type == "cuda"
    if case.backward:
        scene = GaussianScene(*(t.detach().clone().requires_grad_(True) for t in
                                (scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh)),
                              sh_degree=scene.sh_degree)
    weights: dict[str, torch.Tensor] = {}

    def once() -> None:
        render_case(render, scene, rig, pose, case, weights, backend=backend)
        if cuda:
            torch.cuda.synchronize()

    return once


def views(scene: GaussianScene, rig: Rig, pose: torch.Tensor, scale: float, backend: str) -> dict[str, torch.Tensor]:
    """Four camera images and the BEV, rendered without gradients."""
    with torch.no_grad():
        out = render(scene, rig, pose, bev=True, scale=scale, backend=backend)
    assert out.bev is not None
    return {**out.images, "BEV": out.bev}


def main() -> None:
    """Time the cases on CPU and GPU, check agreement, write markdown."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", type=Path, default=Path("data/scene1_320"),
                    help="a parksim synth dataset (rig.json, poses.json, points3d.ply are read)")
    ap.add_argument("--bundle", type=Path, default=None, help="also check agreement on this trained bundle")
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--frame", type=int, default=50)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if not torch.cuda.is_available():
        sys.exit("bench_gpu: no CUDA device")
    rig, pose = Stack("parksim").rig(args.dataset), load_pose(args.dataset, args.frame)
    base_w = rig.cameras[CAMERA].model.width
    s320, s640 = 320 / base_w, 640 / base_w
    cases = [Case("(a) 1 cam 320x240, 1e5, fwd", 100_000, s320, (CAMERA,), False),
             Case("(a) 1 cam 320x240, 1e5, fwd+bwd", 100_000, s320, (CAMERA,), False, backward=True),
             Case("(b) 4 cams 640x480 + BEV 512, 2e5, fwd", 200_000, s640, None, True),
             Case("(b') 4 cams 640x480 + BEV 512, 2e5, fwd+bwd", 200_000, s640, None, True, backward=True),
             Case("1e6: 4 cams 640x480 + BEV 512, fwd", 1_000_000, s640, None, True),
             Case("1e6: 4 cams 640x480 + BEV 512, fwd+bwd", 1_000_000, s640, None, True, backward=True)]
    scenes: dict[int, GaussianScene] = {}
    table = ["| case | CPU numba wall / CPU ms | GPU gsplat wall / CPU ms | GPU speed-up (wall) |",
             "| --- | ---: | ---: | ---: |"]
    checks: list[str] = []
    for case in cases:
        if case.n not in scenes:
            scenes[case.n] = garage_scene(args.dataset, case.n, sh_degree=3)
        cpu_scene = scenes[case.n]
        gpu_scene = cpu_scene.to(device="cuda")
        t_cpu, t_gpu = time_medians([closure(cpu_scene, rig, pose, case, "numba"),
                                     closure(gpu_scene, rig, pose, case, "gsplat")], args.repeats)
        row = (f"| {case.label} | {t_cpu.wall_ms:.1f} / {t_cpu.cpu_ms:.0f} | {t_gpu.wall_ms:.1f} / {t_gpu.cpu_ms:.0f} "
               f"| {t_cpu.wall_ms / t_gpu.wall_ms:.1f}x |")
        table.append(row)
        print(row, flush=True)
        if case.bev and not case.backward:
            checks.append(f"garage scene {case.n:.0e} Gaussians, 640x480")
            checks += agreement_rows(views(cpu_scene, rig, pose, case.scale, "numba"),
                                     views(gpu_scene, rig, pose, case.scale, "gsplat"))
    if args.bundle is not None:
        from parksim.bundle import load

        bundle = load(args.bundle)
        scene = bundle.scene.to(torch.float32)
        checks.append(f"trained bundle `{args.bundle}` ({len(scene.means)} Gaussians), its native size")
        checks += agreement_rows(views(scene, bundle.rig, pose, 1.0, "numba"),
                                 views(scene.to(device="cuda"), bundle.rig, pose, 1.0, "gsplat"))
    report(args, table, checks)


def agreement_rows(cpu: dict[str, torch.Tensor], gpu: dict[str, torch.Tensor]) -> list[str]:
    """Markdown rows per view: max and mean |GPU - CPU|, share of pixels within 1/255, PSNR of GPU against CPU
    (images in [0, 1]), and whether the view is within the stated tolerance."""
    rows = []
    for name, want in cpu.items():
        diff = (gpu[name].detach().cpu().double() - want.detach().double()).abs()
        mse = float((diff ** 2).mean())
        within = float((diff.amax(-1) <= 1.0 / 255.0).double().mean())
        psnr = math.inf if mse == 0 else -10.0 * math.log10(mse)
        ok = psnr >= TOLERANCE_PSNR_DB and within >= TOLERANCE_SHARE
        rows.append(f"| {name} | {float(diff.max()):.4f} | {float(diff.mean()):.2e} | {100 * within:.3f} % | "
                    f"{psnr:.1f} | {'yes' if ok else 'NO'} |")
        print(rows[-1], flush=True)
    return rows


def report(args: argparse.Namespace, table: list[str], checks: list[str]) -> None:
    """Print and write (``--out``) the timing and agreement tables."""
    lines, header = [], ("| view | max abs diff | mean abs diff | pixels within 1/255 | PSNR GPU vs CPU (dB) "
                         "| within tolerance |\n| --- | ---: | ---: | ---: | ---: | --- |")
    for c in checks:
        lines += ([f"\n{c}:\n", header] if not c.startswith("|") else [c])
    text = "\n".join([
        "# render() on a GPU: gsplat backend beside the CPU path", "",
        f"- command: `python {' '.join(['benchmarks/bench_gpu.py', *sys.argv[1:]])}`",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- GPU: {torch.cuda.get_device_name()}; CPU: {cpu_model()}, {platform.machine()}, "
        f"numba threads {numba.get_num_threads()}, torch threads {torch.get_num_threads()}",
        f"- python {platform.python_version()}, torch {torch.__version__}, numba {numba.__version__}, "
        f"gsplat {__import__('gsplat').__version__}",
        f"- scene: `{args.dataset}/points3d.ply` densified (bench_render.py); pose frame {args.frame}; medians of "
        f"{args.repeats} repeats after a warm-up, CPU and GPU alternately",
        "", *table, "",
        f"Agreement (tolerance set before the run: PSNR >= {TOLERANCE_PSNR_DB:g} dB and "
        f"{100 * TOLERANCE_SHARE:g} % of pixels within 1/255):", *lines, ""])
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
