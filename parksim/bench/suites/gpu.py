"""``parksim bench gpu``: ``render()`` on a CUDA GPU (the device projection kernels + gsplat's rasterizer) beside the
CPU path (numba) and beside gsplat's 3DGUT, all in one process and run: the GPU issue's cases, ``render_batch`` at
the env target's size, and how far the GPU images are from the CPU ones.

Scenes are garage-like (``parksim.bench.cases``, as ``parksim bench render``) and, with ``--bundle``, a trained
bundle. Per case the closures are called alternately (``time_medians``): the CPU path, ParkSim on CUDA and, for case
(b)'s sizes, 3DGUT on the same four cameras without a BEV (``parksim.bench.gut``); a GPU closure ends with
``torch.cuda.synchronize()``, so its wall time is the whole call as a user sees it. Goals are the issue's: case (b)
forward <= 3 ms and forward + backward <= 8 ms at 2e5 Gaussians, <= 8 and <= 20 ms at 1e6, and >= 500 env steps/s
from one ``render_batch`` of 64 poses x 4 x 320x240 + BEV. Agreement, per view of the forward BEV cases: max and
mean |GPU - CPU|, the share of pixels within 1/255 and the PSNR of the GPU image against the CPU one; the tolerance
was set before any GPU run: PSNR >= 45 dB and 99.9 % of pixels within 1/255 in every view. Without a CUDA device, or
without the CUDA extra, the suite refuses at once (``ValueError``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..cases import CAMERA, Case, CaseSizes, bev_rig, case, load_pose, render_case
from ..common import Timing, progress, time_medians
from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["GPUSuite", "GPUOptions", "agreement", "TOLERANCE_PSNR_DB", "TOLERANCE_SHARE", "GOALS_MS",
           "BATCH_GOAL_STEPS_S"]

TOLERANCE_PSNR_DB = 45.0
"""Every view's PSNR of the GPU image against the CPU one must reach this."""
TOLERANCE_SHARE = 0.999
"""... and this share of its pixels must be within 1/255 (every channel)."""
GOALS_MS = {(200_000, False): 3.0, (200_000, True): 8.0, (1_000_000, False): 8.0, (1_000_000, True): 20.0}
"""The issue's targets for case (b) (4 x 640x480 + 512 BEV) on one GPU, ms, by (Gaussians, backward)."""
BATCH_GOAL_STEPS_S = 500.0
"""The env target: env steps/s of 64 envs (4 x 320x240 + BEV each) on one GPU."""


@dataclass(frozen=True)
class GPUOptions(CaseSizes):
    """Options of ``parksim bench gpu``."""

    gaussians_large: int = field(default=1_000_000, metadata={
        "help": "Gaussians of the large scene (case (b)'s views and BEV)", "low": 1, "quick": 8_000})
    batch_poses: int = field(default=64, metadata={
        "help": "poses of the render_batch case (the env target's 64 envs), from consecutive frames", "low": 1,
        "quick": 4})
    width_batch: int = field(default=320, metadata={
        "help": "camera width of the render_batch case (every camera + BEV, case (b)'s Gaussians)", "low": 8,
        "quick": 80})
    gut: bool = field(default=True, metadata={
        "help": "also time gsplat's 3DGUT on case (b)'s cameras as the reference (gsplat >= 1.5, OpenCV fisheyes)"})
    dataset: Path | None = field(default=None, metadata={
        "help": "synth dataset whose points, rig and trajectory are used (rig.json, poses.json, points3d.ply; "
                "default: synth scene1 at 320x240 under --work; synth tiny under --quick)"})
    bundle: Path | None = field(default=None, metadata={"help": "also check agreement on this trained bundle"})
    repeats: int = field(default=11, metadata={"help": "timed rounds per case (median)", "low": 1, "quick": 1})
    frame: int = field(default=50, metadata={"help": "frame of the trajectory giving the pose (modulo its length)",
                                             "low": 0})


