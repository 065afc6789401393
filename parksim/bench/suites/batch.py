"""``parksim bench batch``: tiny scenes trained one after the other (``parksim reconstruct`` per scene) against as Ray
tasks (``parksim batch``).

Each variant is the command line a user would run, timed from the outside: wall time, and the CPU time of every
process it started (Ray's GCS, raylet, agents and workers included), sampled from /proc until each is reaped
(``parksim.bench.procs.run_measured``). "Ray, nothing to train" is ``parksim batch`` over the bundles the Ray
variant just wrote: Ray's own start and stop, the fixed cost of a batch. Variants alternate within each repeat;
medians are reported. ``parksim batch`` starts its own local Ray instance, as a user's would, and stops it.
"""

from __future__ import annotations

import shutil
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["BatchSuite", "BatchOptions", "VARIANTS"]

_CLI = [sys.executable, "-m", "parksim.cli"]
_ONE_THREAD = {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


def _sequential(data: list[Path], out: Path, config: str) -> list[list[str]]:
    return [[*_CLI, "reconstruct", str(d), "-o", str(out / d.name), "--config", config] for d in data]


def _batch(data: list[Path], out: Path, config: str) -> list[list[str]]:
    return [[*_CLI, "batch", *map(str, data), "-o", str(out), "--config", config]]


VARIANTS: dict[str, tuple[str, Callable[[list[Path], Path, str], list[list[str]]], dict[str, str], str]] = {
    "sequential": ("sequential (`parksim reconstruct` per scene, default threads)", _sequential, {}, "seq"),
    "sequential-1-thread": ("sequential, 1 thread (`OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1`)", _sequential,
                            _ONE_THREAD, "seq1"),
    "ray": ("Ray tasks (`parksim batch`, 1 CPU each)", _batch, {}, "ray"),
    "ray-nothing": ("Ray, nothing to train (`parksim batch` over finished bundles)", _batch, {}, "ray")}
"""name -> (label, commands(datasets, output folder, config), environment, output folder key); ``ray-nothing``
shares the ``ray`` variant's output folder, so it runs after ``ray`` in a repeat and finds every bundle written."""


@dataclass(frozen=True)
class BatchOptions:
    """Options of ``parksim bench batch``."""

    repeats: int = field(default=3, metadata={"help": "repeats of every variant (median)", "low": 1, "quick": 1})
    scenes: int = field(default=2, metadata={"help": "tiny scenes to train (copies of one synth tiny dataset)",
                                             "low": 1, "quick": 1})
    config: str = field(default="tiny", metadata={"help": "training config of every scene (packaged name or YAML)"})
    variants: list[str] = field(default_factory=lambda: list(VARIANTS), metadata={
        "help": f"variants to run, of {', '.join(VARIANTS)}; the first is the reference",
        "quick": ["sequential", "ray"]})

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown or not self.variants:
            raise ValueError(f"--variants: unknown {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")
        if "ray-nothing" in self.variants and "ray" not in self.variants[:self.variants.index("ray-nothing")]:
            raise ValueError("--variants: ray-nothing needs ray before it (it reuses the bundles ray wrote)")


def _train_seconds(out: Path) -> tuple[float, float]:
    """Training wall and CPU seconds summed over the bundles in ``out`` (the trainer's own clocks: the
    ``elapsed_s`` and ``cpu_s`` of each run's last metrics record)."""
    import json

    records = [json.loads((b / "metrics.jsonl").read_text().splitlines()[-1]) for b in sorted(out.iterdir())
               if (b / "metrics.jsonl").is_file()]
    return sum(r["elapsed_s"] for r in records), sum(r["cpu_s"] for r in records)


class BatchSuite(Suite):
    """Sequential ``parksim reconstruct`` runs against one ``parksim batch`` of Ray tasks, every process counted."""

    name = "batch"
    help = "tiny scenes trained sequentially vs as Ray tasks (parksim batch), every process's CPU counted"
    description = ("Copies of one synth tiny dataset trained with --config by each variant's command line, run as "
                   "a fresh process: `parksim reconstruct` per scene (default threads, and 1 thread), `parksim batch` "
                   "(Ray tasks, 1 CPU each) and `parksim batch` over the finished bundles (Ray's fixed cost). Wall "
                   "time and the CPU time of every process a command started, sampled from /proc until reaped; median "
                   "of --repeats, variants alternating. Figures: each variant's wall seconds (cpu: process CPU "
                   "seconds) against the first variant. Data: every repeat, and the trainer's own wall / CPU seconds.")
    Options = BatchOptions

    def run(self, options: BatchOptions, context: Context) -> Outcome:
        """Make the datasets, then run every variant once per repeat, in turn."""
        from ..datasets import QUICK_SCENE, synth_dataset
        from ..procs import run_measured

        source = synth_dataset(QUICK_SCENE, context.work / "data", None)
        data = [context.work / "batch" / "data" / f"scene{i}" for i in range(options.scenes)]
        for d in data:
            if not d.is_dir():
                shutil.copytree(source, d)
        runs: dict[str, list[dict[str, float]]] = {v: [] for v in options.variants}
        for repeat in range(options.repeats):
            for name in options.variants:
                _, commands, env, key = VARIANTS[name]
                out = context.work / "batch" / "runs" / f"{key}{repeat}"
                if name != "ray-nothing":
                    shutil.rmtree(out, ignore_errors=True)
                start, cpu = time.perf_counter(), 0.0
                for command in commands(data, out, options.config):
                    cpu += run_measured(command, env)
                wall = time.perf_counter() - start
                train_wall, train_cpu = _train_seconds(out) if name != "ray-nothing" else (0.0, 0.0)
                runs[name].append({"wall_s": wall, "cpu_s": cpu, "train_wall_s": train_wall,
                                   "train_cpu_s": train_cpu})
        medians = {name: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for name, rs in runs.items()}
        first = options.variants[0]
        ref = medians[first]
        workload = f"{options.scenes} synth tiny scene{'s' * (options.scenes > 1)}, --config {options.config}"
        figures = [Figure(f"{VARIANTS[name][0]}: {workload}", m["wall_s"], "s", cpu=m["cpu_s"],
                          reference=None if name == first else ref["wall_s"],
                          reference_label=None if name == first else VARIANTS[first][0],
                          reference_cpu=None if name == first else ref["cpu_s"])
                   for name, m in medians.items()]
        data_out: dict[str, Any] = {"scenes": options.scenes, "config": options.config,
                                    "variants": {name: {"label": VARIANTS[name][0], "runs": runs[name],
                                                        "median": medians[name]} for name in runs}}
        return Outcome(figures, data_out)
