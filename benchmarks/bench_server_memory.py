"""Server memory under clients that never read: 8 raw loopback sockets each send the largest request the server
allows (``POST /render``: all cameras, depth and BEV, as many poses and as high a scale as ``max_reply_bytes``
permits) and never call recv. The reply budget must keep the server's peak RSS under

    bound = RSS after warm-up + (peak RSS of one such request read normally - RSS after warm-up) + reply budget

(one render's working set at a time, as the pool has one render thread, plus the unsent replies the budget admits).
A control run gives the server a budget as large as all 8 replies, the unbounded case for these clients.

The scene is ``--gaussians`` surface samples of the synthetic garage scene1 on the 640x480 AVM rig
(tests/sim_fixtures.py), served by ``parksim serve`` in a subprocess. Peak RSS is the kernel's VmHWM of the
server, reset (``/proc/PID/clear_refs``) before each phase. Prints a Markdown section (``--append`` adds it to a
file).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from parksim.bench.common import load_average, meta_lines, metadata  # noqa: E402
from parksim.bench.procs import free_port, rss_mib  # noqa: E402
from parksim.server import Settings  # noqa: E402
from parksim.sim import LocalSim  # noqa: E402
from sim_fixtures import make_bundle  # noqa: E402

MIB = 2**20
CLIENTS = 8


def _status(pid: int, key: str) -> float:
    """A ``/proc/PID/status`` memory field in MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{key}:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {key} for pid {pid}")


