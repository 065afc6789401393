"""Single-process ``parksim serve`` against Ray Serve (1 and 2 replicas, serve.batch on and off) in one run: renders/s
and p50/p99 latency at 16 concurrent clients, the CPU time and memory of every process involved, and what idle Ray
and Serve cost; writes benchmarks/RESULTS_ray_serve.md.

The scene is the one of bench_server.py: a 2e5-Gaussian bundle on the surfaces of synthetic garage ``scene1``, 4 x
640x480 fisheye views and the 600x600 BEV at scale 1. Every configuration gets the same requests (each client's
poses come from its own seed) for ``--duration`` seconds. Ray runs in this process as ``parksim serve --ray`` runs it
(``parksim.server.ray_serve``: local instance, no dashboard, Serve's proxy on 127.0.0.1).
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import datetime
import logging
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import ray  # noqa: E402
from bench_server import load  # noqa: E402  (the same load loop as the single-process benchmark)
from fastapi import FastAPI  # noqa: E402
from ray import serve  # noqa: E402

from parksim.bench.procs import free_port, rss_mib, serve_bundle  # noqa: E402
from parksim.server import Settings  # noqa: E402
from parksim.server.ray_serve import APP_NAME, QUIET, Scaling, SimReplica, application  # noqa: E402
from sim_fixtures import make_bundle  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")
PARAMS = {"bev": "on"}   # four views + BEV at the default scale (1)


# --- processes, from /proc ---------------------------------------------------------------------------------------

def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError):
                continue
            kids.setdefault(ppid, []).append(int(entry.name))
    return kids


def tree(pid: int) -> list[int]:
    """``pid``'s descendants (not ``pid`` itself)."""
    kids, out, todo = _children(), [], [pid]
    while todo:
        for child in kids.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of ``pid`` so far (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / TICK


def name(pid: int) -> str:
    """What ``pid`` runs: its program, or the script for a Python process (Ray's workers retitle themselves)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
    except OSError:
        return "?"
    scripts = [a for a in argv[1:] if a.endswith(".py")] if Path(argv[0]).name.startswith("python") else []
    return Path(scripts[0] if scripts else argv[0]).name


def rss(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        try:
            total += rss_mib(pid)
        except (OSError, RuntimeError):
            continue
    return total


class CpuMeter:
    """CPU seconds ``pids`` spent between ``start()`` and ``stop()``, split by ``group(pid)``."""

    def __init__(self, pids: list[int], group: Callable[[int], str]) -> None:
        self.pids, self.group = pids, group

    def __enter__(self) -> CpuMeter:
        self.before = {p: cpu_s(p) for p in self.pids}
        self.wall = time.perf_counter()
        return self

    def __exit__(self, *_: object) -> None:
        self.wall = time.perf_counter() - self.wall
        self.spent: dict[str, float] = {}
        for p, before in self.before.items():
            key = self.group(p)
            self.spent[key] = self.spent.get(key, 0.0) + max(cpu_s(p) - before, 0.0)


# --- load ----------------------------------------------------------------------------------------------------------

def warm(base: str, n: int) -> None:
    """Two rounds of ``n`` concurrent renders, so every replica has loaded its kernels and per-scale grids."""
    with concurrent.futures.ThreadPoolExecutor(n) as pool, httpx.Client(base_url=base, timeout=600) as c:
        for _ in range(2):
            for r in pool.map(lambda i: c.get("/render", params={**PARAMS, "pose": f"{20 + i},0,0"}), range(n)):
                r.raise_for_status()


# --- serve.batch: the variant under test ---------------------------------------------------------------------------

class _BatchExecutor:
    """Stands in for a replica's render-pool executor: the jobs submitted while a batch renders go to its render
    thread together, as one task (``serve.batch``), rendered back to back (the renderer has no multi-pose kernel)."""

    def __init__(self, executor: concurrent.futures.ThreadPoolExecutor) -> None:
        self.executor = executor

    @serve.batch(max_batch_size=8, batch_wait_timeout_s=0.005)
    async def _together(self, fns: list[Callable[[], Any]]) -> list[tuple[bool, Any]]:
        def run_all() -> list[tuple[bool, Any]]:
            out = []
            for fn in fns:
                try:
                    out.append((True, fn()))
                except Exception as e:   # handed back to that job's own request
                    out.append((False, e))
            return out

        return await asyncio.wrap_future(self.executor.submit(run_all))

    def submit(self, fn: Callable[[], Any]) -> concurrent.futures.Future:
        future: concurrent.futures.Future = concurrent.futures.Future()

        def settle(task: asyncio.Task) -> None:
            if task.exception() is not None:
                future.set_exception(task.exception())
                return
            ok, value = task.result()
            future.set_result(value) if ok else future.set_exception(value)

        asyncio.ensure_future(self._together(fn)).add_done_callback(settle)
        return future


class BatchedReplica(SimReplica):
    """``SimReplica`` whose render pool batches concurrent jobs (the pool's own queueing and limits unchanged)."""

    def __serve_build_asgi_app__(self) -> FastAPI:
        app = super().__serve_build_asgi_app__()
        pool = app.state.pool
        pool._executor = _BatchExecutor(pool._executor)
        return app


# --- configurations ------------------------------------------------------------------------------------------------

def deploy(scenes: Path, scaling: Scaling, batched: bool) -> None:
    """``SimReplica`` as ``parksim serve --ray`` deploys it, or the batching variant with the same options."""
    settings = Settings()
    app = (serve.deployment(name="SimReplica")(BatchedReplica).options(**scaling.options(settings)).bind(
        str(scenes.resolve()), settings) if batched else application(scenes, settings, scaling))
    serve.run(app, name=APP_NAME, route_prefix="/", logging_config=QUIET)


def replicas() -> list[int]:
    return [p for p in tree(os.getpid()) if name(p).startswith("ray::ServeReplica")]


def ray_group(pid: int) -> str:
    n = name(pid)
    return "replicas" if n.startswith("ray::ServeReplica") else "proxy" if n.startswith("ray::ProxyActor") else "ray"


def measure_ray(base: str, label: str, args: argparse.Namespace, n: int) -> dict[str, Any]:
    warm(base, 2 * n)
    with CpuMeter(tree(os.getpid()) + [os.getpid()], lambda p: "client" if p == os.getpid() else ray_group(p)) as m:
        result = load(base, PARAMS, args.clients, args.duration)
    return {"label": label, **result, "cpu": m.spent, "wall": m.wall, "rss_replicas": rss(replicas()),
            "rss_ray": rss([p for p in tree(os.getpid()) if ray_group(p) != "replicas"])}


def idle_ray(seconds: float) -> dict[str, Any]:
    """RSS (MiB) and CPU seconds over ``seconds`` of Ray + Serve with no app deployed, per process."""
    pids = tree(os.getpid())
    with CpuMeter(pids, name) as m:
        time.sleep(seconds)
    by_name: dict[str, float] = {}
    for p in pids:
        by_name[name(p)] = by_name.get(name(p), 0.0) + rss([p])
    return {"seconds": m.wall, "cpu": m.spent, "rss": by_name, "driver_rss": rss_mib()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--clients", type=int, default=16)
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of load per configuration")
    ap.add_argument("--idle", type=float, default=10.0, help="seconds of idle Ray + Serve measured")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "RESULTS_ray_serve.md")
    args = ap.parse_args()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_bundle(Path(tmp) / "scenes" / "scene1", preset="scene1", n=args.gaussians, size=(640, 480))
        with serve_bundle(bundle, startup_s=600) as server:
            warm(server.base, 2)
            with CpuMeter([server.pid, os.getpid()], lambda p: "client" if p == os.getpid() else "server") as m:
                result = load(server.base, PARAMS, args.clients, args.duration)
            runs.append({"label": "single process (parksim serve)", **result, "cpu": m.spent, "wall": m.wall,
                         "rss_replicas": rss_mib(server.pid), "rss_ray": 0.0})
        port = free_port()
        logging.getLogger("ray.serve").setLevel(logging.WARNING)
        ray.init(num_cpus=os.cpu_count() or 1, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
        try:
            serve.start(http_options={"host": "127.0.0.1", "port": port}, logging_config=QUIET)
            idle = idle_ray(args.idle)
            base = f"http://127.0.0.1:{port}"
            cpus = os.cpu_count() or 1
            for label, scaling, batched in [
                    (f"Ray Serve, 1 replica x {cpus} CPUs", Scaling(1, None, cpus), False),
                    ("Ray Serve, 2 replicas x 1 CPU", Scaling(2, None, 1), False),
                    ("Ray Serve, 2 replicas x 1 CPU, serve.batch", Scaling(2, None, 1), True),
                    (f"Ray Serve, 1 replica x {cpus} CPUs, serve.batch", Scaling(1, None, cpus), True)]:
                deploy(bundle.parent, scaling, batched)
                runs.append(measure_ray(base, label, args, scaling.replicas))
                serve.delete(APP_NAME)
        finally:
            serve.shutdown()
            ray.shutdown()
    write(args, runs, idle)


def write(args: argparse.Namespace, runs: list[dict[str, Any]], idle: dict[str, Any]) -> None:
    cpu_model = next((line.split(":", 1)[1].strip() for line in subprocess.run(
        ["lscpu"], capture_output=True, text=True).stdout.splitlines() if line.startswith("Model name")), "?")
    ref = runs[0]["throughput"]
    lines = [
        "# parksim serve: single process against Ray Serve (loopback)", "",
        f"- command: `python benchmarks/bench_server_ray.py --gaussians {args.gaussians} --clients {args.clients} "
        f"--duration {args.duration:g} --idle {args.idle:g}`",
        f"- machine: {platform.node()}, {cpu_model}, {os.cpu_count()} cores, shared with other jobs (loadavg at end "
        f"{os.getloadavg()[0]:.1f}); Ray {ray.__version__}",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- scene: {args.gaussians} Gaussians on synthetic garage scene1, GET /render of 4 x 640x480 views + the "
        "600x600 BEV at scale 1, random aisle poses (the same per client in every configuration)",
        f"- load: {args.clients} clients for {args.duration:g} s per configuration; a 503 is retried after its "
        "Retry-After and latency runs from a render's first try to its 200", "",
        "## Throughput and latency", "",
        "| configuration | renders | renders/s | vs single | p50 ms | p99 ms | 503s | errors | CPU s: server side "
        "(replicas / proxy / ray) | CPU s per render | client CPU s | RSS MiB: replicas / Ray + Serve |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in runs:
        server_cpu = {k: v for k, v in r["cpu"].items() if k != "client"}
        total = sum(server_cpu.values())
        split = " / ".join(f"{server_cpu.get(k, 0):.0f}" for k in ("replicas", "proxy", "ray")) \
            if "replicas" in server_cpu else f"{total:.0f}"
        lines.append(f"| {r['label']} | {r['ok']} | {r['throughput']:.2f} | {r['throughput'] / ref:.2f} | "
                     f"{r['p50']:.0f} | {r['p99']:.0f} | {r['busy_503']} | {r['errors']} | {total:.0f} ({split}) | "
                     f"{total / max(r['ok'], 1):.2f} | {r['cpu'].get('client', 0):.0f} | "
                     f"{r['rss_replicas']:.0f} / {r['rss_ray']:.0f} |")
    walls = ", ".join(f"{r['wall']:.0f} s" for r in runs)
    lines += ["", f"Wall time per configuration: {walls}.", "",
              f"## Idle Ray + Serve (no app deployed), {idle['seconds']:.0f} s", "",
              "| process | RSS MiB | CPU s |", "| --- | --- | --- |"]
    for proc, mib in sorted(idle["rss"].items(), key=lambda kv: -kv[1]):
        if mib:
            lines.append(f"| {proc[:60]} | {mib:.0f} | {idle['cpu'].get(proc, 0):.2f} |")
    lines += [f"| **total** | **{sum(idle['rss'].values()):.0f}** | **{sum(idle['cpu'].values()):.2f}** |",
              f"| (this benchmark process: the Ray driver, as `parksim serve --ray` is, plus the load client) | "
              f"{idle['driver_rss']:.0f} | |", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
