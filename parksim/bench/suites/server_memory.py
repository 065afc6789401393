"""``parksim bench server-memory``: the server's memory under clients that never read.

``--clients`` raw loopback sockets each send the largest request the server allows (``POST /render``: all cameras,
depth and BEV, as many poses and as high a scale as the largest reply permits) and never call recv. The reply
budget must keep the server's peak RSS under

    bound = RSS after warm-up + (peak RSS of one such request read normally - RSS after warm-up) + reply budget

(one render's working set at a time, as the pool has one render thread, plus the unsent replies the budget admits).
A control run gives the server a budget as large as all the replies, the unbounded case for these clients.

The scene is ``--gaussians`` Gaussians on the surfaces of synth scene1's garage with its 640x480 rig (the tiny
garage under --quick), or ``--bundle``, served by ``parksim serve`` in a subprocess. Peak RSS is the kernel's VmHWM
of the server, reset (``/proc/PID/clear_refs``) before each phase.
"""

from __future__ import annotations

import json
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["ServerMemorySuite", "ServerMemoryOptions", "Request", "largest_request"]

MIB = 2**20


@dataclass(frozen=True)
class ServerMemoryOptions:
    """Options of ``parksim bench server-memory``."""

    bundle: Path | None = field(default=None, metadata={
        "help": "bundle to serve (default: --gaussians Gaussians on the surfaces of synth scene1 at 640x480, "
                "made under --work; the tiny garage under --quick)"})
    gaussians: int = field(default=50_000, metadata={"help": "Gaussians of the scene made without --bundle", "low": 1,
                                                      "quick": 2_000})
    hold: float = field(default=5.0, metadata={"help": "seconds the never-reading clients are held", "low": 0,
                                               "quick": 0.5})
    clients: int = field(default=8, metadata={"help": "never-reading clients", "low": 1, "quick": 4})
    max_reply_mib: float = field(default=64.0, metadata={
        "help": "the server's largest reply (as parksim serve --max-reply-mib); keep it well above the "
                "kernel's socket buffers (a few MiB), or they take whole replies", "low": 1, "quick": 8.0})
    reply_budget_mib: float = field(default=256.0, metadata={
        "help": "the server's reply budget of the bounded phase (as parksim serve --reply-budget-mib)",
        "low": 1, "quick": 16.0})

    def __post_init__(self) -> None:
        if self.reply_budget_mib < self.max_reply_mib:
            raise ValueError(f"--reply-budget-mib ({self.reply_budget_mib:g}) must be at least --max-reply-mib "
                             f"({self.max_reply_mib:g}), or the largest request could never be served")


@dataclass(frozen=True)
class Request:
    """The largest allowed request: ``poses`` poses at ``scale``, every camera with depth, and the BEV."""

    poses: int
    scale: float
    reply_bytes: int
    length: float

    def body(self) -> bytes:
        """The JSON body: poses every 3 m along the aisle from x = 8 m (wrapping 8 m before its end)."""
        span = max(self.length - 16.0, 1.0)
        poses = [[8.0 + (3.0 * i) % span, 0.2 * (i % 3), 0.1 * i] for i in range(self.poses)]
        return json.dumps({"poses": poses, "bev": True, "depth": True, "scale": self.scale}).encode()


def largest_request(sim: Any, settings: Any, length: float) -> Request:
    """The (poses, scale) on a 0.05 scale grid whose reply is largest within ``settings.max_reply_bytes``.

    Args:
        sim: the scene's ``LocalSim`` (it counts reply bytes as the server does).
        settings: the server's ``Settings``.
        length: garage length (m), for the poses.

    Returns:
        The request.
    """
    best = Request(0, 0.0, 0, length)
    for step in range(int(settings.max_scale / 0.05), int(settings.min_scale / 0.05) - 1, -1):
        scale = round(step * 0.05, 2)
        sizes = [(n, sim.reply_bytes(n, sim.cameras, True, scale, True)) for n in range(1, settings.max_batch + 1)]
        n, size = max(((n, s) for n, s in sizes if s <= settings.max_reply_bytes), key=lambda t: t[1], default=(0, 0))
        if size > best.reply_bytes:
            best = Request(n, scale, size, length)
    return best


def _never_reading_client(base: str, body: bytes) -> socket.socket:
    """A socket that sends ``POST /render`` and never reads (small receive buffer: nothing drains the reply)."""
    host, port = base.removeprefix("http://").split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    sock.sendall(b"POST /render HTTP/1.1\r\nHost: %s\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n"
                 % (host.encode(), len(body)) + body)
    return sock


