"""Env steps/s of vector ParkSim-v0 for 1, 2 and 4 envs: sub-envs in Ray actors, batch renders against
``parksim serve`` and ``parksim serve --ray``, and gymnasium's in-process SyncVectorEnv as the reference.

Each run: reset(seed=0), ``--warmup`` steps, then ``--steps`` timed vector steps of seeded random actions.
Wall time, and the CPU time of this process's whole tree (this process, Ray's daemons and actors, the server
subprocess and its replicas, read from /proc), so a loaded machine shows in wall time but not in CPU time.
Writes benchmarks/RESULTS_env.md.
"""

from __future__ import annotations

import argparse
import datetime
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from parksim.omp_env import prefer_sleeping_omp_threads  # noqa: E402

prefer_sleeping_omp_threads()   # before torch loads, as the CLI and the server do

import gymnasium as gym  # noqa: E402
import httpx  # noqa: E402
import numpy as np  # noqa: E402

import parksim.env  # noqa: E402, F401  (registers ParkSim-v0)
from sim_fixtures import make_bundle  # noqa: E402

_TICK = os.sysconf("SC_CLK_TCK")


def tree_cpu_seconds(root: int) -> float:
    """User + system CPU seconds of ``root`` and every live descendant (Linux /proc)."""
    stats: dict[int, tuple[int, float]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stats[int(entry)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / _TICK)
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        total += stats.get(pid, (0, 0.0))[1]
        todo.extend(children.get(pid, []))
    return total


def measure(envs: Any, steps: int, warmup: int) -> tuple[float, float]:
    """(env steps/s by wall time, CPU ms of the process tree per env step) over ``steps`` vector steps."""
    rng = np.random.default_rng(0)
    envs.reset(seed=0)
    for _ in range(warmup):
        envs.step(rng.uniform(-1, 1, envs.action_space.shape).astype(np.float32))
    actions = rng.uniform(-1, 1, (steps, *envs.action_space.shape)).astype(np.float32)
    cpu0, t0 = tree_cpu_seconds(os.getpid()), time.perf_counter()
    for a in actions:
        envs.step(a)
    wall, cpu = time.perf_counter() - t0, tree_cpu_seconds(os.getpid()) - cpu0
    n = envs.num_envs * steps
    return n / wall, 1000 * cpu / n


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def served(scenes: Path, ray: bool) -> Iterator[str]:
    """``parksim serve`` (``--ray``: on Ray Serve) as a subprocess on a free port; yields its URL once healthy."""
    port = _free_port()
    cli = "from parksim.cli import main; raise SystemExit(main())"
    cmd = [sys.executable, "-c", cli, "serve", "--scenes", str(scenes), "--port", str(port), *(["--ray"] * ray)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 300
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"{' '.join(cmd)} exited: {proc.stderr.read() if proc.stderr else ''}")
            with suppress(httpx.HTTPError):   # not listening yet
                if httpx.get(f"{url}/healthz", timeout=2).status_code == 200:
                    break
            if time.monotonic() > deadline:
                raise RuntimeError(f"{' '.join(cmd)} not healthy within 300 s")
            time.sleep(0.5)
        yield url
    finally:
        proc.send_signal(2)   # SIGINT: the CLI shuts Serve and Ray down
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--envs", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per setting (median reported)")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "RESULTS_env.md")
    args = ap.parse_args()
    view = {"cameras": ["front", "left", "rear", "right"], "bev": False, "scale": args.scale}
    rows: list[tuple[str, int, float, float]] = []

    def run(name: str, make: Callable[[int], Any]) -> None:
        for n in args.envs:
            envs = make(n)
            results = [measure(envs, args.steps, args.warmup) for _ in range(args.repeats)]
            envs.close()
            rate, cpu = statistics.median(r[0] for r in results), statistics.median(r[1] for r in results)
            rows.append((name, n, rate, cpu))
            print(f"{name:32s} {n}  {rate:7.1f} env steps/s  {cpu:7.1f} CPU ms/env step", flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        scenes = Path(tmp) / "scenes"
        bundle = make_bundle(scenes / args.preset, preset=args.preset, n=args.gaussians)
        run("in-process SyncVectorEnv", lambda n: gym.make_vec(
            "ParkSim-v0", n, vectorization_mode="sync", bundle=bundle, **view))
        import ray

        ray.init(num_cpus=2, object_store_memory=150 * 1024**2, include_dashboard=False, logging_level="WARNING")
        try:
            run("Ray actors (RayVectorEnv)", lambda n: gym.make_vec("ParkSim-v0", n, bundle=str(bundle), **view))
        finally:
            ray.shutdown()
        for ray_serve in (False, True):
            with served(scenes, ray_serve) as url:
                name = f"batch POST /render, serve{' --ray' if ray_serve else ''}"
                run(name, lambda n: gym.make_vec("ParkSim-v0", n, backend="batch", server=url, **view))
    cpu_model = next((line.split(":", 1)[1].strip() for line in subprocess.run(
        ["lscpu"], capture_output=True, text=True).stdout.splitlines() if line.startswith("Model name")), "?")
    ref = {n: rate for name, n, rate, _ in rows if name.startswith("in-process")}
    lines = [f"# Vector env steps/s ({args.preset}, four {args.scale:g}x cameras)", "",
             f"- command: `python benchmarks/bench_env.py --steps {args.steps} --repeats {args.repeats} "
             f"--preset {args.preset} --gaussians {args.gaussians} --scale {args.scale:g}`",
             f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
             f"- machine: {os.cpu_count()} cores ({cpu_model}), shared with other jobs while it ran "
             f"(load average at the end {os.getloadavg()[0]:.1f}); Ray started with num_cpus=2",
             "- observation: four camera views + state per env; random actions, next-step autoreset; "
             f"median of {args.repeats} runs of {args.steps} vector steps after {args.warmup} warm-up steps",
             "- CPU: user + system seconds of the whole process tree (driver, Ray daemons and actors, server "
             "subprocess and its replicas) per env step; wall time suffers from the other jobs, CPU time less", "",
             "| vectorisation | envs | env steps/s | vs in-process, same envs | CPU ms / env step |",
             "| --- | ---: | ---: | ---: | ---: |"]
    lines += [f"| {name} | {n} | {rate:.1f} | {rate / ref[n]:.2f}x | {cpu:.1f} |" for name, n, rate, cpu in rows]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