def _closure(scene: Any, rig: Any, pose: Any, c: Case, backend: str) -> Callable[[], None]:
    """Render the case once on the scene's device (and back-propagate a fixed weighted sum when asked)."""
    import torch

    from ...gaussians import GaussianScene
    from ...render.api import render

    cuda = scene.means.device.type == "cuda"
    if c.backward:
        means, quats, log_scales, opacity_logits, sh = (
            t.detach().clone().requires_grad_(True)
            for t in (scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh))
        scene = GaussianScene(means, quats, log_scales, opacity_logits, sh, sh_degree=scene.sh_degree)
    weights: dict[str, Any] = {}

    def once() -> None:
        render_case(render, scene, rig, pose, c, weights, backend=backend)
        if cuda:
            torch.cuda.synchronize()

    return once


def _batch_closure(scene: Any, rig: Any, poses: Sequence[Any], scale: float, batched: bool) -> Callable[[], None]:
    """Every camera + BEV at ``poses`` on the GPU: one ``render_batch``, or one ``render`` per pose."""
    import torch

    from ...render.api import render, render_batch

    def once() -> None:
        with torch.no_grad():
            if batched:
                render_batch(scene, rig, poses, bev=True, scale=scale, backend="gsplat")
            else:
                for pose in poses:
                    render(scene, rig, pose, bev=True, scale=scale, backend="gsplat")
        torch.cuda.synchronize()

    return once


def _views(scene: Any, rig: Any, pose: Any, scale: float, backend: str) -> dict[str, Any]:
    """Every camera's image and the BEV, rendered without gradients."""
    import torch

    from ...render.api import render

    with torch.no_grad():
        out = render(scene, rig, pose, bev=True, scale=scale, backend=backend)
    return {**out.images, "BEV": out.bev}


def agreement(cpu: dict[str, Any], gpu: dict[str, Any]) -> list[dict[str, Any]]:
    """Per view: max and mean |GPU - CPU|, share of pixels within 1/255, PSNR of GPU against CPU (images in [0, 1])
    and whether the view is within the stated tolerance.

    Args:
        cpu: view name -> ``(H, W, 3)`` image of the CPU path.
        gpu: the same views from the GPU path.

    Returns:
        One dict per view.
    """
    rows = []
    for name, want in cpu.items():
        diff = (gpu[name].detach().cpu().double() - want.detach().cpu().double()).abs()
        mse = float((diff ** 2).mean())
        within = float((diff.amax(-1) <= 1.0 / 255.0).double().mean())
        psnr = math.inf if mse == 0 else -10.0 * math.log10(mse)
        rows.append({"view": name, "max_abs": float(diff.max()), "mean_abs": float(diff.mean()), "within": within,
                     "psnr_db": psnr, "ok": psnr >= TOLERANCE_PSNR_DB and within >= TOLERANCE_SHARE})
    return rows


def _agreement_figures(what: str, rows: list[dict[str, Any]]) -> list[Figure]:
    """The worst view's PSNR and share within 1/255, against the tolerance."""
    return [Figure(f"GPU vs CPU image agreement, {what}: worst view's PSNR", min(r["psnr_db"] for r in rows), "dB",
                   goal=f">= {TOLERANCE_PSNR_DB:g} dB", better="higher"),
            Figure(f"GPU vs CPU image agreement, {what}: worst view's pixels within 1/255",
                   100 * min(r["within"] for r in rows), "%", goal=f">= {100 * TOLERANCE_SHARE:g} %", better="higher")]


def _issue_size(c: Case, rig: Any, width: int, height: int) -> bool:
    """Whether ``c`` renders at a size the issue states goals for: every camera at ``width x height`` + a 512 px BEV."""
    model = rig.cameras[CAMERA].model
    size = (round(model.width * c.scale), round(model.height * c.scale))
    return size == (width, height) and c.cameras is None and c.bev and rig.bev.width == 512


