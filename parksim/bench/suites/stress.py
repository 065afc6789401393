"""``parksim bench stress``: the property-based stress tests (``tests/test_stress.py`` of the repository) run with
many more examples than CI gives them, counting the cases hypothesis tried and the failures it found per property.

The same test code serves both: ``PARKSIM_STRESS_EXAMPLES`` sets its example count (read when the test module is
imported, so a suite run is its own process). Cases are counted through hypothesis' observability callbacks
(coverage collection off), failures from pytest's reports. The test file is the repository's: run from its root,
or pass ``--tests``.
"""

from __future__ import annotations

import os
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...checked_options import CheckedOptions
from ..common import progress, pyplot, save_figure
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["StressSuite", "StressOptions", "run_tests", "EXAMPLES_ENV"]

EXAMPLES_ENV = "PARKSIM_STRESS_EXAMPLES"
"""The environment variable ``tests/test_stress.py`` reads its examples per property from."""


@dataclass(frozen=True)
class StressOptions(CheckedOptions):
    """Options of ``parksim bench stress``."""

    examples: int = field(default=500, metadata={"help": "hypothesis examples per property", "low": 1, "quick": 3})
    tests: Path = field(default=Path("tests/test_stress.py"), metadata={
        "help": "the stress test file, relative to the working folder (the repository's root)"})


class _Reports:
    """pytest plugin: per-test outcome, duration and the failure's text, and a progress bar over the tests."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.bar: Any = None
        self.tests: dict[str, dict[str, Any]] = {}

    def pytest_collection_modifyitems(self, items: list[Any]) -> None:
        self.bar = progress(len(items), "bench stress", self.quiet)

    def pytest_runtest_logreport(self, report: Any) -> None:
        if report.when == "call" or report.outcome != "passed":
            name = report.nodeid.split("::")[-1]
            self.tests[name] = {"outcome": report.outcome, "seconds": report.duration,
                                "failure": str(report.longrepr)[-2000:] if report.failed else None}
        if report.when == "teardown" and self.bar is not None:
            self.bar.update(1)

    def pytest_unconfigure(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run_tests(tests: Path, examples: int, seed: int, quiet: bool) -> tuple[dict[str, Counter], dict[str, dict]]:
    """Run ``tests`` in this process with ``examples`` per property.

    Args:
        tests: the pytest file.
        examples: hypothesis examples per property (``EXAMPLES_ENV``).
        seed: hypothesis seed.
        quiet: no progress bar.

    Returns:
        Per property, its case counts by status (passed / failed / gave_up); per test, pytest's outcome,
        duration and failure text. ``RuntimeError`` when pytest ran no test (a collection or usage error).
    """
    import pytest
    from hypothesis.internal import observability

    os.environ[EXAMPLES_ENV] = str(examples)
    cases: dict[str, Counter] = defaultdict(Counter)

    def seen(observation: Any) -> None:
        if observation.type == "test_case":
            cases[observation.property.split("::")[-1]][observation.status] += 1

    collect_coverage = observability.OBSERVABILITY_COLLECT_COVERAGE
    observability.OBSERVABILITY_COLLECT_COVERAGE = False
    observability.add_observability_callback(seen)
    reports = _Reports(quiet)
    try:
        code = pytest.main([str(tests), "-q", "-p", "no:cacheprovider", f"--hypothesis-seed={seed}",
                            f"--rootdir={tests.parent}"], plugins=[reports])
    finally:
        observability.remove_observability_callback(seen)
        observability.OBSERVABILITY_COLLECT_COVERAGE = collect_coverage
        os.environ.pop(EXAMPLES_ENV, None)
    if code not in (pytest.ExitCode.OK, pytest.ExitCode.TESTS_FAILED):   # nothing ran: not a result
        raise RuntimeError(f"{tests}: pytest stopped with {pytest.ExitCode(code).name} before running the properties")
    return cases, reports.tests


class StressSuite(Suite):
    """Cases tried and failures found by the stress tests at many examples per property."""

    name = "stress"
    help = "the hypothesis stress tests at many examples: cases tried, failures found"
    description = ("Run tests/test_stress.py (projection, rasterizer, IPM, losses, render at the scene edge; float32 "
                   "finiteness and float64 agreement) with --examples per property instead of CI's default, counting "
                   "cases and failures. Run from the repository root, or pass --tests. Figures: cases tried and "
                   "failing properties (goal 0).")
    Options = StressOptions

    def run(self, options: StressOptions, context: Context) -> Outcome:
        """Run the stress tests with ``options.examples`` per property, hypothesis seeded by ``context.seed``."""
        if not options.tests.is_file():
            raise FileNotFoundError(f"{options.tests}: no such test file (run from the repository root or pass "
                                    "--tests)")
        cases, tests = run_tests(options.tests, options.examples, context.seed, context.quiet)
        rows = []
        for name in sorted(set(cases) | set(tests)):
            c, t = cases.get(name, Counter()), tests.get(name, {})
            rows.append({"property": name, "cases": sum(c.values()), "passed": c["passed"],
                         "failed_cases": c["failed"], "invalid": c["gave_up"], "outcome": t.get("outcome", "not run"),
                         "seconds": t.get("seconds"), "failure": t.get("failure")})
        total = {"properties": len(rows), "cases": sum(r["cases"] for r in rows),
                 "failing_properties": sum(r["outcome"] == "failed" for r in rows)}
        where = f"{options.tests.name} at {options.examples} examples per property"
        figures = [Figure(f"{where}: cases tried", total["cases"], "cases", better="higher"),
                   Figure(f"{where}: failing properties", total["failing_properties"], "properties", goal="0")]
        data = {"tests": str(options.tests), "examples_env": EXAMPLES_ENV, "total": total, "properties": rows}
        return Outcome(figures, data, lambda png: _plot(rows, png))


def _plot(rows: list[dict[str, Any]], png: Path) -> None:
    """Cases per property, failing ones in red."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 0.45 * len(rows) + 1.5))
    ax.barh([r["property"] for r in rows], [r["cases"] for r in rows],
            color=["C3" if r["outcome"] == "failed" else "C2" for r in rows])
    ax.set(xlabel="cases tried (red: property failed)", title="stress campaign")
    ax.tick_params(axis="y", labelsize=7)
    save_figure(fig, png)
