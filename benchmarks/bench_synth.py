"""Time ``parksim synth`` serially and with the process pool, in the same run, and record both.

Usage: python benchmarks/bench_synth.py [--preset scene1] [--frames 12] [--workers 1,2] [--repeats 1]
Each configuration renders the same frames into a fresh temporary dataset (the generator's own ``generate``, as
``parksim synth`` calls it); wall time, process CPU time (this process + its pool workers) and the 1-minute load
average before and after are appended as a section to benchmarks/RESULTS_synth.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

from parksim.bench.common import cpu_model


def _cpu_seconds() -> float:
    """User + system CPU of this process and of its reaped children (the pool's workers)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="scene1")
    ap.add_argument("--frames", type=int, default=12, help="frames per run (640x480 x 4 cameras each)")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts to compare (1 = serial)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per worker count, interleaved; medians reported")
    ap.add_argument("--results", default=str(Path(__file__).with_name("RESULTS_synth.md")))
    args = ap.parse_args()
    from parksim.synth import generate, get_preset

    preset = dataclasses.replace(get_preset(args.preset), frames=args.frames)
    counts = [int(w) for w in args.workers.split(",")]
    runs: dict[int, list[tuple[float, float, float, float]]] = {w: [] for w in counts}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for w in counts:
                load0, cpu0, t0 = os.getloadavg()[0], _cpu_seconds(), time.perf_counter()
                generate(preset, Path(tmp) / f"run{r}_w{w}", workers=w)
                wall, cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
                runs[w].append((wall, cpu, load0, os.getloadavg()[0]))
                print(f"workers {w}: wall {wall:.1f} s, CPU {cpu:.1f} s", flush=True)
    serial = statistics.median(x[0] for x in runs[counts[0]])
    rows = []
    for w in counts:
        wall = statistics.median(x[0] for x in runs[w])
        cpu = statistics.median(x[1] for x in runs[w])
        loads = ", ".join(f"{a:.1f}->{b:.1f}" for _, _, a, b in runs[w])
        rows.append(f"| {w} | {wall:.1f} | {cpu:.1f} | {serial / wall:.2f}x | {loads} |")
    text = (f"\n## Serial against the pool: {args.preset}, {args.frames} frames x 4 cameras at "
            f"{preset.width}x{preset.height} ({datetime.datetime.now().isoformat(timespec='minutes')})\n\n"
            f"- command: `python benchmarks/bench_synth.py --preset {args.preset} --frames {args.frames} "
            f"--workers {args.workers} --repeats {args.repeats}` (medians over {args.repeats} interleaved run(s))\n"
            f"- machine: {cpu_model()}, {os.cpu_count()} cores, {platform.system()} {platform.release()}, "
            f"Python {platform.python_version()}\n"
            f"- CPU = user + system time of the process and its pool workers; wall includes pool start-up (each "
            f"worker imports and builds its renderer once)\n\n"
            "| workers | wall (s) | CPU (s) | speed-up (wall, vs first row) | 1-min load before->after |\n"
            "|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
    with open(args.results, "a") as f:
        f.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