def _case_figures(c: Case, t_cpu: Timing, t_gpu: Timing, t_gut: Timing | None, goals: bool) -> list[Figure]:
    """ParkSim on CUDA against the CPU path, and against 3DGUT when it was timed (with the issue's goal when
    ``goals``: the case is at the issue's size)."""
    from ..gut import LABEL

    figures = [Figure(f"{c.target}: ParkSim on CUDA, against the CPU path", t_gpu.wall_ms, "ms", cpu=t_gpu.cpu_ms,
                      reference=t_cpu.wall_ms, reference_cpu=t_cpu.cpu_ms,
                      reference_label="numba CPU path, same machine, same run")]
    if t_gut is not None:
        goal = GOALS_MS.get((c.n, c.backward)) if goals else None
        figures.append(Figure(f"{c.target}: ParkSim on CUDA, against gsplat 3DGUT", t_gpu.wall_ms, "ms",
                              cpu=t_gpu.cpu_ms, reference=t_gut.wall_ms, reference_cpu=t_gut.cpu_ms,
                              reference_label=LABEL, goal=None if goal is None else f"<= {goal:g} ms"))
    return figures


def _batch_figures(target: str, poses: int, t_batch: Timing, t_single: Timing, goal: bool) -> list[Figure]:
    """One render_batch against as many render() calls, and the env steps/s it gives (against the env target when
    ``goal``: the batch is at its size)."""
    return [Figure(f"{target}: one render_batch on CUDA", t_batch.wall_ms, "ms", cpu=t_batch.cpu_ms,
                   reference=t_single.wall_ms, reference_cpu=t_single.cpu_ms,
                   reference_label=f"the same poses as {poses} render() calls, same run"),
            Figure(f"{target}: env steps/s from render_batch on CUDA", 1000.0 * poses / t_batch.wall_ms, "steps/s",
                   goal=f">= {BATCH_GOAL_STEPS_S:g} steps/s" if goal else None, better="higher")]


def _refuse_without_cuda(gut: bool) -> None:
    """Refuse at once, before any work, a machine where the GPU path (or the 3DGUT reference) cannot run.

    Raises:
        ValueError: one line: no CUDA device, the CUDA extra missing, or gsplat without 3DGUT.
    """
    import torch

    from ...device import cuda_extra_missing

    if not torch.cuda.is_available():
        raise ValueError("no CUDA device: bench gpu times ParkSim on CUDA beside the CPU path and gsplat's 3DGUT, "
                         "and torch.cuda.is_available() is False here")
    missing = cuda_extra_missing()
    if missing:
        raise ValueError(f"the CUDA extra is not installed (missing {', '.join(missing)}): pip install "
                         "'parksim[cuda]'")
    if gut:
        from ..gut import require_gut

        require_gut()


