"""What serving a scene with its trained projection costs: ``LocalSim.render`` (what ``parksim serve`` runs, four
cameras, no BEV) of one bundle through each projection, at the dataset's test poses.

Both variants serve the same Gaussians; only ``bundle.json``'s ``projection`` differs. They are timed alternately
in one process (``time_medians``: per round, every test pose once; median over rounds after a warm-up round,
divided by the poses: ms per render, wall and process CPU). Quality of
each projection on the same bundle is ``parksim eval SCENE DATA [--projection ut]``.

    .venv/bin/python benchmarks/bench_serve_projection.py --bundle out/bench/scene1_cpu_30min_ewa --dataset data/scene1
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
from collections.abc import Callable
from pathlib import Path

import numba
import torch
from bench_compact import xy_yaw

from parksim import bundle as bundle_io
from parksim.bench.common import cpu_model, time_medians
from parksim.data import DatasetReader
from parksim.sim import LocalSim


def main() -> None:
    """Time the bundle served through UT and through EWA; print a markdown table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", type=Path, required=True, help="a scene bundle folder")
    ap.add_argument("--dataset", type=Path, required=True, help="its dataset (the test poses are rendered)")
    ap.add_argument("--repeats", type=int, default=5, help="timed rounds over every test pose")
    args = ap.parse_args()
    bundle, reader = bundle_io.load(args.bundle), DatasetReader(args.dataset)
    poses = [xy_yaw(reader.pose(f)) for f in reader.split["test"]]
    sims = {m: LocalSim(dataclasses.replace(bundle, meta={**bundle.meta, "projection": m}), m) for m in ("ut", "ewa")}

    def closure(sim: LocalSim) -> Callable[[], None]:
        def run() -> None:
            for pose in poses:
                sim.render(pose)
        return run

    with torch.no_grad():
        timings = time_medians([closure(s) for s in sims.values()], args.repeats)
    n = len(poses)
    print(f"- command: `.venv/bin/python benchmarks/bench_serve_projection.py --bundle {args.bundle} "
          f"--dataset {args.dataset} --repeats {args.repeats}`")
    print(f"- {datetime.datetime.now():%Y-%m-%d %H:%M}, {cpu_model()}, {os.cpu_count()} cores, numba threads "
          f"{numba.get_num_threads()}, load average {os.getloadavg()[0]:.1f} at the end; {len(bundle.scene)} Gaussians "
          f"trained with {bundle.projection}; {n} test poses x 4 cameras\n")
    print("| served through | ms per render, wall | ms per render, CPU |\n| --- | ---: | ---: |")
    for method, t in zip(sims, timings):
        print(f"| {method} | {t.wall_ms / n:.0f} | {t.cpu_ms / n:.0f} |")


if __name__ == "__main__":
    main()
