"""Scene compaction's Pareto front on a trained bundle: four-camera serving render time against test PSNR.

For each budget of ``BUDGETS`` (fixed before any run; ``--budgets`` for others) four compact scenes are made
from one measurement (``parksim.compact.measure_bundle``): ranked by largest blending weight and by benefit-cost
(training-view summed weight per Gaussian-pixel pair), each with and without ``--finetune`` steps
(``parksim.recon.finetune``); the control is the whole scene fine-tuned the same way. No visibility grid unless
``--cell-budget`` is below 1, SH tolerance ``--sh-tolerance``.
Each is served as ``parksim serve`` does it, by ``LocalSim``: latency is a four-camera render (no BEV, scale 1)
at the dataset's test poses, all variants and the uncompacted bundle timed alternately in one process
(median over repeats after a warm-up; wall and process CPU). PSNR is ``parksim.recon.evaluate``'s on the Gaussians
served at each pose (each view through the bundle's camera response, over the camera's scene mask) on the test
frames and, when ``DATA/offpath`` exists (``parksim offpath DATA``), on every ``--offpath-stride``-th off-path
frame.

    .venv/bin/python benchmarks/bench_compact.py --bundle scenes/s1_320 --dataset data/scene1_320 \
        --out benchmarks/RESULTS_compact.md --figure benchmarks/figures/compact_pareto.png
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import statistics
import time
from pathlib import Path

import numba
import torch

from parksim import bundle as bundle_io
from parksim.bench.common import cpu_model
from parksim.compact import CompactOptions, Measurement, measure_bundle, reduce_bundle
from parksim.data import DatasetReader
from parksim.recon.evaluate import evaluate_views
from parksim.recon.finetune import FINETUNE_ITERATIONS, bundle_config, finetune
from parksim.recon.response import CameraResponse
from parksim.sim import LocalSim

BUDGETS = (0.5, 0.35, 0.25, 0.15)
"""Fractions of the scene kept, decided before the first run."""
SERIES = (("weight", False), ("benefit-cost", False), ("benefit-cost", True), ("weight", True))
"""(ranking, fine-tuned) per budget: the old ranking, the new one, the new one fine-tuned, and the old one
fine-tuned (the control that tells the ranking's share from the fine-tuning's)."""


@dataclasses.dataclass
class Variant:
    """A served bundle, what it was made with, its scores and timings."""

    name: str
    sim: LocalSim
    ranking: str | None = None
    budget: float = 1.0
    tuned: bool = False
    psnr: float = 0.0
    offpath_psnr: float | None = None
    make_s: float = 0.0
    wall_ms: list[float] = dataclasses.field(default_factory=list)
    cpu_ms: list[float] = dataclasses.field(default_factory=list)


def mean_psnr(sim: LocalSim, reader: DatasetReader, frames: list[int]) -> float:
    """Mean PSNR of ``frames`` x every camera as served: the Gaussians ``sim`` renders at each frame's pose (its
    visibility cell's when the bundle has a grid), through the bundle's camera response."""
    response = CameraResponse(reader.rig, 0.0)
    response.load_dict(sim.bundle.meta.get("camera_response", {}))
    return statistics.fmean(
        evaluate_views(sim.scene_at(xy_yaw(reader.pose(f))), reader, [(f, c) for c in reader.rig.names], response,
                       slots=False).mean("psnr") or 0.0 for f in frames)   # every frame has every camera


def xy_yaw(pose: torch.Tensor) -> list[float]:
    """A dataset pose as the planner's (x, y, yaw); the synthetic datasets' ego poses are planar."""
    T = pose.double()
    if abs(float(T[2, 3])) > 1e-6 or 1.0 - float(T[2, 2]) > 1e-6:
        raise ValueError(f"test pose is not planar: {T.tolist()}")
    return [float(T[0, 3]), float(T[1, 3]), float(torch.atan2(T[1, 0], T[0, 0]))]


def time_alternating(variants: list[Variant], poses: list[list[float]], repeats: int) -> None:
    """Per repeat, each variant renders every pose (four cameras); stores wall and CPU ms per render. One warm-up."""
    for r in range(repeats + 1):
        for v in variants:
            start, cpu = time.perf_counter(), time.process_time()
            for pose in poses:
                v.sim.render(pose)
            if r:
                v.wall_ms.append(1000 * (time.perf_counter() - start) / len(poses))
                v.cpu_ms.append(1000 * (time.process_time() - cpu) / len(poses))


def make_variants(full: bundle_io.Bundle, measured: Measurement, base: CompactOptions, reader: DatasetReader,
                  bundle_dir: Path, steps: int, budgets: tuple[float, ...]) -> list[Variant]:
    """One compact scene per budget and series, fine-tuning where the series says so (timed)."""
    config, out = bundle_config(bundle_dir, full.meta), []
    for budget in budgets:
        for ranking, tuned in SERIES:
            opts = dataclasses.replace(base, budget=budget, ranking=ranking)
            start = time.perf_counter()
            tune = (lambda b: finetune(b, reader, steps, config, progress=True)) if tuned else None
            compact = reduce_bundle(full, measured, opts, tune)
            name = f"{ranking}{' + fine-tune' if tuned else ''}, budget {budget:g}"
            out.append(Variant(name, LocalSim(compact, name), ranking, budget, tuned,
                               make_s=time.perf_counter() - start))
            print(f"{name}: {len(compact.scene)} Gaussians in {out[-1].make_s:.0f} s", flush=True)
    return out


def table(variants: list[Variant], full: Variant, control: Variant, offpath: bool) -> list[str]:
    """Markdown rows: count, latency (wall, CPU), speed-up and PSNR (loss) against the full bundle, and the test
    loss against the control (the full bundle fine-tuned as the compact ones are)."""
    base_ms = statistics.median(full.wall_ms)
    head = ("| variant | Gaussians | render ms wall (median) | render ms CPU (median) | speed-up | test PSNR dB | "
            "loss dB | loss vs control dB |" + (" off-path PSNR dB | off-path loss dB |" if offpath else ""))
    lines = [head, "|" + " --- |" * head.count(" |")]
    for v in variants:
        ms = statistics.median(v.wall_ms)
        row = (f"| {v.name} | {len(v.sim.bundle.scene)} | {ms:.1f} | {statistics.median(v.cpu_ms):.1f} | "
               f"{base_ms / ms:.2f}x | {v.psnr:.2f} | {full.psnr - v.psnr:.2f} | {control.psnr - v.psnr:.2f} |")
        if offpath:
            assert v.offpath_psnr is not None and full.offpath_psnr is not None
            row += f" {v.offpath_psnr:.2f} | {full.offpath_psnr - v.offpath_psnr:.2f} |"
        lines.append(row)
    return lines


def plot(variants: list[Variant], full: Variant, path: Path) -> None:
    """Render ms against test PSNR, one line per series, the full scene as a star (off-path dashed when measured)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    base = statistics.median(full.wall_ms)
    controls = [v for v in variants if v.ranking is None]
    ax.plot([statistics.median(v.wall_ms) for v in controls], [v.psnr for v in controls], "kP", markersize=9,
            label="full scene + fine-tune (control), test")
    for (ranking, tuned), colour in zip(SERIES, ("tab:grey", "tab:blue", "tab:green", "tab:orange")):
        rows = [v for v in variants if v.ranking == ranking and v.tuned == tuned]
        ms = [statistics.median(v.wall_ms) for v in rows]
        label = f"{ranking}{' + fine-tune' if tuned else ''}"
        ax.plot(ms, [v.psnr for v in rows], "o-", color=colour, label=f"{label}, test")
        if full.offpath_psnr is not None:
            ax.plot(ms, [v.offpath_psnr or 0.0 for v in rows], "s--", color=colour, alpha=0.6,
                    label=f"{label}, off-path")
        for v, x in zip(rows, ms):
            ax.annotate(f"{v.budget:g}", (x, v.psnr), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.plot([base], [full.psnr], "k*", markersize=12, label="full scene, test")
    if full.offpath_psnr is not None:
        ax.plot([base], [full.offpath_psnr], "k*", markersize=12, alpha=0.5, label="full scene, off-path")
    ax.axvline(base / 2.5, color="tab:red", lw=0.8, ls=":", label="target: 2.5x faster")
    ax.axhline(full.psnr - 0.3, color="tab:red", lw=0.8, ls="-.", label="target: test PSNR loss 0.3 dB")
    ax.set_xlabel("four-camera serving render, ms (median, wall)")
    ax.set_ylabel("PSNR, dB")
    ax.set_title("parksim compact: render time against PSNR (budget fraction at each point)")
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bundle", type=Path, required=True)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--finetune", type=int, default=FINETUNE_ITERATIONS, help="fine-tuning steps")
    parser.add_argument("--budgets", type=lambda t: tuple(float(x) for x in t.split(",")), default=BUDGETS,
                        help="comma-separated fractions of the scene (default: the fixed BUDGETS); say in the "
                             "results when a run's budgets were chosen after seeing another run")
    parser.add_argument("--cell", type=float, default=4.0)
    parser.add_argument("--cell-budget", type=float, default=1.0,
                        help="below 1: every compact variant also serves per-cell visibility lists of this fraction "
                             "of its kept Gaussians (parksim compact --cell-budget); 1: no visibility grid")
    parser.add_argument("--per-cell", type=int, default=8)
    parser.add_argument("--sh-tolerance", type=float, default=0.01)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--offpath-stride", type=int, default=6, help="score every n-th off-path frame")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/RESULTS_compact.md"))
    parser.add_argument("--figure", type=Path, default=Path("benchmarks/figures/compact_pareto.png"))
    parser.add_argument("--measurement", type=Path,
                        help="measurement cache (torch file): read when it exists, else written after measuring")
    args = parser.parse_args()

    started = datetime.datetime.now(datetime.timezone.utc)
    load_start = os.getloadavg()
    full_bundle, reader = bundle_io.load(args.bundle), DatasetReader(args.dataset)
    offpath = DatasetReader(args.dataset / "offpath") if (args.dataset / "offpath").is_dir() else None
    base = CompactOptions(cell=args.cell, per_cell=args.per_cell, sh_tolerance=args.sh_tolerance,
                          visibility=args.cell_budget < 1.0, cell_budget=args.cell_budget,
                          ranking="benefit-cost")
    if args.measurement is not None and args.measurement.is_file():
        measured, measure_s, measure_cpu = torch.load(args.measurement, weights_only=False)
    else:
        t0, cpu0 = time.perf_counter(), time.process_time()
        measured = measure_bundle(full_bundle, base, progress=True, reader=reader)
        measure_s, measure_cpu = time.perf_counter() - t0, time.process_time() - cpu0
        if args.measurement is not None:
            torch.save((measured, measure_s, measure_cpu), args.measurement)

    full = Variant("full (reference)", LocalSim(full_bundle, "full"))
    start = time.perf_counter()
    tuned_full = finetune(full_bundle, reader, args.finetune, bundle_config(args.bundle, full_bundle.meta),
                          progress=True)
    control = Variant("full + fine-tune (control)", LocalSim(tuned_full, "full-tuned"), tuned=True,
                      make_s=time.perf_counter() - start)
    variants = [control, *make_variants(full_bundle, measured, base, reader, args.bundle, args.finetune,
                                        args.budgets)]
    for v in [full, *variants]:
        v.psnr = mean_psnr(v.sim, reader, reader.split["test"])
        if offpath is not None:
            v.offpath_psnr = mean_psnr(v.sim, offpath, offpath.split["test"][::args.offpath_stride])
        print(f"{v.name}: {len(v.sim.bundle.scene)} Gaussians, test PSNR {v.psnr:.2f} dB"
              + (f", off-path {v.offpath_psnr:.2f} dB" if v.offpath_psnr is not None else ""), flush=True)
    poses = [xy_yaw(reader.pose(f)) for f in reader.split["test"]]
    time_alternating([full, *variants], poses, args.repeats)
    rows = table([full, *variants], full, control, offpath is not None)
    print("\n".join(rows))
    plot(variants, full, args.figure)

    load_end = os.getloadavg()
    s, cam = full_bundle.scene, reader.rig.cameras[reader.rig.names[0]].model
    tuned = [v.make_s for v in variants if v.tuned]
    text = [
        "## Pareto front: old ranking, benefit-cost ranking, each with and without fine-tuning", "",
        f"Command: `.venv/bin/python benchmarks/bench_compact.py --bundle {args.bundle} --dataset {args.dataset} "
        f"--finetune {args.finetune} --budgets {','.join(f'{b:g}' for b in args.budgets)} "
        f"--cell {args.cell:g} --cell-budget {args.cell_budget:g} --per-cell {args.per_cell} "
        f"--sh-tolerance {args.sh_tolerance:g} --repeats {args.repeats} --offpath-stride {args.offpath_stride}"
        + (f" --measurement {args.measurement}" if args.measurement else "") + "`", "",
        f"Machine: {cpu_model()}, {os.cpu_count()} cores, numba threads {numba.get_num_threads()}, torch "
        f"{torch.__version__}; started {started:%Y-%m-%d %H:%M} UTC; load average {load_start[0]:.1f} at the start, "
        f"{load_end[0]:.1f} at the end (shared machine: other jobs were running).", "",
        f"Scene: {len(s)} Gaussians, SH degree {s.sh_degree}; {len(reader.split['test'])} test frames x "
        f"{len(reader.rig.names)} cameras at {cam.width}x{cam.height}"
        + (f"; off-path: every {args.offpath_stride}th of {len(offpath.split['test'])} frames "
           f"({len(offpath.split['test'][::args.offpath_stride])}) x {len(offpath.rig.names)} cameras "
           f"({args.dataset / 'offpath'})" if offpath is not None else
           "; no off-path split (DATA/offpath missing): off-path PSNR not measured") + ". "
        f"Measurement: {len(measured.grid.poses)} drivable poses in {len(set(measured.grid.cells.tolist()))} cells "
        f"of {args.cell:g} m ({args.per_cell} per cell), plus the benefit over "
        f"{len(reader.split['train']) * len(reader.rig.names)} training views: {measure_s:.0f} s wall / "
        f"{measure_cpu:.0f} s CPU, once for all budgets. Fine-tuning: {args.finetune} steps per budget "
        f"(median {statistics.median(tuned):.0f} s wall). The control row is the uncompacted scene fine-tuned the "
        "same way: what the extra steps alone give.", "",
        f"Budgets: {', '.join(f'{b:g}' for b in args.budgets)} of the scene"
        f"{' (fixed in the script before the first run)' if args.budgets == BUDGETS else ''}; "
        + (f"per-cell visibility lists of {args.cell_budget:g} of the kept Gaussians (full scene and control: "
           "none); " if args.cell_budget < 1.0 else "no visibility grid; ") +
        "latency is `LocalSim.render(pose)` (what `parksim serve` runs), four cameras, no BEV, at the test poses, "
        f"median of {args.repeats} repeats after a warm-up, every variant timed alternately in one process; "
        "wall and process-CPU ms per render.", "", *rows, "",
        f"![Pareto front]({os.path.relpath(args.figure, args.out.parent)})", ""]
    args.out.write_text("\n".join(text) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
