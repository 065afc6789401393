"""``parksim bench train-step``: median wall and process-CPU time of one ``Trainer.iteration()`` at a finished run's
state, against a reference copy of the package timed in alternating rounds.

The run's last checkpoint (by default ``cpu_30min`` on scene1: 200k Gaussians, SH degree 3, 640x480, made under
``--work`` on first use) is loaded with the photometric phase extended, so every timed step is a photometric step
at the run's final size and no densification. Each package is timed in its own process (two packages named
``parksim`` cannot share one), with the folder holding it first on ``PYTHONPATH``; ``--reference DIR`` is such a
folder, e.g. ``git archive OLD parksim | tar -x -C DIR`` (a copy from before ``recon`` moved under ``parksim`` holds
``recon/`` beside it: ``git archive OLD parksim recon``). Rounds alternate the order of the two, since the
machine's speed drifts within minutes. ``--profile N`` adds where N steps of this package spend their CPU (torch
profiler, self CPU per op, after this package's last timed round in the same process; numba kernels appear under
their autograd Function's name).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..bundles import ensure_bundle
from ..common import progress
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["TrainStepSuite", "TrainStepOptions"]

_PROBE = """
import json, resource, statistics, sys, tempfile, time
from pathlib import Path

import parksim

try:   # the layout since recon moved under parksim
    from parksim.data import DatasetReader
    from parksim.recon.checkpoint import checkpoint_path, load_checkpoint
    from parksim.recon.config import load_config
    from parksim.recon.trainer import Trainer
except ModuleNotFoundError:   # a reference copy from before: recon/ beside parksim/
    from parksim.data import DatasetReader
    from recon.checkpoint import checkpoint_path, load_checkpoint
    from recon.config import load_config
    from recon.trainer import Trainer

args = json.loads(sys.argv[1])
run = Path(args["run"])
config = load_config(run / "config.yaml")
config = config.model_copy(update={"photometric": config.photometric.model_copy(update={"iterations": 10**9})})
state = load_checkpoint(checkpoint_path(run))
state["config"] = config.model_dump(mode="json")   # the same run, with its photometric phase extended
result = {"package": str(Path(parksim.__file__).parent.parent)}
with tempfile.TemporaryDirectory() as scratch:
    trainer = Trainer(DatasetReader(Path(args["dataset"])), config, Path(scratch), lambda _: None)
    trainer.decode_inputs()
    trainer.resume(state)
    for _ in range(args["warmup"]):
        trainer.iteration()
    walls, cpus, faults = [], [], []
    for _ in range(args["iterations"]):
        wall, cpu = time.perf_counter(), time.process_time()
        minflt = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        trainer.iteration()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - minflt)
    result.update(wall_ms=1000 * statistics.median(walls), cpu_ms=1000 * statistics.median(cpus),
                  faults=statistics.median(faults))
    if args["profile"]:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(args["profile"]):
                trainer.iteration()
        ops = sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)[:20]
        result["ops"] = [{"op": e.key, "self_cpu_ms": e.self_cpu_time_total / 1e3 / args["profile"],
                          "calls": e.count / args["profile"]} for e in ops]
    result["gaussians"] = len(trainer.params) if trainer.params is not None else 0
