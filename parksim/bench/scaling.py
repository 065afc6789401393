"""``parksim bench scaling``: forward latency of one camera as the number of Gaussians and of pixels grow,
with the fitted growth exponents (time ~ N^a, time ~ pixels^b) so a user can predict cost at their scale.

Scenes are garage-like (a dataset's surfaces densified to N Gaussians, ``scenes.garage_scene``); the
exponents are fitted on process-CPU medians, over the whole sweep and over its upper half (the regime
where fixed per-call costs no longer dominate).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import torch

from ..data import DatasetReader
from ..render import render
from ..rig import Rig
from .common import (
    Timing,
    fit_exponent,
    md_table,
    metadata,
    progress,
    pyplot,
    save_figure,
    set_threads,
    time_medians,
    write_result,
)
from .scenes import garage_scene

__all__ = ["run"]


def _sweep_point(scene: Any, rig: Rig, pose: torch.Tensor, camera: str, scale: float, args: argparse.Namespace
                 ) -> Timing:
    """Median forward time of one camera at ``scale``."""
    def once() -> None:
        with torch.no_grad():
            render(scene, rig, pose, cameras=[camera], scale=scale)

    return time_medians([once], args.repeats, args.warmup)[0]


def _exponents(xs: list[float], timings: list[Timing]) -> dict[str, float]:
    """CPU-time growth exponent over all points and over the upper half (at least the last two)."""
    cpu = [t.cpu_ms for t in timings]
    upper = max(2, (len(xs) + 1) // 2)
    return {"all": fit_exponent(xs, cpu), "upper": fit_exponent(xs[-upper:], cpu[-upper:])}


def run(args: argparse.Namespace) -> Any:
    """Sweep N at ``--base-width`` and the width at ``--base-gaussians``; write ``scaling.json/md/png``."""
    set_threads(args.threads)
    reader = DatasetReader(args.dataset)
    rig = reader.rig
    camera = rig.names[0]
    width = rig.cameras[camera].model.width
    pose = reader.pose(reader.frames[len(reader.frames) // 2])
    meta = {**metadata(args.command_line), "dataset": str(args.dataset), "camera": camera}
    by_n: list[Timing] = []
    by_px: list[Timing] = []
    with progress(len(args.gaussians) + len(args.widths), "bench scaling", args.quiet) as bar:
        for n in args.gaussians:
            by_n.append(_sweep_point(garage_scene(args.dataset, n, args.seed), rig, pose, camera,
                                     args.base_width / width, args))
            bar.update(1)
        scene = garage_scene(args.dataset, args.base_gaussians, args.seed)
        for w in args.widths:
            by_px.append(_sweep_point(scene, rig, pose, camera, w / width, args))
            bar.update(1)
    aspect = rig.cameras[camera].model.height / width
    base_px = round(args.base_width * aspect)
    pixels = [float(w * round(w * aspect)) for w in args.widths]
    exp_n, exp_px = _exponents([float(n) for n in args.gaussians], by_n), _exponents(pixels, by_px)
    data = {"gaussians": {"x": args.gaussians, "timings": by_n, "exponent": exp_n, "pixels": args.base_width * base_px},
            "pixels": {"x": pixels, "widths": args.widths, "timings": by_px, "exponent": exp_px,
                       "gaussians": args.base_gaussians}}
    body = [f"One camera (`{camera}`) of `{args.dataset}`'s rig, forward only, garage-like scenes; medians of "
            f"{args.repeats} after {args.warmup} warm-up; exponents fitted on process-CPU time.", "",
            f"**time ~ N^{exp_n['upper']:.2f}** over the upper half of N (N^{exp_n['all']:.2f} over all), "
            f"**time ~ pixels^{exp_px['upper']:.2f}** over the upper half of the resolutions "
            f"(pixels^{exp_px['all']:.2f} over all).", "",
            *md_table([f"Gaussians ({args.base_width}x{base_px})", "wall ms", "CPU ms"],
                      [(f"{n:,}", f"{t.wall_ms:.1f}", f"{t.cpu_ms:.1f}") for n, t in zip(args.gaussians, by_n)]), "",
            *md_table([f"resolution ({args.base_gaussians:,} Gaussians)", "wall ms", "CPU ms"],
                      [(f"{w}x{round(w * aspect)}", f"{t.wall_ms:.1f}", f"{t.cpu_ms:.1f}")
                       for w, t in zip(args.widths, by_px)])]
    return write_result(args.out, "scaling", meta, data, body,
                        lambda png: _plot(data, meta, png))


def _plot(data: dict[str, Any], meta: dict[str, Any], png: Path) -> None:
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
    save_figure(fig, meta, png)
