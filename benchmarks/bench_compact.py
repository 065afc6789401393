"""Scene compaction on a trained bundle: Gaussian count, four-camera serving latency and test PSNR per budget.

One measurement (``parksim.compact.measure_bundle``) serves every budget. Each variant is served as
``parksim serve`` does it, by ``LocalSim`` (with the cell's subset when the variant has a visibility grid):
latency is a four-camera render (no BEV, scale 1) at the dataset's test poses, timed alternately with the
uncompacted bundle in the same process (median over repeats after a warm-up); PSNR is ``recon.evaluate``'s
(each test view through the bundle's camera response, over the camera's scene mask) against ground truth.

    .venv/bin/python benchmarks/bench_compact.py --bundle scenes/scene1_320 --dataset data/scene1_320 \
        --out benchmarks/RESULTS_compact.md

A variant is ``BUDGET[:CELL_BUDGET][@SH_TOLERANCE]``: the ``--budget`` kept in the scene, with a visibility
grid serving ``--cell-budget`` per cell when given (none otherwise), SH tolerance ``--sh-tolerance`` unless given.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import statistics
import time
from pathlib import Path

import numba
import torch

from parksim import bundle as bundle_io
from parksim.client import LocalSim
from parksim.compact import CompactOptions, measure_bundle, reduce_bundle
from parksim.data import DatasetReader
from recon.evaluate import evaluate_views
from recon.response import CameraResponse


@dataclasses.dataclass
class Variant:
    """A served bundle and what it was made with."""

    name: str
    sim: LocalSim
    options: CompactOptions | None
    psnr: float = 0.0
    latency_ms: list[float] = dataclasses.field(default_factory=list)


def served_psnr(sim: LocalSim, reader: DatasetReader) -> float:
    """Mean test-view PSNR with the subset ``sim`` serves at each test pose."""
    response = CameraResponse(reader.rig, 0.0)
    response.load_dict(sim.bundle.meta.get("camera_response", {}))
    rows = []
    for frame in reader.split["test"]:
        pose = reader.pose(frame)
        scene = sim.scene_at(_xy_yaw(pose))
        views = [(frame, c) for c in reader.rig.names]
        rows += evaluate_views(scene, reader, views, response, slots=False).views
    return statistics.fmean(r["psnr"] for r in rows)


def _xy_yaw(pose: torch.Tensor) -> list[float]:
    """A dataset pose as the planner's (x, y, yaw); the synthetic datasets' ego poses are planar."""
    T = pose.double()
    if abs(float(T[2, 3])) > 1e-6 or 1.0 - float(T[2, 2]) > 1e-6:
        raise ValueError(f"test pose is not planar: {T.tolist()}")
    return [float(T[0, 3]), float(T[1, 3]), float(torch.atan2(T[1, 0], T[0, 0]))]


def time_alternating(variants: list[Variant], poses: list[list[float]], repeats: int) -> None:
    """Per repeat, each variant renders every pose (four cameras); stores ms per render. One warm-up pass."""
    for r in range(repeats + 1):
        for v in variants:
            start = time.perf_counter()
            for pose in poses:
                v.sim.render(pose)
            if r:
                v.latency_ms.append(1000 * (time.perf_counter() - start) / len(poses))


def table(variants: list[Variant], full: Variant) -> list[str]:
    """Markdown rows: count, mean cell subset, SH degree, latency, speed-up and PSNR loss vs the full bundle."""
    base_ms, lines = statistics.median(full.latency_ms), [
        "| variant | Gaussians | served per cell (mean) | SH degree (Gaussians per degree) | four-camera render ms "
        "(median) | speed-up | test PSNR dB | PSNR loss dB |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for v in variants:
        b, ms = v.sim.bundle, statistics.median(v.latency_ms)
        report = b.meta.get("compaction", {})
        cell = f"{report['cell_gaussians_mean']:.0f}" if b.visibility is not None else "all"
        degrees = "/".join(map(str, report.get("sh_degree_counts", [])))
        lines.append(f"| {v.name} | {len(b.scene)} | {cell} | {b.scene.sh_degree} ({degrees or 'as trained'}) | "
                     f"{ms:.1f} | {base_ms / ms:.2f}x | "
                     f"{v.psnr:.2f} | {full.psnr - v.psnr:.2f} |")
    return lines


def parse_variant(spec: str, base: CompactOptions) -> tuple[str, CompactOptions]:
    """``BUDGET[:CELL_BUDGET][@SH_TOLERANCE]`` -> (row name, options)."""
    head, _, sh = spec.partition("@")
    budget, _, cell = head.partition(":")
    opts = dataclasses.replace(base, budget=float(budget), cell_budget=float(cell or 1.0), visibility=bool(cell),
                               sh_tolerance=float(sh) if sh else base.sh_tolerance)
    name = f"budget {opts.budget:g}" + (f", cell budget {opts.cell_budget:g}" if cell else ", no visibility")
    return name + (f", SH tolerance {opts.sh_tolerance:g}" if sh else ""), opts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bundle", type=Path, required=True)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--variants", default="1@0,1,0.5,0.35,0.25,1:1,1:0.5,1:0.35,1:0.25,0.5:0.35",
                        help="comma-separated BUDGET[:CELL_BUDGET][@SH_TOLERANCE]")
    parser.add_argument("--cell", type=float, default=4.0)
    parser.add_argument("--per-cell", type=int, default=16)
    parser.add_argument("--sh-tolerance", type=float, default=0.01)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/RESULTS_compact.md"))
    parser.add_argument("--weights", type=Path,
                        help="measurement cache (torch file): read when it exists, else written after measuring")
    args = parser.parse_args()

    started = datetime.datetime.now(datetime.timezone.utc)
    load_start = os.getloadavg()
    full_bundle, reader = bundle_io.load(args.bundle), DatasetReader(args.dataset)
    base = CompactOptions(cell=args.cell, per_cell=args.per_cell, sh_tolerance=args.sh_tolerance)
    if args.weights is not None and args.weights.is_file():
        grid, weights, measure_s, measure_cpu = torch.load(args.weights, weights_only=False)
    else:
        t0, cpu0 = time.perf_counter(), time.process_time()
        grid, weights = measure_bundle(full_bundle, base, progress=True)
        measure_s, measure_cpu = time.perf_counter() - t0, time.process_time() - cpu0
        if args.weights is not None:
            torch.save((grid, weights, measure_s, measure_cpu), args.weights)

    variants = [Variant("full (reference)", LocalSim(full_bundle, "full"), None)]
    for spec in args.variants.split(","):
        name, opts = parse_variant(spec, base)
        variants.append(Variant(name, LocalSim(reduce_bundle(full_bundle, grid, weights, opts), name), opts))
    for v in variants:
        v.psnr = served_psnr(v.sim, reader)
        print(f"{v.name}: {len(v.sim.bundle.scene)} Gaussians, test PSNR {v.psnr:.2f} dB", flush=True)
    poses = [_xy_yaw(reader.pose(f)) for f in reader.split["test"]]
    time_alternating(variants, poses, args.repeats)
    rows = table(variants, variants[0])
    print("\n".join(rows))

    load_end = os.getloadavg()
    s = full_bundle.scene
    text = [
        "# Scene compaction (`parksim compact`)", "",
        f"Command: `.venv/bin/python benchmarks/bench_compact.py --bundle {args.bundle} --dataset {args.dataset} "
        f"--variants {args.variants} --cell {args.cell:g} --per-cell {args.per_cell} "
        f"--sh-tolerance {args.sh_tolerance:g} --repeats {args.repeats}"
        + (f" --weights {args.weights}" if args.weights else "") + "`", "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, numba threads "
        f"{numba.get_num_threads()}, torch {torch.__version__}; started {started:%Y-%m-%dT%H:%M}Z; load average "
        f"{load_start[0]:.1f} at the start, {load_end[0]:.1f} at the end "
        "(shared machine: other jobs were running).", "",
        f"Scene: {len(s)} Gaussians, SH degree {s.sh_degree}; {len(reader.split['test'])} test frames x "
        f"{len(reader.rig.names)} cameras at {reader.rig.cameras[reader.rig.names[0]].model.width}x"
        f"{reader.rig.cameras[reader.rig.names[0]].model.height}. Measurement: {len(grid.poses)} drivable poses in "
        f"{len(set(grid.cells.tolist()))} cells of {args.cell:g} m ({args.per_cell} per cell, 1 m margin), "
        f"{measure_s:.0f} s wall / {measure_cpu:.0f} s CPU, once for all budgets.", "",
        "Latency: `LocalSim.render(pose)` (what `parksim serve` runs), four cameras, no BEV, at the test poses, "
        f"median of {args.repeats} repeats after a warm-up, every variant timed alternately in one process. "
        "\"served per cell\" is the mean size of a visibility cell's subset (what a render at a pose in that cell "
        "projects and rasterizes).", "", *rows, ""]
    args.out.write_text("\n".join(text) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
