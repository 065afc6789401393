"""``parksim bench gpu``: ``render()`` on a CUDA GPU (torch UT projection + gsplat rasterizer) beside the CPU path
(numba) on the same machine: the speed issue's cases (a) and (b) and a 1e6-Gaussian scene, and how far the GPU
images are from the CPU ones.

Scenes are garage-like (``parksim.bench.cases``, as ``parksim bench render``) and, with ``--bundle``, a trained
bundle. The CPU and GPU closures are called alternately (``time_medians``); a GPU closure ends with
``torch.cuda.synchronize()``, so its wall time is the whole call as a user sees it. Agreement, per view of the
forward BEV cases: max and mean |GPU - CPU|, the share of pixels within 1/255 and the PSNR of the GPU image against
the CPU one. The tolerance was set before any GPU run: PSNR >= 45 dB and 99.9 % of pixels within 1/255 in every
view. Without a CUDA device the suite refuses at once (``ValueError``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..cases import CAMERA, Case, CaseSizes, bev_rig, case, load_pose, render_case
from ..common import progress, time_medians
from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["GPUSuite", "GPUOptions", "agreement", "TOLERANCE_PSNR_DB", "TOLERANCE_SHARE"]

TOLERANCE_PSNR_DB = 45.0
"""Every view's PSNR of the GPU image against the CPU one must reach this."""
TOLERANCE_SHARE = 0.999
"""... and this share of its pixels must be within 1/255 (every channel)."""


@dataclass(frozen=True)
class GPUOptions(CaseSizes):
    """Options of ``parksim bench gpu``."""

    gaussians_large: int = field(default=1_000_000, metadata={
        "help": "Gaussians of the large scene (case (b)'s views and BEV)", "low": 1, "quick": 8_000})
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
        diff = (gpu[name].detach().cpu().double() - want.detach().double()).abs()
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


class GPUSuite(Suite):
    """render() with gsplat on CUDA beside the numba CPU path: timings and image agreement."""

    name = "gpu"
    help = "render() on CUDA (gsplat) beside the CPU path: cases (a), (b), 1e6 Gaussians; image agreement"
    description = ("The speed issue's cases on a CUDA GPU (torch UT projection + gsplat rasterizer) against the "
                   "numba CPU path of the same machine, called alternately: (a) one camera at 320 px, 1e5 Gaussians, "
                   "fwd and fwd+bwd; (b) every camera at 640 px + a 512 px BEV, 2e5 Gaussians, fwd and fwd+bwd; the "
                   "same views of 1e6 Gaussians. Agreement of the GPU images with the CPU ones (tolerance set before "
                   "any run: PSNR >= 45 dB, 99.9 % of pixels within 1/255) on the forward scenes and --bundle. "
                   "Refuses without a CUDA device.")
    Options = GPUOptions

    def run(self, options: GPUOptions, context: Context) -> Outcome:
        """Time the cases on CPU and GPU, then check agreement."""
        import torch

        if not torch.cuda.is_available():
            raise ValueError("no CUDA device: bench gpu times gsplat on CUDA beside the CPU path, and "
                             "torch.cuda.is_available() is False here")
        from ...rig import Rig
        from ..scenes import garage_scene

        dataset = options.dataset or ensure_dataset(context, "scene1", "320x240")
        rig, pose = bev_rig(Rig.load(dataset / "rig.json"), options.bev_px), load_pose(dataset, options.frame)
        o = options
        cases = [case("a", "case (a)", o.gaussians_a, o.width_a, rig, (CAMERA,), False, backward=b)
                 for b in (False, True)]
        cases += [case("b", label, n, o.width_b, rig, None, True, backward=b)
                  for label, n in (("case (b)", o.gaussians_b), ("large scene", o.gaussians_large))
                  for b in (False, True)]
        scenes: dict[int, Any] = {}
        figures: list[Figure] = []
        data: dict[str, Any] = {"dataset": str(dataset), "frame": o.frame, "gpu": torch.cuda.get_device_name(),
                                "cases": {}, "agreement": {}}
        with progress(len(cases) + (o.bundle is not None), "bench gpu", context.quiet) as bar:
            for c in cases:
                cpu_scene = scenes.setdefault(c.n, garage_scene(dataset, c.n, context.seed, sh_degree=3))
                gpu_scene = cpu_scene.to(device="cuda")
                t_cpu, t_gpu = time_medians([_closure(cpu_scene, rig, pose, c, "numba"),
                                             _closure(gpu_scene, rig, pose, c, "gsplat")], o.repeats)
                figures.append(Figure(f"{c.target}: gsplat on CUDA", t_gpu.wall_ms, "ms", cpu=t_gpu.cpu_ms,
                                      reference=t_cpu.wall_ms, reference_cpu=t_cpu.cpu_ms,
                                      reference_label="numba CPU path, same machine, same run"))
                data["cases"][c.target] = {"cpu": t_cpu, "gpu": t_gpu}
                if c.bev and not c.backward:
                    what = f"garage scene, {c.target.split(', ', 1)[1]}"
                    rows = agreement(_views(cpu_scene, rig, pose, c.scale, "numba"),
                                     _views(gpu_scene, rig, pose, c.scale, "gsplat"))
                    figures += _agreement_figures(what, rows)
                    data["agreement"][what] = rows
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
