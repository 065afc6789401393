"""Training-step speed: median wall and process-CPU time of one ``Trainer.iteration()`` at a finished run's state.

The run's last checkpoint (e.g. ``cpu_30min`` on scene1: 200k Gaussians, SH degree 3, 640x480) is loaded
with the photometric phase extended, so every timed step is a photometric step at the run's final size
and no densification. ``--reference DIR`` times a copy of the packages (``parksim`` and ``recon`` under
DIR, e.g. ``git archive OLD parksim recon | tar -x -C DIR``) in alternating rounds, each in its own
process (two ``recon`` packages cannot share one):

    .venv/bin/python benchmarks/bench_train_step.py --run out/bench/scene1_cpu_30min --dataset data/scene1 \\
        --reference /tmp/old --rounds 2 --iterations 25

``--profile N`` instead runs N steps of this tree under the torch profiler and prints where their CPU goes
(numba kernels appear under their autograd Function's name).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def resumed_trainer(run: Path, dataset: Path, scratch: Path) -> Any:
    """A ``Trainer`` at the run's last checkpoint with its photometric phase extended (every step photometric)."""
    from parksim.data import DatasetReader
    from parksim.recon.checkpoint import checkpoint_path, load_checkpoint
    from parksim.recon.config import load_config
    from parksim.recon.trainer import Trainer

    config = load_config(run / "config.yaml")
    config = config.model_copy(update={"photometric": config.photometric.model_copy(update={"iterations": 10**9})})
    state = load_checkpoint(checkpoint_path(run))
    state["config"] = config.model_dump(mode="json")   # the same run, with its photometric phase extended
    trainer = Trainer(DatasetReader(dataset), config, scratch, lambda _: None)
    trainer.decode_inputs()
    trainer.resume(state)
    return trainer


def measure(run: Path, dataset: Path, iterations: int, warmup: int) -> dict[str, float | int | str]:
    """Time ``iterations`` steps after ``warmup`` untimed ones (kernel compilation, allocator warm-up); also
    count the minor page faults per step (fresh pages the allocator maps)."""
    import parksim

    with tempfile.TemporaryDirectory() as scratch:
        trainer = resumed_trainer(run, dataset, Path(scratch))
        walls, cpus, faults = [], [], []
        for i in range(warmup + iterations):
            wall, cpu = time.perf_counter(), time.process_time()
            minflt = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            trainer.iteration()
            if i >= warmup:
                walls.append(time.perf_counter() - wall)
                cpus.append(time.process_time() - cpu)
                faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - minflt)
    gaussians = len(trainer.params) if trainer.params is not None else 0
    return {"package": str(Path(parksim.__file__).parent.parent), "gaussians": gaussians,
            "wall_ms": 1000 * statistics.median(walls), "cpu_ms": 1000 * statistics.median(cpus),
            "faults": statistics.median(faults)}


def profile(run: Path, dataset: Path, steps: int, warmup: int) -> str:
    """The torch profiler's table (self CPU per op, top 20) over ``steps`` steps after ``warmup``."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    with tempfile.TemporaryDirectory() as scratch:
        trainer = resumed_trainer(run, dataset, Path(scratch))
        for _ in range(warmup):
            trainer.iteration()
        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(steps):
                trainer.iteration()
    return str(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20, max_name_column_width=40))


def _child(path: Path, args: argparse.Namespace) -> dict[str, float | int | str]:
    """``measure`` in a fresh process with ``path`` first on the import path."""
    cmd = [sys.executable, __file__, "--run", str(args.run), "--dataset", str(args.dataset), "--iterations",
           str(args.iterations), "--warmup", str(args.warmup), "--child"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(path), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(cmd, env=env, cwd=tempfile.gettempdir(), check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    """Parse arguments; time this tree (and the reference) in alternating rounds; print a markdown table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a finished `parksim reconstruct` output folder")
    ap.add_argument("--dataset", type=Path, required=True, help="the dataset it was trained on")
    ap.add_argument("--iterations", type=int, default=25, help="timed iterations per round")
    ap.add_argument("--warmup", type=int, default=5, help="untimed iterations first")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--reference", type=Path, default=None, help="folder holding older parksim/ and recon/")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="profile N steps of this tree instead of timing (torch profiler, self CPU per op)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.run, args.dataset = args.run.resolve(), args.dataset.resolve()
    if args.child:
        print(json.dumps(measure(args.run, args.dataset, args.iterations, args.warmup)))
        return
    if args.profile:
        print(f"- command: `.venv/bin/python benchmarks/bench_train_step.py {' '.join(sys.argv[1:])}`\n")
        print(profile(args.run, args.dataset, args.profile, args.warmup))
        return
    trees = [ROOT] + ([args.reference.resolve()] if args.reference else [])
    rows = [(round_, _child(tree, args)) for round_ in range(args.rounds) for tree in trees]
    print(f"- command: `.venv/bin/python benchmarks/bench_train_step.py {' '.join(sys.argv[1:])}`")
    print(f"- {time.strftime('%Y-%m-%dT%H:%M:%S')}, {os.cpu_count()} cores, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} at the end\n")
    print("| round | package | Gaussians | median wall ms | median CPU ms | minor page faults per step |\n"
          "| ---: | --- | ---: | ---: | ---: | ---: |")
    for round_, r in rows:
        print(f"| {round_ + 1} | `{r['package']}` | {r['gaussians']} | {r['wall_ms']:.0f} | {r['cpu_ms']:.0f} | "
              f"{r['faults']:.0f} |")


if __name__ == "__main__":
    main()
