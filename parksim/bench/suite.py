"""The benchmark-suite contract, its registry and the one function that runs a suite into a record.

A suite is a ``Suite`` subclass in its own module under ``parksim.bench.suites``: a ``name``, one-line ``help``,
a ``description``, an ``Options`` dataclass (its fields' ``metadata`` give ``--help`` and the ``--quick``
preset; ``parksim.commands.options`` builds the command line from it) and ``run(options, context)`` returning an
``Outcome``: the figures, the raw data and a plot. ``run_suite`` times nothing itself; it stamps the record
(command, commit, date, machine, load, versions) and writes it. A new suite is one module and one line in
``SUITES`` (``docs/architecture.md``). Suite modules import torch and friends inside ``run``, so building
``parksim bench --help`` stays cheap.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..checked_options import check_options
from ..plugins import Plugin, instantiate
from .record import Figure, Record, current_commit, this_machine, utc_now, write_record

__all__ = ["Suite", "Context", "Outcome", "SUITES", "suite", "run_suite"]


@dataclass(frozen=True)
class Context:
    """What every suite gets besides its options.

    Attributes:
        work: scratch folder for the datasets, bundles and runs a suite makes (kept between runs, reused).
        seed: seed of the scenes, poses and sampling.
        quick: the seconds-long preset (tests); its records are not results.
        quiet: no progress bars.
    """

    work: Path
    seed: int = 0
    quick: bool = False
    quiet: bool = False


@dataclass
class Outcome:
    """What a suite's run gives back.

    Attributes:
        figures: the dashboard's rows, one per target.
        data: everything else measured (tables, series), kept in the record as it is.
        plot: ``plot(png)`` draws the run's figure, or None.
        details: Markdown too long for the dashboard's rows (a full table), which ``parksim bench report`` writes
            as ``RESULTS_<suite>.md`` beside the dashboard and links from the suite's section; or None.
    """

    figures: list[Figure]
    data: dict[str, Any] = field(default_factory=dict)
    plot: Callable[[Path], None] | None = None
    details: str | None = None


class Suite(Plugin):
    """A named benchmark (see the module docstring)."""

    @abstractmethod
    def run(self, options: Any, context: Context) -> Outcome:
        """Measure.

        Args:
            options: an instance of ``self.Options``.
            context: scratch folder, seed, quick and quiet.

        Returns:
            The figures, raw data and plot of this run.
        """


SUITES: dict[str, str] = {
    "scaling": "scaling:ScalingSuite",
    "render": "render:RenderSuite",
    "projection": "projection:ProjectionSuite",
    "rasterize": "rasterize:RasterizeSuite",
    "ipm": "ipm:IPMSuite",
    "ut-accuracy": "ut_accuracy:UTAccuracySuite",
    "gpu": "gpu:GPUSuite",
    "knobs": "knobs:KnobsSuite",
    "train": "train:TrainSuite",
    "stress": "stress:StressSuite",
    "soak-train": "soak:SoakTrainSuite",
    "soak-server": "soak:SoakServerSuite",
    "train-step": "train_step:TrainStepSuite",
    "compact": "compact:CompactSuite",
    "import": "imports:ImportSuite",
    "pose-refine": "pose_refine:PoseRefineSuite",
    "real": "real:RealSuite",
    "synth": "synth:SynthSuite",
    "detectors": "detectors:DetectorsSuite",
    "planner": "planner:PlannerSuite",
    "slot-aware": "slot_aware:SlotAwareSuite",
    "server": "server:ServerSuite",
    "server-memory": "server_memory:ServerMemorySuite",
    "ray": "ray:RaySuite",
    "batch": "batch:BatchSuite",
    "env": "env:EnvSuite",
    "hardening": "hardening:HardeningSuite",
    "actors": "actors:ActorsSuite",
    "scenarios": "scenarios:ScenariosSuite",
}
"""Suite name -> ``module:Class`` under ``parksim.bench.suites``."""


def suite(name: str) -> Suite:
    """The registered suite ``name``, instantiated (imports its module)."""
    return instantiate(SUITES, name, f"{__package__}.suites", Suite, "benchmark suite")


def _versions() -> dict[str, str]:
    import sys
    from importlib.metadata import PackageNotFoundError, version

    found = {"python": sys.version.split()[0]}
    for package in ("parksim", "torch", "numba", "numpy", "gsplat"):
        try:
            found[package] = version(package)
        except PackageNotFoundError:
            continue
    return found


def _threads() -> dict[str, int]:
    import sys

    found: dict[str, int] = {}
    if "torch" in sys.modules:
        found["torch_threads"] = sys.modules["torch"].get_num_threads()
    if "numba" in sys.modules:
        found["numba_threads"] = sys.modules["numba"].get_num_threads()
    return found


def run_suite(name: str, options: Any, context: Context, results: Path, command: str) -> Path:
    """Run suite ``name`` and write its record.

    Args:
        name: a key of ``SUITES``.
        options: the suite's ``Options`` instance.
        context: scratch folder, seed, quick, quiet.
        results: the results folder the record goes under (``results/<name>/``).
        command: the command line that reproduces the run (recorded as it is).

    Returns:
        The record's path.
    """
    import os

    chosen = suite(name)
    if not isinstance(options, chosen.Options):
        raise TypeError(f"suite {name}: options must be {chosen.Options.__name__}, got {type(options).__name__}")
    check_options(options)
    date, load_start = utc_now(), [round(x, 2) for x in os.getloadavg()]
    outcome = chosen.run(options, context)
    record = Record(suite=name, command=command, commit=current_commit(), date=date, machine=this_machine(),
                    figures=outcome.figures, options={**vars(options), "seed": context.seed,
                                                      "quick": context.quick},
                    load={"start": load_start, "end": [round(x, 2) for x in os.getloadavg()]},
                    versions={**_versions(), **{k: str(v) for k, v in _threads().items()}}, data=outcome.data,
                    details=outcome.details)
    return write_record(record, results, outcome.plot)
