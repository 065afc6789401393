"""``parksim bench compact``: scene compaction's Pareto front on a trained bundle, serving render time against test
PSNR.

For each budget (fraction of the scene kept) four compact scenes are made from one measurement
(``parksim.compact.measure_bundle``): ranked by largest blending weight and by benefit-cost (training-view summed
weight per Gaussian-pixel pair), each with and without ``--finetune`` steps (``parksim.recon.finetune``); the
control is the whole scene fine-tuned the same way (what the extra steps alone give). No visibility grid unless
``--cell-budget`` is below 1. Each is served as ``parksim serve`` does it, by ``LocalSim``: latency is a render of
every camera (no BEV, scale 1) at the dataset's test poses, all variants and the uncompacted bundle timed in turn in
one process. PSNR is ``parksim.recon.evaluate``'s on the Gaussians served at each pose (each view through the
bundle's camera response, over the camera's scene mask) on the test frames and, when ``DATA/offpath`` exists, on
every ``--offpath-stride``-th off-path frame. The goal (issue: >= 2.5x faster at <= 0.3 dB test PSNR loss) is read
on the best measured point.
"""

from __future__ import annotations

import dataclasses
import functools
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..bundles import ensure_bundle
from ..common import Timing, progress, pyplot, save_figure, time_medians
from ..record import Figure
from ..suite import Context, Outcome, Suite

if TYPE_CHECKING:
    import torch

    from ...data import DatasetReader
    from ...sim import LocalSim

__all__ = ["CompactSuite", "CompactBenchOptions", "mean_psnr", "xy_yaw", "SERIES", "LOSS_DB", "SPEEDUP"]

SERIES = (("weight", False), ("benefit-cost", False), ("benefit-cost", True), ("weight", True))
"""(ranking, fine-tuned) per budget: the old ranking, the new one, the new one fine-tuned, and the old one
fine-tuned (the control that tells the ranking's share from the fine-tuning's)."""
LOSS_DB, SPEEDUP = 0.3, 2.5
"""The goal: at least ``SPEEDUP`` times faster at no more than ``LOSS_DB`` dB test PSNR loss."""


@dataclass(frozen=True)
class CompactBenchOptions:
    """Options of ``parksim bench compact``."""

    bundle: Path | None = field(default=None, metadata={
        "help": "a trained bundle folder (default: scene1 at 320x240 trained with cpu_fast under --work, with its "
                "off-path split; --quick: the tiny garage with the tiny config)"})
    dataset: Path | None = field(default=None, metadata={"help": "the dataset --bundle was trained on"})
    finetune: int = field(default=300, metadata={"help": "fine-tuning steps", "low": 0, "quick": 2})
    budgets: list[float] = field(default_factory=lambda: [0.5, 0.35, 0.25, 0.15], metadata={
        "help": "fractions of the scene kept (fixed before any run; say so when a run's were chosen after seeing "
                "another)", "low": 0.0, "open_low": True, "high": 1.0, "quick": [0.5]})
    cell: float = field(default=4.0, metadata={"help": "visibility cell size, m", "low": 0.0, "open_low": True})
    cell_budget: float = field(default=1.0, metadata={
        "help": "below 1: every compact variant also serves per-cell visibility lists of this fraction of its kept "
                "Gaussians (parksim compact --cell-budget); 1: no visibility grid", "low": 0.0, "open_low": True,
        "high": 1.0})
    per_cell: int = field(default=8, metadata={"help": "poses measured per cell", "low": 1, "quick": 2})
    sh_tolerance: float = field(default=0.01, metadata={"help": "SH lowering tolerance", "low": 0.0})
    repeats: int = field(default=5, metadata={"help": "timed rounds (median)", "low": 1, "quick": 1})
    offpath_stride: int = field(default=6, metadata={"help": "score every n-th off-path frame", "low": 1})
    measurement: Path | None = field(default=None, metadata={
        "help": "measurement cache (torch file): read when it exists, else written after measuring"})

    def __post_init__(self) -> None:
        if (self.bundle is None) != (self.dataset is None):
            raise ValueError("--bundle and --dataset go together (the dataset the bundle was trained on)")


