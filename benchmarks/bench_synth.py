"""Time ``parksim synth scene1`` (default: 100 frames x 4 cameras at 640x480) and record it.

Usage: python benchmarks/bench_synth.py [--preset scene1] [-o data/scene1]
Writes benchmarks/RESULTS_synth.md with the command, machine, date and wall time.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="scene1")
    ap.add_argument("-o", "--output", default="data/scene1")
    ap.add_argument("--results", default=str(Path(__file__).with_name("RESULTS_synth.md")))
    args = ap.parse_args()
    start = time.perf_counter()
    from parksim.commands import synth  # the CLI's own subcommand, run in-process (imports are timed)

    parser = argparse.ArgumentParser(prog="parksim")
    synth.add_parser(parser.add_subparsers())
    synth.run(parser.parse_args(["synth", args.preset, "-o", args.output, "--overwrite", "--quiet"]))
    wall = time.perf_counter() - start
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    text = (f"# `parksim synth` timing\n\n"
            f"- command: `parksim synth {args.preset} -o {args.output}` (run by `python benchmarks/bench_synth.py`)\n"
            f"- machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"{platform.system()} {platform.release()}, Python {platform.python_version()}; "
            f"1-min load average at the end: {load:.1f} (shared machine)\n"
            f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}\n"
            f"- wall time: **{wall:.1f} s** (target: under 300 s for 100 frames x 4 cameras at 640x480)\n")
    Path(args.results).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
