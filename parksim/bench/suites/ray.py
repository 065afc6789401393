"""``parksim bench ray``: single-process ``parksim serve`` (plain uvicorn) against Ray Serve in one run.

Renders/s and p50/p99 latency at ``--clients`` concurrent clients (GET /render of every view + the BEV at scale 1,
a 503 retried after its Retry-After), the CPU time and memory of every process involved, and what idle Ray and
Serve cost. Ray Serve runs as ``parksim serve --ray`` runs it (``parksim.server.ray_serve``: no dashboard, Serve's
proxy on 127.0.0.1) in the Ray instance of this process (``parksim.bench.procs.local_ray``), in 1 replica x
``--cpus`` CPUs and 2 replicas x 1 CPU, each with and without ``serve.batch`` (``parksim.bench.batched_replica``).
Every configuration gets the same requests (each client's poses come from its own seed) for ``--duration`` s.

The scene is ``--gaussians`` Gaussians on the surfaces of synth scene1's garage with its 640x480 rig and 600x600
BEV (the tiny garage under --quick), or ``--bundle``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["RaySuite", "RayOptions", "CONFIGS", "PARAMS"]

PARAMS = {"bev": "on"}
"""Every view + the BEV at the default scale (1)."""
CONFIGS: dict[str, tuple[int, int | None, bool]] = {"1xN": (1, None, False), "2x1": (2, 1, False),
                                                    "2x1-batch": (2, 1, True), "1xN-batch": (1, None, True)}
"""Ray Serve configurations: name -> (replicas, CPUs per replica (None: ``--cpus``), serve.batch)."""


@dataclass(frozen=True)
class RayOptions:
    """Options of ``parksim bench ray``."""

    bundle: Path | None = field(default=None, metadata={
        "help": "bundle to serve (default: --gaussians Gaussians on the surfaces of synth scene1 at 640x480, "
                "made under --work; the tiny garage under --quick)"})
    gaussians: int = field(default=200_000, metadata={"help": "Gaussians of the scene made without --bundle", "low": 1,
                                                       "quick": 2_000})
    clients: int = field(default=16, metadata={"help": "concurrent clients", "low": 1, "quick": 4})
    duration: float = field(default=30.0, metadata={"help": "seconds of load per configuration", "low": 0.1,
                                                    "quick": 1.0})
    idle: float = field(default=10.0, metadata={"help": "seconds of idle Ray + Serve measured", "low": 0,
                                                "quick": 0.5})
    cpus: int = field(default_factory=lambda: os.cpu_count() or 1, metadata={
        "help": "Ray CPUs, and the CPUs of the 1-replica configurations", "low": 1, "quick": 2})
    configs: list[str] = field(default_factory=lambda: list(CONFIGS), metadata={
        "help": f"Ray Serve configurations to measure, of {', '.join(CONFIGS)} (replicas x CPUs, N = --cpus)",
        "quick": ["1xN"]})

    def __post_init__(self) -> None:
        unknown = [c for c in self.configs if c not in CONFIGS]
        if unknown or not self.configs:
            raise ValueError(f"--configs: unknown {', '.join(unknown)}; choose from {', '.join(CONFIGS)}")


def _label(name: str, cpus: int) -> str:
    replicas, per, batched = CONFIGS[name]
    per = per or cpus
    return (f"Ray Serve, {replicas} replica{'s' * (replicas > 1)} x {per} CPU{'s' * (per > 1)}"
            + (", serve.batch" if batched else ""))


def _ray_group(pid: int) -> str:
    from ..procs import process_name

    name = process_name(pid)
    return "replicas" if name.startswith("ray::ServeReplica") else "proxy" if name.startswith("ray::ProxyActor") \
        else "ray"


def _deploy(bundle: Path, name: str, cpus: int) -> None:
    """The configuration ``name``: ``SimReplica`` as ``parksim serve --ray`` deploys it, or the batching variant
    with the same options."""
    from ray import serve

    from ...server import Settings
    from ...server.ray_serve import APP_NAME, QUIET, Scaling, application

    replicas, per, batched = CONFIGS[name]
    settings, scaling = Settings(), Scaling(replicas, None, per or cpus)
    if batched:
        from ..batched_replica import BatchedReplica

        app = serve.deployment(name="SimReplica")(BatchedReplica).options(**scaling.options(settings)).bind(
            str(bundle.resolve()), settings)
    else:
        app = application(bundle, settings, scaling)
    serve.run(app, name=APP_NAME, route_prefix="/", logging_config=QUIET)


def _measure_ray(base: str, replicas: int, options: RayOptions, length: float) -> dict[str, Any]:
    """Warm every replica, then the load; CPU of this process (the client) and Ray's processes by group."""
    from ..procs import CpuMeter, descendants, total_rss_mib
    from ..serving import client_load, warm

    me = os.getpid()
    warm(base, PARAMS, 2 * replicas, rounds=2)
    with CpuMeter([me, *descendants(me)], lambda p: "client" if p == me else _ray_group(p)) as meter:
        result = client_load(base, PARAMS, options.clients, options.duration, length)
    pids = descendants(me)
    serving = [p for p in pids if _ray_group(p) == "replicas"]
    return {**result, "cpu": meter.spent, "wall": meter.wall, "rss_replicas": total_rss_mib(serving),
            "rss_ray": total_rss_mib(set(pids) - set(serving))}