@dataclass
class _Variant:
    """A served bundle, what it was made with, and its scores."""

    name: str
    sim: LocalSim
    ranking: str | None = None
    budget: float = 1.0
    tuned: bool = False
    psnr: float = 0.0
    offpath_psnr: float | None = None
    make_s: float = 0.0


def xy_yaw(pose: torch.Tensor) -> list[float]:
    """A dataset pose as the planner's (x, y, yaw).

    Args:
        pose: [4, 4] ``T_world_vehicle``; the synthetic datasets' ego poses are planar.

    Returns:
        ``[x, y, yaw]`` (m, m, rad). ``ValueError`` for a pose off the ground plane.
    """
    import torch

    T = pose.double()
    if abs(float(T[2, 3])) > 1e-6 or 1.0 - float(T[2, 2]) > 1e-6:
        raise ValueError(f"test pose is not planar: {T.tolist()}")
    return [float(T[0, 3]), float(T[1, 3]), float(torch.atan2(T[1, 0], T[0, 0]))]


def mean_psnr(sim: LocalSim, reader: DatasetReader, frames: list[int]) -> float:
    """Mean PSNR (dB) of ``frames`` x every camera as served: the Gaussians ``sim`` renders at each frame's pose (its
    visibility cell's when the bundle has a grid), through the bundle's camera response.

    Args:
        sim: the served bundle.
        reader: the dataset whose images are the truth.
        frames: its frames to score (each with every camera).

    Returns:
        The mean over frames of each frame's mean view PSNR.
    """
    from ...recon.evaluate import evaluate_views
    from ...recon.response import CameraResponse

    response = CameraResponse(reader.rig, 0.0)
    response.load_dict(sim.bundle.meta.get("camera_response", {}))
    return statistics.fmean(
        evaluate_views(sim.scene_at(xy_yaw(reader.pose(f))), reader, [(f, c) for c in reader.rig.names], response,
                       slots=False).mean("psnr") or 0.0 for f in frames)   # every frame has every camera


def _serve(sim: LocalSim, poses: list[list[float]]) -> None:
    """Render every camera (no BEV) at each pose, as ``parksim serve`` answers ``GET /render``."""
    for pose in poses:
        sim.render(pose)


def _inputs(options: CompactBenchOptions, context: Context) -> tuple[Path, Path]:
    """The bundle and its dataset: the options', else the default made under ``--work`` (with the dataset's
    off-path split, ``parksim offpath``, outside ``--quick``)."""
    if options.bundle is not None and options.dataset is not None:
        return options.bundle, options.dataset
    from ...synth.offpath import OFFPATH_DIR

    bundle, dataset = ensure_bundle(context, "scene1", "320x240", "cpu_fast")
    if not context.quick and not (dataset / OFFPATH_DIR).is_dir():
        subprocess.run([sys.executable, "-m", "parksim.cli", "offpath", str(dataset), "--quiet"], check=True,
                       stdout=subprocess.DEVNULL if context.quiet else None)
    return bundle, dataset


