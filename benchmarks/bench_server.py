"""Loopback benchmark of ``parksim serve``: GET /render latency (4 views + BEV, one view, BEV only) and a
16-client load test, with the server's memory before and after; writes benchmarks/RESULTS_server.md.

The scene is a 2e5-Gaussian bundle sampled on the surfaces of the synthetic garage ``scene1`` with
the 640x480 AVM rig (tests/sim_fixtures.py), served by a separate server process on 127.0.0.1.
Bounded: ``--requests`` per latency case and ``--duration`` seconds of load.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from parksim.bench.procs import rss_mib, serve_bundle  # noqa: E402
from sim_fixtures import make_bundle  # noqa: E402


def _pose(rng: np.random.Generator) -> str:
    return f"{rng.uniform(8, 40):.3f},{rng.uniform(-0.5, 0.5):.3f},{rng.uniform(-0.3, 0.3):.4f}"


def _latency(client: httpx.Client, params: dict[str, str], n: int, seed: int) -> dict[str, float]:
    """p50/p95/p99 (ms) of ``n`` sequential GET /render at random aisle poses."""
    rng = np.random.default_rng(seed)
    times = []
    for _ in range(n):
        start = time.perf_counter()
        r = client.get("/render", params={**params, "pose": _pose(rng)})
        r.raise_for_status()
        times.append((time.perf_counter() - start) * 1000)
    p50, p95, p99 = np.percentile(times, [50, 95, 99])
    return {"n": n, "p50": p50, "p95": p95, "p99": p99, "mean": float(np.mean(times))}


def load(base: str, params: dict[str, str], clients: int, duration: float) -> dict[str, Any]:
    """``clients`` threads sending GET /render with ``params`` for ``duration`` s, a 503 retried after its
    Retry-After; latency is from a render's first try to its 200 (retries included), as a client sees it.
    Shared with bench_server_ray.py, so both measure load the same way."""
    latencies: list[float] = []
    counts = {"busy_503": 0, "errors": 0}
    lock = threading.Lock()
    stop = time.monotonic() + duration

    def worker(i: int) -> None:
        rng = np.random.default_rng(100 + i)
        with httpx.Client(base_url=base, timeout=300) as c:
            while time.monotonic() < stop:
                first, query = time.perf_counter(), {**params, "pose": _pose(rng)}
                while time.monotonic() < stop:
                    try:
                        r = c.get("/render", params=query)
                    except httpx.HTTPError:
                        r = None
                    with lock:
                        if r is not None and r.status_code == 200:
                            latencies.append(time.perf_counter() - first)
                            break
                        counts["busy_503" if r is not None and r.status_code == 503 else "errors"] += 1
                    time.sleep(float(r.headers.get("retry-after", 1)) if r is not None else 1.0)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(clients)]
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    seconds = time.perf_counter() - start
    p50, p99 = np.percentile(latencies, [50, 99]) * 1000 if latencies else (float("nan"),) * 2
    return {"ok": len(latencies), **counts, "seconds": seconds, "throughput": len(latencies) / seconds,
            "p50": p50, "p99": p99}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--requests", type=int, default=20, help="requests per latency case")
    ap.add_argument("--clients", type=int, default=16)
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of load")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "RESULTS_server.md")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_bundle(Path(tmp) / "scene1", preset="scene1", n=args.gaussians, size=(640, 480))
        with serve_bundle(bundle, startup_s=300) as server, httpx.Client(base_url=server.base, timeout=300) as client:
            mem_start = rss_mib(server.pid)
            cases = {"4 views + BEV": {"bev": "on"}, "one view (front)": {"cameras": "front"},
                     "BEV only": {"cameras": "", "bev": "on"}}
            for params in cases.values():      # warm-up: JIT compilation and the per-scale IPM grids
                client.get("/render", params={**params, "pose": "20,0,0"}).raise_for_status()
            mem_before = rss_mib(server.pid)
            latency = {name: _latency(client, p, args.requests, i) for i, (name, p) in enumerate(cases.items())}
            load_result = load(server.base, {"bev": "on"}, args.clients, args.duration)
            mem_after = rss_mib(server.pid)
            metrics = client.get("/metrics").text
    _write(args, latency, load_result, (mem_start, mem_before, mem_after), metrics)


def _write(args: argparse.Namespace, latency: dict, load: dict, mem: tuple[float, float, float], metrics: str) -> None:
    stage = {line.split("{")[1].split('"')[1]: float(line.split()[-1]) for line in metrics.splitlines()
             if line.startswith("parksim_render_stage_seconds_sum")}
    count = {line.split("{")[1].split('"')[1]: float(line.split()[-1]) for line in metrics.splitlines()
             if line.startswith("parksim_render_stage_seconds_count")}
    lines = [
        "# Simulator server benchmark (loopback)", "",
        f"- command: `python benchmarks/bench_server.py --gaussians {args.gaussians} --requests {args.requests} "
        f"--clients {args.clients} --duration {args.duration:g}`",
        f"- machine: {platform.node()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores "
        f"(shared, loadavg at end {os.getloadavg()[0]:.1f}), CPU rasterizer (numba), server: 1 render thread, "
        "queue 8",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- scene: {args.gaussians} Gaussians on the surfaces of synthetic garage scene1, rig 4 x 640x480 "
        "fisheye, BEV 600x600", "",
        "## GET /render latency, sequential (ms)", "",
        "| request | n | p50 | p95 | p99 | mean |", "| --- | --- | --- | --- | --- | --- |"]
    for name, r in latency.items():
        lines.append(f"| {name} | {r['n']} | {r['p50']:.0f} | {r['p95']:.0f} | {r['p99']:.0f} | {r['mean']:.0f} |")
    lines += ["", f"## Load: {args.clients} concurrent clients, 4 views + BEV, {load['seconds']:.0f} s", "",
              f"- successful renders: {load['ok']} ({load['throughput']:.2f} /s)",
              f"- 503 (queue full, retried after Retry-After): {load['busy_503']}",
              f"- errors (other non-200 or transport): {load['errors']}", "",
              "## Server render time split over the whole run (mean ms per job, from /metrics)", ""]
    lines += [f"- {k}: {1000 * stage[k] / max(count[k], 1):.1f} ms over {int(count[k])} jobs" for k in sorted(stage)]
    lines += ["", "## Server memory (RSS, MiB)", "",
              f"- after loading the scene: {mem[0]:.0f}", f"- after warm-up (before the load test): {mem[1]:.0f}",
              f"- after the load test: {mem[2]:.0f}", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