def _idle_ray(seconds: float) -> dict[str, Any]:
    """RSS (MiB) and CPU seconds over ``seconds`` of Ray + Serve with no app deployed, per process name."""
    import time

    from ..procs import CpuMeter, descendants, process_name, rss_mib, total_rss_mib

    pids = descendants(os.getpid())
    with CpuMeter(pids, process_name) as meter:
        time.sleep(seconds)
    by_name: dict[str, float] = {}
    for p in pids:
        by_name[process_name(p)] = by_name.get(process_name(p), 0.0) + total_rss_mib([p])
    return {"seconds": meter.wall, "cpu": meter.spent, "rss": by_name, "driver_rss": rss_mib()}


class RaySuite(Suite):
    """Ray Serve configurations against the single-process server, same requests, same run."""

    name = "ray"
    help = "Ray Serve (1 and 2 replicas, serve.batch on/off) against single-process parksim serve"
    description = ("Single-process `parksim serve` (uvicorn, subprocess), then Ray Serve in this process's Ray "
                   "instance (started with --cpus CPUs and a small object store unless one is running; shut down "
                   "after) in each of --configs; --clients concurrent clients for --duration s each on GET /render of "
                   "every view + the BEV. Figures per Ray configuration: renders/s, p99 latency and server-side CPU "
                   "per render (replicas, proxy and Ray daemons), each against the single process measured in the "
                   "same run; idle Ray + Serve RSS and CPU. Data: every configuration's load result, CPU by process "
                   "group, RSS, wall time; idle Ray + Serve per process.")
    Options = RayOptions

    def run(self, options: RayOptions, context: Context) -> Outcome:
        """Single process first, then Ray: idle, then every configuration in turn."""
        import logging

        from ray import serve

        from ...server.ray_serve import APP_NAME, QUIET
        from ..procs import CpuMeter, free_port, local_ray, rss_mib, serve_bundle
        from ..serving import client_load, scene_bundle, warm

        served = scene_bundle(options.bundle, context, "scene1", (640, 480), options.gaussians)
        bundle, scene, length = served.bundle, served.label, served.length
        me = os.getpid()
        with serve_bundle(bundle, startup_s=600) as server:
            warm(server.base, PARAMS, 2, rounds=2)
            with CpuMeter([server.pid, me], lambda p: "client" if p == me else "server") as meter:
                result = client_load(server.base, PARAMS, options.clients, options.duration, length)
            single = {**result, "cpu": meter.spent, "wall": meter.wall, "rss_replicas": rss_mib(server.pid),
                      "rss_ray": 0.0}
        runs: dict[str, dict[str, Any]] = {}
        logging.getLogger("ray.serve").setLevel(logging.WARNING)
        with local_ray(options.cpus):
            port = free_port()
            try:
                serve.start(http_options={"host": "127.0.0.1", "port": port}, logging_config=QUIET)
                idle = _idle_ray(options.idle)
                for name in options.configs:
                    _deploy(bundle, name, options.cpus)
                    runs[name] = _measure_ray(f"http://127.0.0.1:{port}", CONFIGS[name][0], options, length)
                    serve.delete(APP_NAME)
            finally:
                serve.shutdown()
        return Outcome(_figures(single, runs, idle, options, scene),
                       {"bundle": str(bundle), "scene": scene, "single": single,
                        "ray": {_label(k, options.cpus): v for k, v in runs.items()}, "idle": idle})


def _server_cpu_ms(run: dict[str, Any]) -> float:
    """Server-side CPU ms per render answered (everything but the client)."""
    return 1000 * sum(v for k, v in run["cpu"].items() if k != "client") / max(run["ok"], 1)


def _figures(single: dict[str, Any], runs: dict[str, dict[str, Any]], idle: dict[str, Any], options: RayOptions,
             scene: str) -> list[Figure]:
    """Per Ray configuration: renders/s, p99 and CPU per render against the single process; idle Ray's cost."""
    reference = "parksim serve, single process"
    load = f"{options.clients} clients on GET /render every view + BEV, {scene}"
    figures = []
    for name, run in runs.items():
        label = _label(name, options.cpus)
        figures += [
            Figure(f"{label}: renders/s, {load}", run["throughput"], "renders/s", reference=single["throughput"],
                   reference_label=reference, better="higher"),
            Figure(f"{label}: p99 latency, {load}", run["p99"], "ms", reference=single["p99"],
                   reference_label=reference),
            Figure(f"{label}: server-side CPU per render, {load}", _server_cpu_ms(run), "ms",
                   reference=_server_cpu_ms(single), reference_label=reference)]
    seconds = max(idle["seconds"], 1e-9)
    figures += [Figure("idle Ray + Serve (no app deployed): RSS of its processes", sum(idle["rss"].values()), "MiB"),
                Figure("idle Ray + Serve (no app deployed): CPU", 100 * sum(idle["cpu"].values()) / seconds,
                       "% of a core")]
    return figures
