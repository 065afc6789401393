"""Two tiny scenes trained one after the other (``parksim reconstruct`` twice) vs as Ray tasks (``parksim batch``).

Each variant is the command line a user would run, timed from the outside: wall time, and the CPU time of every
process it started (Ray's GCS, raylet, agents, workers included), sampled from /proc until each is reaped (this
process is their child subreaper, so none escapes). "Ray, nothing to train" is ``parksim batch`` over finished
bundles: Ray's own start and stop, the fixed cost of a batch. Variants alternate within each repeat; medians are
reported.

    .venv/bin/python benchmarks/bench_batch.py --repeats 3 --out benchmarks/RESULTS_batch.md
"""

from __future__ import annotations

import argparse
import ctypes
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import ray
import torch

PR_SET_CHILD_SUBREAPER = 36
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
CLI = [sys.executable, "-m", "parksim.cli"]


def become_subreaper() -> None:
    """Orphaned descendants (Ray workers whose raylet exited) become this process's children, so they are reaped
    here, after their last CPU sample, and never outlive the measurement."""
    if ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER) failed")


def cpu_by_pid() -> dict[int, tuple[int, float]]:
    """Every process's parent and its own user + system CPU seconds, from /proc (zombies included)."""
    out = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:   # exited while listed
            continue
        out[int(stat.parent.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / CLOCK_TICKS)
    return out


def run_measured(command: list[str], env: dict[str, str]) -> float:
    """Run ``command`` to the end of every process it starts; returns their CPU seconds, each sampled every 0.1 s
    until it is reaped. (``RUSAGE_CHILDREN`` misses most of Ray's: 9.5 s against 29.7 s sampled for one batch.)"""
    log = tempfile.TemporaryFile("w+")
    proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, text=True, env={**os.environ, **env})
    tree, cpu, code = {proc.pid}, {}, None
    while True:
        for pid, (ppid, seconds) in cpu_by_pid().items():
            if pid in tree or ppid in tree:
                tree.add(pid)
                cpu[pid] = max(cpu.get(pid, 0.0), seconds)
        try:
            while (reaped := os.waitpid(-1, os.WNOHANG))[0]:   # after sampling: a zombie still shows its CPU
                code = os.waitstatus_to_exitcode(reaped[1]) if reaped[0] == proc.pid else code
        except ChildProcessError:
            break
        time.sleep(0.1)
    if code != 0:
        log.seek(0)
        raise RuntimeError(f"{' '.join(command)} exited {code}:\n{log.read()}")
    return sum(cpu.values())


def measure(commands: list[list[str]], env: dict[str, str]) -> tuple[float, float]:
    """Wall and CPU seconds of running ``commands`` one after the other, every process they start included."""
    start = time.perf_counter()
    cpu = sum(run_measured(command, env) for command in commands)
    return time.perf_counter() - start, cpu


def train_seconds(scenes: Path) -> tuple[float, float]:
    """Training wall and CPU seconds summed over the bundles in ``scenes`` (the trainer's own clocks)."""
    records = [json.loads((b / "metrics.jsonl").read_text().splitlines()[-1]) for b in sorted(scenes.iterdir())]
    return sum(r["elapsed_s"] for r in records), sum(r["cpu_s"] for r in records)


def load_average() -> str:
    return ", ".join(f"{v:.1f}" for v in os.getloadavg())


def cpu_model() -> str:
    out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    return next((line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name")), "?")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/RESULTS_batch.md"))
    args = parser.parse_args()
    become_subreaper()
    work = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    try:
        data = [work / "a", work / "b"]
        subprocess.run([*CLI, "synth", "tiny", "-o", str(data[0]), "--quiet"], check=True)
        shutil.copytree(data[0], data[1])
        started, load_start = datetime.datetime.now(datetime.timezone.utc), load_average()

        def sequential(out: Path) -> list[list[str]]:
            return [[*CLI, "reconstruct", str(d), "-o", str(out / d.name), "--config", "tiny"] for d in data]

        def batch(out: Path) -> list[list[str]]:
            return [[*CLI, "batch", *map(str, data), "-o", str(out), "--config", "tiny"]]

        one_thread = {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
        variants: dict[str, tuple[Callable[[Path], list[list[str]]], dict[str, str], str]] = {
            "sequential (`parksim reconstruct` x2, default threads)": (sequential, {}, "seq"),
            "sequential, 1 thread (`OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1`)": (sequential, one_thread, "seq1"),
            "Ray tasks (`parksim batch`, 1 CPU each)": (batch, {}, "ray"),
            "Ray, nothing to train (`parksim batch` over finished bundles)": (batch, {}, "ray")}
        results: dict[str, list[tuple[float, float, float, float]]] = {name: [] for name in variants}
        for repeat in range(args.repeats):
            for name, (commands, env, folder) in variants.items():
                out = work / f"{folder}{repeat}"
                wall, cpu = measure(commands(out), env)
                results[name].append((wall, cpu, *train_seconds(out)))
                print(f"{name}: {wall:.1f} s wall, {cpu:.1f} s CPU", file=sys.stderr)
        write_report(args, results, started, load_start)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def write_report(args: argparse.Namespace, results: dict[str, list[tuple[float, float, float, float]]],
                 started: datetime.datetime, load_start: str) -> None:
    reference = statistics.median(r[0] for r in next(iter(results.values())))
    rows = []
    for name, runs in results.items():
        wall, cpu, train_wall, train_cpu = (statistics.median(r[k] for r in runs) for k in range(4))
        train = "(none: skipped)" if "nothing" in name else f"{train_wall:.1f} / {train_cpu:.1f}"
        rows.append(f"| {name} | {wall:.1f} | {cpu:.1f} | {train} | {wall / reference:.2f}x |")
    command = f".venv/bin/python benchmarks/bench_batch.py --repeats {args.repeats} --out {args.out}"
    text = f"""# Many scenes as Ray tasks (`parksim batch`)

Command: `{command}`

Machine: {platform.machine()}, {os.cpu_count()} cores ({cpu_model()}), torch {torch.__version__}, Ray {ray.__version__};
started {started.isoformat(timespec="minutes")}; load average {load_start} at the start, {load_average()} at the end.
The machine was shared with other jobs running at the same time (up to 7 other sessions): wall times are
inflated and noisy, so CPU time is reported beside them.

Workload: two `parksim synth tiny` datasets (12 frames x 4 cameras at 160x120, one copied under a second name),
`--config tiny` (20 iterations). Each variant is the command a user runs, as a fresh process; median of
{args.repeats} repeats, variants alternating. CPU is every process the command started (Ray's GCS, raylet, agents,
workers included), each sampled from /proc every 0.1 s until this benchmark, their child subreaper, reaps it.
Train wall / CPU is the trainer's own clock summed over both scenes (the `elapsed_s` and `cpu_s` of each run's
last metrics record).

| variant | wall s (median) | process CPU s (median) | train wall / CPU s, both scenes | wall vs sequential |
| --- | --- | --- | --- | --- |
{chr(10).join(rows)}
"""
    args.out.write_text(text)


if __name__ == "__main__":
    main()
