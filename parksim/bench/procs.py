"""Processes under measurement: resident memory from /proc, and ``parksim serve`` on loopback in a subprocess."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from .common import ROOT

__all__ = ["Server", "serve_bundle", "rss_mib", "free_port"]

_SERVER = ("import sys, uvicorn; from server import create_app; uvicorn.run(create_app(sys.argv[1]), "
           "host='127.0.0.1', port=int(sys.argv[2]), log_level='warning')")


def rss_mib(pid: int | None = None) -> float:
    """Resident memory (MiB) of process ``pid`` (default: this one), from /proc."""
    for line in Path(f"/proc/{pid or os.getpid()}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass(frozen=True)
class Server:
    """A running server: its base URL (always 127.0.0.1) and process id."""

    base: str
    pid: int


@contextlib.contextmanager
def serve_bundle(bundle: Path, startup_s: float = 300.0) -> Iterator[Server]:
    """Serve ``bundle`` with uvicorn on a free 127.0.0.1 port in a subprocess; yields once /healthz answers."""
    import httpx

    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", _SERVER, str(bundle), str(port)], env=env, cwd=ROOT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + startup_s
        while True:
            with contextlib.suppress(httpx.HTTPError):   # not listening yet
                if httpx.get(f"{base}/healthz").status_code == 200:
                    break
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"server for {bundle} did not start (exit code {proc.poll()})")
            time.sleep(0.5)
        yield Server(base, proc.pid)
    finally:
        proc.terminate()
        proc.wait(30)
