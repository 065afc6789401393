"""``parksim bench SUITE`` runs one benchmark suite into a JSON record; ``parksim bench report`` builds the dashboard.

The suites and their options come from ``parksim.bench.suite.SUITES``; each suite's command line is built from its
``Options`` dataclass (``parksim.commands.options``).
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path
from typing import Any

from .options import add_plugin_parsers, options_from_args

__all__ = ["add_parser", "run", "RESULTS", "WORK"]

RESULTS = Path("benchmarks/results")
"""Where records go by default (relative to the working folder: run from the repository's root)."""
WORK = Path("out/bench")
"""Scratch folder for the datasets, bundles and runs the suites make."""


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``bench`` with one sub-command per suite, and ``report``."""
    from ..bench.suite import SUITES, suite

    p = sub.add_parser(
        "bench", help="benchmark suites that write JSON records; `report` builds benchmarks/RESULTS.md",
        description="Seeded benchmark suites. Each run writes one record, RESULTS/SUITE/STAMP-COMMIT.json (+ .png): "
                    "the command, commit, date, machine, CPU model, load and every figure with its unit beside the "
                    "reference measured in the same run. `parksim bench report` regenerates the dashboard "
                    "benchmarks/RESULTS.md from the records. --quick is a seconds-long smoke run whose record goes "
                    "under the work folder, not the results.")
    cmds = p.add_subparsers(dest="bench", metavar="SUITE", required=True)
    for q in add_plugin_parsers(cmds, (suite(name) for name in SUITES), p.formatter_class).values():
        q.add_argument("--results", type=Path, default=None,
                       help=f"results folder for the record (default {RESULTS}; --quick: WORK/results)")
        q.add_argument("--work", type=Path, default=WORK, help="scratch folder for datasets, bundles and runs")
        q.add_argument("--seed", type=int, default=0, help="seed of the scenes, poses and sampling")
        q.add_argument("--quick", action="store_true", help="the small preset (seconds), for tests")
        q.add_argument("--quiet", action="store_true", help="no progress bars")
    r = cmds.add_parser("report", help="regenerate benchmarks/RESULTS.md from the records",
                        description="Build the dashboard from the records alone: one row per target with the figure "
                                    "of the latest record holding it, the reference measured in the same run, the "
                                    "machine and a link to the record. The same records give the same bytes.",
                        formatter_class=p.formatter_class)
    r.add_argument("--results", type=Path, default=RESULTS, help="results folder to read")
    r.add_argument("-o", "--output", type=Path, default=Path("benchmarks/RESULTS.md"), help="dashboard to write")
    return p


def run(args: argparse.Namespace) -> int:
    """Run the chosen suite (or the report) and print where its record went."""
    from ..bench.report import write_dashboard
    from ..bench.suite import Context, run_suite, suite

    if args.bench == "report":
        if not args.results.is_dir():
            raise FileNotFoundError(f"{args.results}: no results folder (run from the repository root, or --results)")
        print(f"wrote {write_dashboard(args.results, args.output)}")
        return 0
    options: Any = options_from_args(suite(args.bench).Options, args, quick=args.quick)
    context = Context(work=args.work, seed=args.seed, quick=args.quick, quiet=args.quiet)
    results = args.results or (args.work / "results" if args.quick else RESULTS)
    path = run_suite(args.bench, options, context, results, shlex.join(["parksim", *args.argv]))
    print(f"wrote {path}")
    return 0