print(json.dumps(result))
"""
"""The program each timed process runs: written against the trainer API that both package layouts share, it
imports whichever ``parksim`` comes first on ``PYTHONPATH``, times ``iterations`` steps after ``warmup``, then
profiles ``profile`` more; it prints one JSON line."""


@dataclass(frozen=True)
class TrainStepOptions:
    """Options of ``parksim bench train-step``."""

    run: Path | None = field(default=None, metadata={
        "help": "a finished `parksim reconstruct` output folder (default: scene1 trained with cpu_30min under "
                "--work; --quick: the tiny garage with the tiny config)"})
    dataset: Path | None = field(default=None, metadata={"help": "the dataset --run was trained on"})
    iterations: int = field(default=25, metadata={"help": "timed iterations per round", "low": 1, "quick": 3})
    warmup: int = field(default=5, metadata={"help": "untimed iterations first (kernel compilation, allocator)",
                                             "low": 0, "quick": 1})
    rounds: int = field(default=2, metadata={"help": "rounds; each times this package and the reference", "low": 1,
                                             "quick": 1})
    reference: Path | None = field(default=None, metadata={
        "help": "folder holding a reference copy of the package (parksim/, and recon/ for copies from before "
                "recon moved under parksim), timed in the same rounds"})
    reference_label: str | None = field(default=None, metadata={
        "help": "what the reference is, for the record (e.g. 'commit 5ebf0ca'; default: its folder)"})
    profile: int = field(default=0, metadata={
        "help": "also profile N steps of this package after its last round (torch profiler, top 20 ops by self "
                "CPU)", "low": 0, "metavar": "N"})

    def __post_init__(self) -> None:
        if (self.run is None) != (self.dataset is None):
            raise ValueError("--run and --dataset go together (the dataset the run was trained on)")
        if self.reference is not None and not (self.reference / "parksim" / "__init__.py").is_file():
            raise ValueError(f"--reference {self.reference}: no parksim package in it (expected "
                             f"{self.reference / 'parksim' / '__init__.py'})")


def _probe(tree: Path, run: Path, dataset: Path, options: TrainStepOptions, profile: int = 0) -> dict[str, Any]:
    """``_PROBE`` in a fresh process with ``tree`` first on the import path; checks it imported ``tree``'s package.

    Args:
        tree: the folder holding the ``parksim`` package to time.
        run: the finished run whose last checkpoint the trainer resumes.
        dataset: the dataset it was trained on.
        options: iterations and warm-up.
        profile: profile this many steps after the timed ones.

    Returns:
        ``folder`` (``tree``), ``gaussians``, ``wall_ms``, ``cpu_ms``, ``faults`` (medians per step), and ``ops``
        (the top 20 ops by self CPU per step) when profiling.
    """
    args = {"run": str(run), "dataset": str(dataset), "iterations": options.iterations, "warmup": options.warmup,
            "profile": profile}
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(args)], env=env, cwd=tempfile.gettempdir(),
                         check=True, capture_output=True, text=True)
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    package = Path(result.pop("package"))
    if package != tree:
        raise RuntimeError(f"timing {tree}: the child imported parksim from {package}")
    return {"folder": str(tree), **result}


def _median(rows: list[dict[str, Any]], key: str) -> float:
    return statistics.median(float(r[key]) for r in rows)


class TrainStepSuite(Suite):
    """A training step's time at a finished run's state, against a reference copy of the package."""

    name = "train-step"
    help = "training step time at a finished run's state, against a reference package copy"
    description = ("Median wall and process-CPU ms of Trainer.iteration() resumed from a finished run's last "
                   "checkpoint (photometric phase extended), each package in its own process, this package and "
                   "--reference in alternating rounds. Figures: the step's time and minor page faults, beside the "
                   "reference's.")
    Options = TrainStepOptions

    def run(self, options: TrainStepOptions, context: Context) -> Outcome:
        """Time this package (and the reference) round by round."""
        import parksim

        from ...data import DatasetReader
        from ...recon.config import load_config

        if options.run is not None and options.dataset is not None:
            run, dataset = options.run.resolve(), options.dataset.resolve()
        else:
            run, dataset = (p.resolve() for p in ensure_bundle(context, "scene1", None, "cpu_30min"))
        this = Path(parksim.__file__).resolve().parent.parent
        trees = {"this": ("this package", this)}
        if options.reference is not None:
            trees["reference"] = (options.reference_label or f"package copy at {options.reference}",
                                  options.reference.resolve())
        order = list(trees)
        rows: list[dict[str, Any]] = []
        with progress(options.rounds * len(trees), "bench train-step", context.quiet) as bar:
            for r in range(options.rounds):
                for which in order if r % 2 == 0 else order[::-1]:
                    label, tree = trees[which]
                    profile = options.profile if which == "this" and r == options.rounds - 1 else 0
                    rows.append({"round": r + 1, "package": which, "label": label,
                                 **_probe(tree, run, dataset, options, profile)})
                    bar.update(1)
        ops = next((row.pop("ops") for row in rows if "ops" in row), None)
        model = next(iter(DatasetReader(dataset).rig.cameras.values())).model
        mine = [r for r in rows if r["package"] == "this"]
        theirs = [r for r in rows if r["package"] == "reference"]
        condition = (f"{mine[0]['gaussians']:,} Gaussians, SH degree "
                     f"{load_config(run / 'config.yaml').photometric.sh_degree}, {model.width}x{model.height}")
        figures = []
        for target, key, unit, cpu in ((f"training step, {condition}", "wall_ms", "ms", "cpu_ms"),
                                       (f"minor page faults per training step, {condition}", "faults", "count", None)):
            ref: dict[str, Any] = {}
            if theirs:
                ref = {"reference": _median(theirs, key), "reference_label": trees["reference"][0],
                       "reference_cpu": _median(theirs, cpu) if cpu else None,
                       "goal": "1.5x faster than 5ebf0ca (issue [13])" if cpu else None}
            figures.append(Figure(target, _median(mine, key), unit, cpu=_median(mine, cpu) if cpu else None, **ref))
        return Outcome(figures, {"run": str(run), "dataset": str(dataset), "rounds": rows, "profile": ops})