def run_phase(bundle: Path, request: Request, budget_mib: float, options: ServerMemoryOptions) -> dict[str, float]:
    """Warm up, one largest request read normally, then the never-reading clients held ``options.hold`` s.

    Args:
        bundle: the bundle served.
        request: the largest request.
        budget_mib: the server's reply budget in this phase.
        options: the suite's options (clients, hold, largest reply).

    Returns:
        RSS figures in MiB, the clients held and refused, the reply bytes held, and whether closing the clients
        released the budget (1.0) or not (0.0).
    """
    import httpx

    from ..procs import reset_peak_rss, rss_mib, serve_bundle, status_mib

    flags = ["--max-reply-mib", f"{options.max_reply_mib:g}", "--reply-budget-mib", f"{budget_mib:g}"]
    with serve_bundle(bundle, flags) as server, httpx.Client(base_url=server.base, timeout=600) as client:
        pid = server.pid
        out = {"rss_loaded": rss_mib(pid)}
        client.get("/render", params={"pose": "20,0,0", "scale": "0.25", "bev": "on"}).raise_for_status()
        out["rss_warm"] = rss_mib(pid)
        reset_peak_rss(pid)
        start = time.perf_counter()
        r = client.post("/render", content=request.body(), headers={"content-type": "application/json"})
        r.raise_for_status()
        out["single_s"] = time.perf_counter() - start
        out["single_reply_mib"] = len(r.content) / MIB
        del r
        out["single_peak"] = status_mib(pid, "VmHWM")
        out["rss_before_clients"] = rss_mib(pid)
        reset_peak_rss(pid)
        socks = [_never_reading_client(server.base, request.body()) for _ in range(options.clients)]
        try:
            deadline = time.monotonic() + 1800
            while True:      # every client admitted (rendered, reply unsent) or refused
                health = client.get("/healthz").json()
                held = health["replies"]["in_flight_bytes"] // request.reply_bytes
                if health["pool"]["in_flight"] == 0 and held + health["replies"]["rejected"] == options.clients:
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError(f"clients not settled: {health}")
                time.sleep(0.2)
            out["settle_s"] = time.perf_counter() - start
            time.sleep(options.hold)
            health = client.get("/healthz").json()
            out["held_clients"] = health["replies"]["in_flight_bytes"] // request.reply_bytes
            out["refused_503"] = health["replies"]["rejected"]
            out["held_mib"] = health["replies"]["in_flight_bytes"] / MIB
            out["peak_with_clients"] = status_mib(pid, "VmHWM")
            out["rss_with_clients"] = rss_mib(pid)
        finally:
            for s in socks:
                s.close()
        deadline = time.monotonic() + 60
        while client.get("/healthz").json()["replies"]["in_flight_bytes"] and time.monotonic() < deadline:
            time.sleep(0.2)
        out["released"] = float(client.get("/healthz").json()["replies"]["in_flight_bytes"] == 0)
        out["rss_after_close"] = rss_mib(pid)
    return out


class ServerMemorySuite(Suite):
    """Peak server RSS under never-reading clients, against the bound the reply budget promises."""

    name = "server-memory"
    help = "server peak RSS under clients that never read, against the reply budget's bound"
    description = ("`parksim serve` in a subprocess; --clients raw sockets each send the largest allowed POST /render "
                   "(all cameras, depth and BEV, as many poses and as high a scale as --max-reply-mib permits) and "
                   "never read. Bound = RSS after warm-up + one such request's render working set + reply budget. "
                   "A control run has a budget holding every client's reply. Figures: peak RSS with the clients "
                   "(reference: the control run), headroom under the bound (goal >= 0 MiB). Data: every RSS, clients "
                   "held and refused, reply bytes held, whether closing the clients released the budget.")
    Options = ServerMemoryOptions

    def run(self, options: ServerMemoryOptions, context: Context) -> Outcome:
        """Find the largest request, then the bounded phase and the control phase, each on a fresh server."""
        from ...server import Settings
        from ...sim import LocalSim
        from ..serving import scene_bundle

        served = scene_bundle(options.bundle, context, "scene1", (640, 480), options.gaussians)
        bundle, scene = served.bundle, served.label
        settings = Settings(max_reply_bytes=int(options.max_reply_mib * MIB),
                            reply_budget_bytes=int(options.reply_budget_mib * MIB))
        request = largest_request(LocalSim.from_dir(bundle), settings, served.length)
        bounded = run_phase(bundle, request, options.reply_budget_mib, options)
        control_mib = options.clients * request.reply_bytes / MIB + 1
        control = run_phase(bundle, request, control_mib, options)
        bound = bounded["single_peak"] + options.reply_budget_mib   # warm + (single peak - warm) + budget
        condition = (f"{options.clients} never-reading clients of {request.reply_bytes / MIB:.1f} MiB replies, "
                     f"{scene}")
        figures = [
            Figure(f"parksim serve peak RSS, {condition}, reply budget {options.reply_budget_mib:g} MiB",
                   bounded["peak_with_clients"], "MiB", reference=control["peak_with_clients"],
                   reference_label=f"control: budget {control_mib:.0f} MiB (every reply)"),
            Figure(f"headroom of the peak RSS under the reply budget's bound, {condition}",
                   bound - bounded["peak_with_clients"], "MiB", goal=">= 0 MiB", better="higher")]
        data = {"bundle": str(bundle), "scene": scene, "request": {"poses": request.poses, "scale": request.scale,
                                                                   "reply_mib": request.reply_bytes / MIB},
                "budget_mib": options.reply_budget_mib, "control_budget_mib": control_mib, "bound_mib": bound,
                "bounded": bounded, "control": control}
        return Outcome(figures, data)
