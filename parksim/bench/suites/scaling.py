"""``parksim bench scaling``: forward latency of one camera as the number of Gaussians and of pixels grow,
with the fitted growth exponents (time ~ N^a, time ~ pixels^b) so a user can predict cost at their scale.

Scenes are garage-like (a dataset's surfaces densified to N Gaussians, ``parksim.bench.scenes.garage_scene``); the
exponents are fitted on process-CPU medians, over the whole sweep and over its upper half (the regime
where fixed per-call costs no longer dominate).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..common import Timing, fit_exponent, progress, pyplot, save_figure, set_threads, time_medians
from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["ScalingSuite", "ScalingOptions"]


@dataclass(frozen=True)
class ScalingOptions:
    """Options of ``parksim bench scaling``."""

    dataset: Path | None = field(default=None, metadata={
        "help": "dataset whose points and rig are used (default: synth scene1 at 320x240 under --work; "
                "synth tiny under --quick)"})
    gaussians: list[int] = field(
        default_factory=lambda: [1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000],
        metadata={"help": "scene sizes of the N sweep", "low": 1, "quick": [500, 1_000, 2_000]})
    widths: list[int] = field(default_factory=lambda: [160, 320, 640, 1280],
                              metadata={"help": "image widths of the pixel sweep", "low": 8, "quick": [40, 80, 160]})
    base_width: int = field(default=320, metadata={"help": "width during the N sweep", "low": 8, "quick": 80})
    base_gaussians: int = field(default=100_000, metadata={"help": "Gaussians during the pixel sweep", "low": 1,
                                                           "quick": 1_000})
    repeats: int = field(default=5, metadata={"help": "timed renders per point (median)", "low": 1, "quick": 1})
    warmup: int = field(default=1, metadata={"help": "untimed renders first", "low": 0})
    threads: int = field(default_factory=lambda: os.cpu_count() or 1,
                         metadata={"help": "numba/torch threads", "low": 1})


def _sweep_point(scene: Any, rig: Any, pose: Any, camera: str, scale: float, options: ScalingOptions) -> Timing:
    """Median forward time of one camera at ``scale``."""
    import torch

    from ...render import render

    def once() -> None:
        with torch.no_grad():
            render(scene, rig, pose, cameras=[camera], scale=scale)

    return time_medians([once], options.repeats, options.warmup)[0]


def _exponents(xs: list[float], timings: list[Timing]) -> dict[str, float]:
    """CPU-time growth exponent over all points and over the upper half (at least the last two)."""
    cpu = [t.cpu_ms for t in timings]
    upper = max(2, (len(xs) + 1) // 2)
    return {"all": fit_exponent(xs, cpu), "upper": fit_exponent(xs[-upper:], cpu[-upper:])}


class ScalingSuite(Suite):
    """Latency against the number of Gaussians and of pixels, with fitted growth exponents."""

    name = "scaling"
    help = "latency vs Gaussians and pixels, fitted growth exponents"
    description = ("Forward latency of one camera over N Gaussians (garage-like scenes from the dataset's points) at "
                   "--base-width, and over widths at --base-gaussians; exponents of time ~ N^a and ~ pixels^b fitted "
                   "on CPU time. Figures: the exponents (upper half of each sweep) and the largest point's latency.")
    Options = ScalingOptions

    def run(self, options: ScalingOptions, context: Context) -> Outcome:
        """Sweep N at ``base_width`` and the width at ``base_gaussians``."""
        from ...data import DatasetReader
        from ..scenes import garage_scene

        dataset = options.dataset or ensure_dataset(context, "scene1", "320x240")
        set_threads(options.threads)
        reader = DatasetReader(dataset)
        rig = reader.rig
        camera = rig.names[0]
        width = rig.cameras[camera].model.width
        pose = reader.pose(reader.frames[len(reader.frames) // 2])
        by_n: list[Timing] = []
        by_px: list[Timing] = []
        with progress(len(options.gaussians) + len(options.widths), "bench scaling", context.quiet) as bar:
            for n in options.gaussians:
                by_n.append(_sweep_point(garage_scene(dataset, n, context.seed), rig, pose, camera,
                                         options.base_width / width, options))
                bar.update(1)
            scene = garage_scene(dataset, options.base_gaussians, context.seed)
            for w in options.widths:
                by_px.append(_sweep_point(scene, rig, pose, camera, w / width, options))
                bar.update(1)
        aspect = rig.cameras[camera].model.height / width
        base_px = round(options.base_width * aspect)
        pixels = [float(w * round(w * aspect)) for w in options.widths]
        exp_n, exp_px = _exponents([float(n) for n in options.gaussians], by_n), _exponents(pixels, by_px)
        data = {"dataset": str(dataset), "camera": camera,
                "gaussians": {"x": options.gaussians, "timings": by_n, "exponent": exp_n,
                              "pixels": options.base_width * base_px},
                "pixels": {"x": pixels, "widths": options.widths, "timings": by_px, "exponent": exp_px,
                           "gaussians": options.base_gaussians}}
        top_n, top_w = options.gaussians[-1], options.widths[-1]
        figures = [
            Figure("growth exponent of CPU time in Gaussians (upper half)", exp_n["upper"], "exponent"),
            Figure("growth exponent of CPU time in pixels (upper half)", exp_px["upper"], "exponent"),
            Figure(f"1 camera forward, {top_n:,} Gaussians at {options.base_width}x{base_px}", by_n[-1].wall_ms, "ms",
                   cpu=by_n[-1].cpu_ms),
            Figure(f"1 camera forward, {options.base_gaussians:,} Gaussians at {top_w}x{round(top_w * aspect)}",
                   by_px[-1].wall_ms, "ms", cpu=by_px[-1].cpu_ms)]
        return Outcome(figures, data, lambda png: _plot(data, png))


def _plot(data: dict[str, Any], png: Path) -> None:
    """Log-log wall and CPU time against N and against pixels, exponents in the titles."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
    for ax, key, xlabel in ((axes[0], "gaussians", f"Gaussians (1 camera, {data['gaussians']['pixels']:,} px)"),
                            (axes[1], "pixels", f"pixels (1 camera, {data['pixels']['gaussians']:,} Gaussians)")):
        xs, ts, e = data[key]["x"], data[key]["timings"], data[key]["exponent"]
        ax.loglog(xs, [t.wall_ms for t in ts], "o-", label="wall")
        ax.loglog(xs, [t.cpu_ms for t in ts], "s--", label="process CPU")
        ax.set(xlabel=xlabel, ylabel="forward ms (median)",
               title=f"CPU ~ {'N' if key == 'gaussians' else 'px'}^{e['upper']:.2f} (upper half), "
                     f"^{e['all']:.2f} (all)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, png)