class CompactSuite(Suite):
    """Compaction's Pareto front: serving render time against test PSNR, per budget and ranking."""

    name = "compact"
    help = "compaction's Pareto front: serving render time against test PSNR"
    description = ("Per budget: weight and benefit-cost rankings, each with and without fine-tuning, and the whole "
                   "scene fine-tuned as the control; every camera rendered by LocalSim at the test poses (all "
                   "variants timed in turn in one process), PSNR on the test (and off-path) frames. Figures: each "
                   "variant's latency and test PSNR beside the full scene's, and the best speed-up within "
                   f"{LOSS_DB} dB (goal >= {SPEEDUP}x).")
    Options = CompactBenchOptions

    def run(self, options: CompactBenchOptions, context: Context) -> Outcome:
        """Measure once, reduce per budget and series, score and time every variant."""
        import torch

        from ... import bundle as bundle_io
        from ...compact import CompactOptions, measure_bundle, reduce_bundle
        from ...data import DatasetReader
        from ...recon.finetune import bundle_config, finetune
        from ...sim import LocalSim
        from ...synth.offpath import OFFPATH_DIR

        bundle_dir, dataset = _inputs(options, context)
        full_bundle, reader = bundle_io.load(bundle_dir), DatasetReader(dataset)
        offpath = DatasetReader(dataset / OFFPATH_DIR) if (dataset / OFFPATH_DIR).is_dir() else None
        base = CompactOptions(cell=options.cell, per_cell=options.per_cell, sh_tolerance=options.sh_tolerance,
                              visibility=options.cell_budget < 1.0, cell_budget=options.cell_budget,
                              ranking="benefit-cost", seed=context.seed)
        if options.measurement is not None and options.measurement.is_file():
            measured, measure_s, measure_cpu = torch.load(options.measurement, weights_only=False)
        else:
            t0, cpu0 = time.perf_counter(), time.process_time()
            measured = measure_bundle(full_bundle, base, progress=not context.quiet, reader=reader)
            measure_s, measure_cpu = time.perf_counter() - t0, time.process_time() - cpu0
            if options.measurement is not None:
                torch.save((measured, measure_s, measure_cpu), options.measurement)

        config = bundle_config(bundle_dir, full_bundle.meta)
        full = _Variant("full scene", LocalSim(full_bundle, "full"))
        start = time.perf_counter()
        tuned_full = finetune(full_bundle, reader, options.finetune, config, progress=not context.quiet)
        control = _Variant("full scene + fine-tune (control)", LocalSim(tuned_full, "full-tuned"), tuned=True,
                           make_s=time.perf_counter() - start)
        variants = [full, control]
        with progress(len(options.budgets) * len(SERIES), "bench compact: variants", context.quiet) as bar:
            for budget in options.budgets:
                for ranking, tuned in SERIES:
                    opts = dataclasses.replace(base, budget=budget, ranking=ranking)
                    start = time.perf_counter()
                    tune = (lambda b: finetune(b, reader, options.finetune, config)) if tuned else None
                    compact = reduce_bundle(full_bundle, measured, opts, tune)
                    name = f"{ranking}{' + fine-tune' if tuned else ''}, budget {budget:g}"
                    variants.append(_Variant(name, LocalSim(compact, name), ranking, budget, tuned,
                                             make_s=time.perf_counter() - start))
                    bar.update(1)
        with progress(len(variants), "bench compact: PSNR", context.quiet) as bar:
            for v in variants:
                v.psnr = mean_psnr(v.sim, reader, reader.split["test"])
                if offpath is not None:
                    v.offpath_psnr = mean_psnr(v.sim, offpath, offpath.split["test"][::options.offpath_stride])
                bar.update(1)
        poses = [xy_yaw(reader.pose(f)) for f in reader.split["test"]]
        with progress(options.repeats + 1, "bench compact: latency", context.quiet) as bar:
            timings = time_medians([functools.partial(_serve, v.sim, poses) for v in variants], options.repeats, 1,
                                   tick=lambda: bar.update(1))
        per_render = [Timing(t.wall_ms / len(poses), t.cpu_ms / len(poses), t.repeats) for t in timings]
        rows = _rows(variants, per_render)
        s, cam = full_bundle.scene, reader.rig.cameras[reader.rig.names[0]].model
        data = {"bundle": str(bundle_dir), "dataset": str(dataset), "variants": rows,
                "scene": {"gaussians": len(s), "sh_degree": s.sh_degree, "test_frames": len(reader.split["test"]),
                          "cameras": len(reader.rig.names), "width": cam.width, "height": cam.height},
                "offpath_frames": None if offpath is None else len(offpath.split["test"][::options.offpath_stride]),
                "measurement": {"poses": len(measured.grid.poses), "cells": len(set(measured.grid.cells.tolist())),
                                "training_views": len(reader.split["train"]) * len(reader.rig.names),
                                "wall_s": measure_s, "cpu_s": measure_cpu}}
        return Outcome(_figures(rows, len(reader.rig.names)), data, lambda png: _plot(rows, png))