def _reset_peak(pid: int) -> None:
    """Make VmHWM (peak RSS) start again from the current RSS."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


@dataclass(frozen=True)
class Request:
    """The largest allowed request: ``poses`` poses at ``scale``, every camera with depth, and the BEV."""

    poses: int
    scale: float
    reply_bytes: int

    def body(self) -> bytes:
        poses = [[8.0 + 3.0 * i, 0.2 * (i % 3), 0.1 * i] for i in range(self.poses)]
        return json.dumps({"poses": poses, "bev": True, "depth": True, "scale": self.scale}).encode()


def largest_request(sim: LocalSim, settings: Settings) -> Request:
    """The (poses, scale) on a 0.05 scale grid whose reply is largest within ``settings.max_reply_bytes``."""
    best = Request(0, 0.0, 0)
    for step in range(int(settings.max_scale / 0.05), int(settings.min_scale / 0.05) - 1, -1):
        scale = round(step * 0.05, 2)
        sizes = [(n, sim.reply_bytes(n, sim.cameras, True, scale, True)) for n in range(1, settings.max_batch + 1)]
        n, size = max(((n, s) for n, s in sizes if s <= settings.max_reply_bytes), key=lambda t: t[1], default=(0, 0))
        if size > best.reply_bytes:
            best = Request(n, scale, size)
    return best


@contextlib.contextmanager
def serve(bundle: Path, budget_mib: float) -> Iterator[tuple[str, int]]:
    """``parksim serve`` on a free loopback port with the default limits but ``budget_mib``; (base URL, pid)."""
    port = free_port()
    cmd = [sys.executable, "-m", "parksim.cli", "serve", "--scenes", str(bundle), "--port", str(port),
           "--reply-budget-mib", f"{budget_mib:g}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 300
        while True:
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{base}/healthz").status_code == 200:
                    break
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"parksim serve did not start (exit code {proc.poll()})")
            time.sleep(0.5)
        yield base, proc.pid
    finally:
        proc.terminate()
        proc.wait(30)


def _never_reading_client(base: str, body: bytes) -> socket.socket:
    """A socket that sends ``POST /render`` and never reads (small receive buffer: nothing drains the reply)."""
    host, port = base.removeprefix("http://").split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    sock.sendall(b"POST /render HTTP/1.1\r\nHost: %s\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n"
                 % (host.encode(), len(body)) + body)
    return sock


def run_phase(bundle: Path, request: Request, budget_mib: float, hold_s: float) -> dict[str, float]:
    """Warm up with one largest request read normally, then 8 clients that never read; RSS figures in MiB."""
    with serve(bundle, budget_mib) as (base, pid), httpx.Client(base_url=base, timeout=600) as client:
        out = {"rss_loaded": rss_mib(pid)}
        client.get("/render", params={"pose": "20,0,0", "scale": "0.25", "bev": "on"}).raise_for_status()
        out["rss_warm"] = rss_mib(pid)
        _reset_peak(pid)
        start = time.perf_counter()
        r = client.post("/render", content=request.body(), headers={"content-type": "application/json"})
        r.raise_for_status()
        out["single_s"] = time.perf_counter() - start
        out["single_reply_mib"] = len(r.content) / MIB
        del r
        out["single_peak"] = _status(pid, "VmHWM")
        out["rss_before_clients"] = rss_mib(pid)
        _reset_peak(pid)
        socks = [_never_reading_client(base, request.body()) for _ in range(CLIENTS)]
        try:
            deadline = time.monotonic() + 1800
            while True:      # every client admitted (rendered, reply unsent) or refused
                health = client.get("/healthz").json()
                held = health["replies"]["in_flight_bytes"] // request.reply_bytes
                if health["pool"]["in_flight"] == 0 and held + health["replies"]["rejected"] == CLIENTS:
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError(f"clients not settled: {health}")
                time.sleep(0.2)
            out["settle_s"] = time.perf_counter() - start
            time.sleep(hold_s)
            health = client.get("/healthz").json()
            out["held_clients"] = health["replies"]["in_flight_bytes"] // request.reply_bytes
            out["refused_503"] = health["replies"]["rejected"]
            out["held_mib"] = health["replies"]["in_flight_bytes"] / MIB
            out["peak_with_clients"] = _status(pid, "VmHWM")
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=50_000)
    ap.add_argument("--hold", type=float, default=5.0, help="seconds the never-reading clients are held")
    ap.add_argument("--append", type=Path, help="append the Markdown section to this file")
    args = ap.parse_args()
    command = (f"python benchmarks/bench_server_memory.py --gaussians {args.gaussians} --hold {args.hold:g}"
               + (f" --append {args.append}" if args.append else ""))
    meta = metadata(command)
    settings = Settings()
    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_bundle(Path(tmp) / "scene1", preset="scene1", n=args.gaussians, size=(640, 480))
        request = largest_request(LocalSim.from_dir(bundle), settings)
        budget_mib = settings.reply_budget_bytes / MIB
        bounded = run_phase(bundle, request, budget_mib, args.hold)
        control = run_phase(bundle, request, CLIENTS * request.reply_bytes / MIB + 1, args.hold)
    meta["load_end"] = load_average()
    lines = _markdown(meta, settings, request, bounded, control)
    print("\n".join(lines))
    if args.append:
        with args.append.open("a") as f:
            f.write("\n" + "\n".join(lines) + "\n")


def _markdown(meta: dict, settings: Settings, request: Request, bounded: dict, control: dict) -> list[str]:
    budget_mib = settings.reply_budget_bytes / MIB
    bound = bounded["rss_warm"] + (bounded["single_peak"] - bounded["rss_warm"]) + budget_mib
    ok = bounded["peak_with_clients"] <= bound
    cpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    model = next((ln.split(":", 1)[1].strip() for ln in cpu.splitlines() if ln.startswith("Model name")), "?")
    rows = [("", "budget = default", "control: budget = all 8 replies"),
            ("reply budget (MiB)", f"{budget_mib:.0f}", f"{CLIENTS * request.reply_bytes / MIB + 1:.0f}"),
            ("RSS after loading / after warm-up", f"{bounded['rss_loaded']:.0f} / {bounded['rss_warm']:.0f}",
             f"{control['rss_loaded']:.0f} / {control['rss_warm']:.0f}"),
            ("peak RSS of one largest request, read normally", f"{bounded['single_peak']:.0f}",
             f"{control['single_peak']:.0f}"),
            ("clients holding an unsent reply / answered 503", f"{bounded['held_clients']:.0f} / "
             f"{bounded['refused_503']:.0f}", f"{control['held_clients']:.0f} / {control['refused_503']:.0f}"),
            ("reply bytes held (MiB)", f"{bounded['held_mib']:.0f}", f"{control['held_mib']:.0f}"),
            ("**peak RSS with the 8 clients**", f"**{bounded['peak_with_clients']:.0f}**",
             f"{control['peak_with_clients']:.0f}"),
            ("RSS after the clients closed (budget released)", f"{bounded['rss_after_close']:.0f} "
             f"({'yes' if bounded['released'] else 'NO'})",
             f"{control['rss_after_close']:.0f} ({'yes' if control['released'] else 'NO'})")]
    table = [f"| {' | '.join(r)} |" for r in rows[:1]] + ["| --- | --- | --- |"] + [f"| {' | '.join(r)} |"
                                                                                     for r in rows[1:]]
    return ["## Server memory with clients that never read (`benchmarks/bench_server_memory.py`)", "",
            *meta_lines(meta), f"- CPU (lscpu): {model}, {os.cpu_count()} CPUs",
            f"- scene: {meta['command'].split('--gaussians ')[1].split()[0]} Gaussians on the surfaces of synthetic "
            "garage scene1, rig 4 x 640x480 fisheye, BEV 600x600; `parksim serve` with default limits "
            f"(max_reply_bytes {settings.max_reply_bytes / MIB:.0f} MiB, 1 render thread, queue 8)",
            f"- largest allowed request: POST /render, {request.poses} poses at scale {request.scale:g}, 4 cameras + "
            f"depth + BEV: {request.reply_bytes / MIB:.1f} MiB counted before rendering "
            f"({bounded['single_reply_mib']:.1f} MiB sent; {bounded['single_s']:.1f} s), sent by {CLIENTS} raw "
            "sockets on 127.0.0.1 that never call recv", "",
            "RSS in MiB (peaks are the kernel's VmHWM, reset before each phase):", "", *table, "",
            f"Stated bound = RSS after warm-up + one request's render working set + reply budget = "
            f"{bounded['rss_warm']:.0f} + {bounded['single_peak'] - bounded['rss_warm']:.0f} + {budget_mib:.0f} = "
            f"**{bound:.0f} MiB**; measured peak **{bounded['peak_with_clients']:.0f} MiB**: "
            f"{'within the bound' if ok else 'OVER THE BOUND'}."]


if __name__ == "__main__":
    main()
