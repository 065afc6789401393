"""``parksim bench server``: ``parksim serve`` on loopback: GET /render latency (4 views + BEV, one view, BEV only),
a load test of concurrent clients, the server's render-time split from /metrics and its memory.

The scene is ``--gaussians`` Gaussians sampled on the surfaces of synth scene1's garage with its 640x480 rig and
600x600 BEV (``parksim.bench.serving.garage_bundle``; the tiny garage under --quick), or ``--bundle``; the server is
a separate process with its default settings (1 render thread, queue 8) on ``--device`` (on CUDA the targets say "on
CUDA" and the GPU issue's goals apply). Bounded: ``--requests`` per latency case and ``--duration`` seconds of
load.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["ServerSuite", "ServerOptions", "CASES", "GOAL_MS", "CUDA_GOAL_MS", "CUDA_GOAL_RENDERS_S"]

CASES: dict[str, dict[str, str]] = {"4 views + BEV": {"bev": "on"}, "one view (front)": {"cameras": "front"},
                                    "BEV only": {"cameras": "", "bev": "on"}}
"""The latency cases: name -> GET /render query besides the pose."""
GOAL_MS = 250.0
"""p50 latency goal of the 4 views + BEV request (ms)."""
CUDA_GOAL_MS = 15.0
"""... served from one GPU (``--device cuda``)."""
CUDA_GOAL_RENDERS_S = 150.0
"""Renders/s goal of the load test served from one GPU (16 clients)."""


@dataclass(frozen=True)
class ServerOptions:
    """Options of ``parksim bench server``."""

    bundle: Path | None = field(default=None, metadata={
        "help": "bundle to serve (default: --gaussians Gaussians on the surfaces of synth scene1 at 640x480, "
                "made under --work; the tiny garage under --quick)"})
    gaussians: int = field(default=200_000, metadata={"help": "Gaussians of the scene made without --bundle", "low": 1,
                                                       "quick": 2_000})
    requests: int = field(default=20, metadata={"help": "sequential requests per latency case", "low": 1,
                                                "quick": 3})
    clients: int = field(default=16, metadata={"help": "concurrent clients of the load test", "low": 1, "quick": 4})
    duration: float = field(default=60.0, metadata={"help": "seconds of load", "low": 0.1, "quick": 2.0})
    device: str = field(default="auto", metadata={
        "help": "the server's --device: auto, cpu or cuda[:N] (resolved here; on CUDA the targets say so and the "
                "GPU goals apply)"})


def _stage_means(metrics: str) -> dict[str, dict[str, float]]:
    """Mean ms per job and job count of each render stage, from the server's Prometheus text."""
    sums: dict[str, float] = {}
    counts: dict[str, float] = {}
    for line in metrics.splitlines():
        for prefix, into in (("parksim_render_stage_seconds_sum", sums), ("parksim_render_stage_seconds_count",
                                                                          counts)):
            if line.startswith(prefix + "{"):
                into[line.split('"')[1]] = float(line.split()[-1])
    return {k: {"mean_ms": 1000 * sums[k] / max(counts.get(k, 0.0), 1.0), "jobs": counts.get(k, 0.0)}
            for k in sorted(sums)}


class ServerSuite(Suite):
    """GET /render latency, a concurrent load and memory of ``parksim serve``."""

    name = "server"
    help = "parksim serve on loopback: GET /render p50/p95 latency, load test, memory"
    description = ("Serve a bundle with `parksim serve` in a subprocess (default settings: 1 render thread, queue 8) "
                   "and time --requests sequential GET /render at random aisle poses for 4 views + BEV, one view and "
                   "BEV only (after one warm-up request each), then --clients concurrent clients for --duration s "
                   "(a 503 retried after its Retry-After). Figures: p50 and p95 latency of each case (cpu: the same "
                   f"percentile of the server's CPU time per request), goal <= {GOAL_MS:g} ms p50 for 4 views + BEV "
                   f"({CUDA_GOAL_MS:g} ms on --device cuda); renders/s under load (goal on CUDA >= "
                   f"{CUDA_GOAL_RENDERS_S:g}); server RSS. Data: every latency, the load test, the render stage split "
                   "from /metrics, RSS after loading, after warm-up and after the load.")
    Options = ServerOptions

    def run(self, options: ServerOptions, context: Context) -> Outcome:
        """Serve, warm up, time the three cases, load, read /metrics and RSS."""
        import httpx

        from ...device import resolve_device
        from ..procs import rss_mib, serve_bundle
        from ..serving import client_load, latency, scene_bundle, warm

        device = resolve_device(options.device)   # a bad name or a missing GPU: refused before any work
        cuda = device.type == "cuda"
        goal_ms = CUDA_GOAL_MS if cuda else GOAL_MS
        served = scene_bundle(options.bundle, context, "scene1", (640, 480), options.gaussians)
        scene, length = served.label + (", on CUDA" if cuda else ""), served.length
        with (serve_bundle(served.bundle, ["--device", str(device)]) as server,
              httpx.Client(base_url=server.base, timeout=300) as client):
            mem = {"loaded": rss_mib(server.pid)}
            for params in CASES.values():   # warm-up: JIT compilation and the per-scale IPM grids
                warm(server.base, params)
            mem["warm"] = rss_mib(server.pid)
            cases = {name: latency(client, params, options.requests, length, context.seed + i, server.pid)
                     for i, (name, params) in enumerate(CASES.items())}
            load = client_load(server.base, CASES["4 views + BEV"], options.clients, options.duration, length)
            mem["after_load"] = rss_mib(server.pid)
            stages = _stage_means(client.get("/metrics").text)
        figures = [Figure(f"GET /render {name}, {scene}: p{q} latency", cases[name][f"p{q}"], "ms",
                          cpu=cases[name][f"cpu_p{q}"],
                          goal=f"<= {goal_ms:g} ms" if name == "4 views + BEV" and q == 50 else None)
                   for name in CASES for q in (50, 95)]
        figures += [Figure(f"GET /render 4 views + BEV, {scene}: renders/s at {options.clients} clients",
                           load["throughput"], "renders/s", better="higher",
                           goal=f">= {CUDA_GOAL_RENDERS_S:g} renders/s" if cuda else None),
                    Figure(f"parksim serve RSS after the load test, {scene}", mem["after_load"], "MiB")]
        data = {"bundle": str(served.bundle), "scene": scene, "device": str(device), "latency": cases, "load": load,
                "stages": stages, "rss_mib": mem}
        return Outcome(figures, data)