class GPUSuite(Suite):
    """render() on CUDA beside the numba CPU path and gsplat's 3DGUT: timings, render_batch and image agreement."""

    name = "gpu"
    help = "render() on CUDA beside the CPU path and gsplat 3DGUT: cases (a), (b), 1e6, render_batch; agreement"
    description = ("The GPU issue's cases on a CUDA GPU (device projection kernels + gsplat rasterizer), called "
                   "alternately with the numba CPU path of the same machine and, for case (b)'s sizes, gsplat's "
                   "3DGUT (rasterization(camera_model='fisheye', with_ut=True, with_eval3d=True)) on the same four "
                   "cameras without BEV: (a) one camera at 320 px, 1e5 Gaussians, fwd and fwd+bwd; (b) every camera "
                   "at 640 px + a 512 px BEV, 2e5 and 1e6 Gaussians, fwd and fwd+bwd (goals 3 / 8 ms at 2e5, "
                   "8 / 20 ms at 1e6); one render_batch of 64 poses x every camera at 320 px + BEV against 64 "
                   "render() calls (goal >= 500 env steps/s). Agreement of the "
                   "GPU images with the CPU ones (tolerance set before any run: PSNR >= 45 dB, 99.9 % of pixels "
                   "within 1/255) on the forward scenes and --bundle. Refuses without a CUDA device or the CUDA extra.")
    Options = GPUOptions

    def run(self, options: GPUOptions, context: Context) -> Outcome:
        """Time the cases on CPU, GPU and 3DGUT, then render_batch, then check agreement."""
        _refuse_without_cuda(options.gut)
        import torch

        from ...rig import Rig
        from ..gut import gut_cameras, gut_closure, gut_images
        from ..scenes import garage_scene

        dataset = options.dataset or ensure_dataset(context, "scene1", "320x240")
        rig, pose = bev_rig(Rig.load(dataset / "rig.json"), options.bev_px), load_pose(dataset, options.frame)
        o = options
        cases = [case("a", "case (a)", o.gaussians_a, o.width_a, rig, (CAMERA,), False, backward=b)
                 for b in (False, True)]
        cases += [case("b", label, n, o.width_b, rig, None, True, backward=b)
                  for label, n in (("case (b)", o.gaussians_b), ("large scene", o.gaussians_large))
                  for b in (False, True)]
        batch = case("batch", "render_batch", o.gaussians_b, o.width_batch, rig, None, True)
        b_scale = next(c.scale for c in cases if c.group == "b")
        gut = gut_cameras(rig, rig.names, b_scale, pose, "cuda") if o.gut else None   # refused here, before timing
        scenes: dict[int, Any] = {}

        def scene_of(n: int) -> Any:
            """The CPU garage scene of ``n`` Gaussians, made once."""
            if n not in scenes:
                scenes[n] = garage_scene(dataset, n, context.seed, sh_degree=3)
            return scenes[n]

        figures: list[Figure] = []
        data: dict[str, Any] = {"dataset": str(dataset), "frame": o.frame, "gpu": torch.cuda.get_device_name(),
                                "cases": {}, "agreement": {}, "parksim_vs_3dgut": {}}
        with progress(len(cases) + 1 + (o.bundle is not None), "bench gpu", context.quiet) as bar:
            for c in cases:
                cpu_scene = scene_of(c.n)
                gpu_scene = cpu_scene.to(device="cuda")
                closures = [_closure(cpu_scene, rig, pose, c, "numba"), _closure(gpu_scene, rig, pose, c, "gsplat")]
                if gut is not None and c.group == "b":
                    closures.append(gut_closure(gpu_scene, gut, c.backward))
                t_cpu, t_gpu, *t_gut = time_medians(closures, o.repeats)
                figures += _case_figures(c, t_cpu, t_gpu, t_gut[0] if t_gut else None,
                                         _issue_size(c, rig, 640, 480))
                data["cases"][c.target] = {"cpu": t_cpu, "gpu": t_gpu, "3dgut": t_gut[0] if t_gut else None}
                if c.bev and not c.backward:
                    what = f"garage scene, {c.target.split(', ', 1)[1]}"
                    gpu_views = _views(gpu_scene, rig, pose, c.scale, "gsplat")
                    rows = agreement(_views(cpu_scene, rig, pose, c.scale, "numba"), gpu_views)
                    figures += _agreement_figures(what, rows)
                    data["agreement"][what] = rows
                    if gut is not None and c.group == "b":   # a wrong camera mapping would show here
                        data["parksim_vs_3dgut"][what] = [
                            {"view": r["view"], "psnr_db": r["psnr_db"], "within": r["within"]}
                            for r in agreement(gut_images(gpu_scene, gut), gpu_views)]
                bar.update(1)
            gpu_scene = scene_of(batch.n).to(device="cuda")
            poses = [load_pose(dataset, o.frame + i) for i in range(o.batch_poses)]
            t_batch, t_single = time_medians([_batch_closure(gpu_scene, rig, poses, batch.scale, True),
                                              _batch_closure(gpu_scene, rig, poses, batch.scale, False)], o.repeats)
            target = f"{o.batch_poses} poses x {batch.target.removeprefix('render_batch fwd, ')}"
            figures += _batch_figures(target, o.batch_poses, t_batch, t_single,
                                      _issue_size(batch, rig, 320, 240) and o.batch_poses == 64)
            data["batch"] = {"target": target, "batch": t_batch, "single": t_single}
            bar.update(1)
            if o.bundle is not None:
                from ...bundle import load

                bundle = load(o.bundle)
                scene = bundle.scene.to(torch.float32)
                what = f"trained bundle {o.bundle.name} ({len(scene.means):,} Gaussians), its native size"
                rows = agreement(_views(scene, bundle.rig, pose, 1.0, "numba"),
                                 _views(scene.to(device="cuda"), bundle.rig, pose, 1.0, "gsplat"))
                figures += _agreement_figures(what, rows)
                data["agreement"][what] = rows
                bar.update(1)
        return Outcome(figures, data)