def _rows(variants: list[_Variant], timings: list[Timing]) -> list[dict[str, Any]]:
    """One row per variant (the full scene first, then the control): count, latency, speed-up and PSNR loss against
    the full scene, loss against the control."""
    full, control = variants[0], variants[1]
    base_ms = timings[0].wall_ms
    return [{"name": v.name, "ranking": v.ranking, "budget": v.budget, "tuned": v.tuned,
             "gaussians": len(v.sim.bundle.scene), "wall_ms": t.wall_ms, "cpu_ms": t.cpu_ms,
             "speedup": base_ms / t.wall_ms, "psnr": v.psnr, "loss_db": full.psnr - v.psnr,
             "loss_vs_control_db": control.psnr - v.psnr, "offpath_psnr": v.offpath_psnr,
             "offpath_loss_db": None if v.offpath_psnr is None or full.offpath_psnr is None
             else full.offpath_psnr - v.offpath_psnr, "make_s": v.make_s}
            for v, t in zip(variants, timings)]


def _figures(rows: list[dict[str, Any]], cameras: int) -> list[Figure]:
    """Every variant's latency and test PSNR beside the full scene's, and the best speed-up within ``LOSS_DB``."""
    full = rows[0]
    render = f"{cameras}-camera serving render"
    figures = [Figure(f"full scene: {render}", full["wall_ms"], "ms", cpu=full["cpu_ms"]),
               Figure("full scene: test PSNR", full["psnr"], "dB", better="higher")]
    for r in rows[1:]:
        figures += [Figure(f"{r['name']}: {render}", r["wall_ms"], "ms", cpu=r["cpu_ms"], reference=full["wall_ms"],
                           reference_label="full scene", reference_cpu=full["cpu_ms"]),
                    Figure(f"{r['name']}: test PSNR", r["psnr"], "dB", reference=full["psnr"],
                           reference_label="full scene", better="higher")]
    best = max(r["speedup"] for r in rows if r["loss_db"] <= LOSS_DB)   # the full scene itself qualifies
    figures.append(Figure(f"best speed-up at <= {LOSS_DB} dB test PSNR loss against the full scene", best, "x",
                          goal=f">= {SPEEDUP}x", better="higher"))
    return figures


def _plot(rows: list[dict[str, Any]], png: Path) -> None:
    """Render ms against PSNR, one line per series, the full scene as a star, the control as a cross (off-path
    dashed where measured), the goal's lines in red."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    full, control = rows[0], rows[1]
    ax.plot([control["wall_ms"]], [control["psnr"]], "kP", markersize=9, label="full scene + fine-tune (control), test")
    for (ranking, tuned), colour in zip(SERIES, ("tab:grey", "tab:blue", "tab:green", "tab:orange")):
        series = [r for r in rows[2:] if r["ranking"] == ranking and r["tuned"] == tuned]
        ms = [r["wall_ms"] for r in series]
        label = f"{ranking}{' + fine-tune' if tuned else ''}"
        ax.plot(ms, [r["psnr"] for r in series], "o-", color=colour, label=f"{label}, test")
        if full["offpath_psnr"] is not None:
            ax.plot(ms, [r["offpath_psnr"] for r in series], "s--", color=colour, alpha=0.6, label=f"{label}, off-path")
        for r in series:
            ax.annotate(f"{r['budget']:g}", (r["wall_ms"], r["psnr"]), textcoords="offset points", xytext=(4, 4),
                        fontsize=7)
    ax.plot([full["wall_ms"]], [full["psnr"]], "k*", markersize=12, label="full scene, test")
    if full["offpath_psnr"] is not None:
        ax.plot([full["wall_ms"]], [full["offpath_psnr"]], "k*", markersize=12, alpha=0.5, label="full scene, off-path")
    ax.axvline(full["wall_ms"] / SPEEDUP, color="tab:red", lw=0.8, ls=":", label=f"goal: {SPEEDUP}x faster")
    ax.axhline(full["psnr"] - LOSS_DB, color="tab:red", lw=0.8, ls="-.", label=f"goal: test PSNR loss {LOSS_DB} dB")
    ax.set_xlabel("serving render of every camera, ms (median, wall)")
    ax.set_ylabel("PSNR, dB")
    ax.set_title("parksim compact: render time against PSNR (budget fraction at each point)")
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(alpha=0.3)
    save_figure(fig, png)
