"""``parksim bench stress``: the property-based stress suite (``tests/test_stress.py``) run with many more
examples than CI gives it, counting the cases hypothesis tried and the failures it found per property.

The same test code serves both: ``PARKSIM_STRESS_EXAMPLES`` sets its example count. Cases are counted
through hypothesis' observability callbacks (coverage collection off), failures from pytest's reports.
"""

from __future__ import annotations

import argparse
import os
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

from .common import ROOT, md_table, metadata, progress, pyplot, save_figure, write_result

__all__ = ["run", "run_suite", "STRESS_TESTS", "EXAMPLES_ENV"]

STRESS_TESTS = ROOT / "tests" / "test_stress.py"
EXAMPLES_ENV = "PARKSIM_STRESS_EXAMPLES"


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


def run_suite(tests: Path, examples: int, seed: int, quiet: bool) -> tuple[dict[str, Counter], dict[str, dict]]:
    """Run ``tests`` in this process with ``examples`` per property; returns per-property case counts by status
    (passed / failed / gave_up) and per-test pytest reports."""
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
        pytest.main([str(tests), "-q", "-p", "no:cacheprovider", f"--hypothesis-seed={seed}",
                     f"--rootdir={tests.parent}"], plugins=[reports])
    finally:
        observability.remove_observability_callback(seen)
        observability.OBSERVABILITY_COLLECT_COVERAGE = collect_coverage
        os.environ.pop(EXAMPLES_ENV, None)
    return cases, reports.tests


def run(args: argparse.Namespace) -> Any:
    """Run the stress suite; write ``stress.json/md/png`` with cases tried and failures per property."""
    meta = {**metadata(args.command_line), "examples": args.examples, "seed": args.seed}
    cases, tests = run_suite(args.tests, args.examples, args.seed, args.quiet)
    names = sorted(set(cases) | set(tests))
    rows = []
    for name in names:
        c, t = cases.get(name, Counter()), tests.get(name, {})
        rows.append({"property": name, "cases": sum(c.values()), "passed": c["passed"], "failed_cases": c["failed"],
                     "invalid": c["gave_up"], "outcome": t.get("outcome", "not run"), "seconds": t.get("seconds"),
                     "failure": t.get("failure")})
    total = {"properties": len(rows), "cases": sum(r["cases"] for r in rows),
             "failing_properties": sum(r["outcome"] == "failed" for r in rows)}
    body = [f"`{args.tests.relative_to(ROOT) if args.tests.is_relative_to(ROOT) else args.tests}` with "
            f"{EXAMPLES_ENV}={args.examples} (CI runs the default), hypothesis seed {args.seed}, float32 kernels "
            "checked for finiteness and against float64 / reference implementations.", "",
            f"**{total['cases']:,} cases tried over {total['properties']} properties; "
            f"{total['failing_properties']} failing properties.** A failing property's cases include hypothesis' "
            "shrinking of the failure.", "",
            *md_table(["property", "cases", "passed", "failed cases", "invalid (filtered)", "outcome", "seconds"],
                      [(r["property"], r["cases"], r["passed"], r["failed_cases"], r["invalid"], r["outcome"],
                        "-" if r["seconds"] is None else f"{r['seconds']:.1f}") for r in rows])]
    body += [f"\nFailure of `{r['property']}`:\n\n```\n{r['failure'][-1500:]}\n```" for r in rows if r["failure"]]
    return write_result(args.out, "stress", meta, {"total": total, "properties": rows}, body,
                        lambda png: _plot(rows, meta, png))


def _plot(rows: list[dict[str, Any]], meta: dict[str, Any], png: Path) -> None:
    """Cases per property, failing ones in red."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 0.45 * len(rows) + 1.5))
    ax.barh([r["property"] for r in rows], [r["cases"] for r in rows],
            color=["C3" if r["outcome"] == "failed" else "C2" for r in rows])
    ax.set(xlabel="cases tried (red: property failed)", title="stress campaign")
    ax.tick_params(axis="y", labelsize=7)
    save_figure(fig, meta, png)
