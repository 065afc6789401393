"""Processes under measurement: memory and CPU time read from /proc (one process, or a process and its
descendants), ``parksim serve`` on loopback in a subprocess, a command run until every process it started has
exited, and the one local Ray instance the Ray suites use.

Linux only (/proc). CPU times are user + system seconds at the kernel's clock tick (usually 10 ms).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Server", "serve_bundle", "rss_mib", "total_rss_mib", "status_mib", "reset_peak_rss", "free_port",
           "descendants", "cpu_seconds", "tree_cpu_seconds", "process_name", "CpuMeter", "run_measured", "local_ray",
           "RAY_OBJECT_STORE_MIB"]

_TICK = os.sysconf("SC_CLK_TCK")
_PR_SET_CHILD_SUBREAPER, _PR_GET_CHILD_SUBREAPER = 36, 37
RAY_OBJECT_STORE_MIB = 150
"""Object store of a Ray instance ``local_ray`` starts (the suites pass replies and actor results of a few MiB)."""


def status_mib(pid: int | None = None, key: str = "VmRSS") -> float:
    """A memory field of ``/proc/PID/status`` in MiB (``VmRSS``: resident now; ``VmHWM``: peak resident).

    Args:
        pid: the process (default: this one).
        key: the field.

    Returns:
        Its value in MiB; ``RuntimeError`` when the process has no such field (a zombie, a kernel thread).
    """
    for line in Path(f"/proc/{pid or os.getpid()}/status").read_text().splitlines():
        if line.startswith(f"{key}:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {key} for pid {pid}")


def rss_mib(pid: int | None = None) -> float:
    """Resident memory (MiB) of process ``pid`` (default: this one), from /proc."""
    return status_mib(pid, "VmRSS")


def total_rss_mib(pids: Iterable[int]) -> float:
    """Summed resident memory (MiB) of ``pids``; a process gone, or without memory of its own, counts 0."""
    total = 0.0
    for pid in pids:
        with contextlib.suppress(OSError, RuntimeError):
            total += rss_mib(pid)
    return total


def reset_peak_rss(pid: int) -> None:
    """Make the peak resident memory (``VmHWM``) of ``pid`` start again from its current RSS (a process of ours)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _stats() -> dict[int, tuple[int, float]]:
    """Every process's parent and its own CPU seconds so far (zombies included)."""
    out: dict[int, tuple[int, float]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):   # exited while listed
                continue
            out[int(entry)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / _TICK)
    return out


def _descendants(root: int, stats: dict[int, tuple[int, float]]) -> list[int]:
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    out, todo = [], [root]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def descendants(pid: int) -> list[int]:
    """The live descendants of ``pid`` (not ``pid`` itself)."""
    return _descendants(pid, _stats())


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of ``pid`` so far (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _TICK


def tree_cpu_seconds(root: int) -> float:
    """CPU seconds of ``root`` and every live descendant (a Ray driver with its daemons, workers, servers)."""
    stats = _stats()
    return sum(stats.get(pid, (0, 0.0))[1] for pid in [root, *_descendants(root, stats)])


def process_name(pid: int) -> str:
    """What ``pid`` runs: its program, or the script of a Python process (Ray's workers retitle themselves
    ``ray::...``); ``?`` once it is gone."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
    except OSError:
        return "?"
    scripts = [a for a in argv[1:] if a.endswith(".py")] if Path(argv[0]).name.startswith("python") else []
    return Path(scripts[0] if scripts else argv[0]).name


class CpuMeter:
    """CPU seconds that ``pids`` spend inside a ``with`` block, summed by ``group(pid)`` (``spent``), and the
    block's wall seconds (``wall``)."""

    def __init__(self, pids: Sequence[int], group: Callable[[int], str]) -> None:
        self.pids, self.group = list(pids), group
        self.spent: dict[str, float] = {}
        self.wall = 0.0

    def __enter__(self) -> CpuMeter:
        self._before = {p: cpu_seconds(p) for p in self.pids}
        self._start = time.perf_counter()
        return self

    def __exit__(self, *_: object) -> None:
        self.wall = time.perf_counter() - self._start
        for p, before in self._before.items():
            key = self.group(p)
            self.spent[key] = self.spent.get(key, 0.0) + max(cpu_seconds(p) - before, 0.0)


@contextlib.contextmanager
def _child_subreaper() -> Iterator[None]:
    """This process adopts its orphaned descendants while the block runs (``PR_SET_CHILD_SUBREAPER``), so a
    command's grandchildren stay measurable after their parent exits; the previous setting comes back after."""
    libc = ctypes.CDLL(None, use_errno=True)
    before = ctypes.c_int(0)
    libc.prctl(_PR_GET_CHILD_SUBREAPER, ctypes.byref(before), 0, 0, 0)
    if libc.prctl(_PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER) failed")
    try:
        yield
    finally:
        libc.prctl(_PR_SET_CHILD_SUBREAPER, before.value, 0, 0, 0)


def run_measured(command: Sequence[str], env: dict[str, str] | None = None, poll_s: float = 0.1,
                 settle_s: float = 120.0) -> float:
    """Run ``command`` until it and every process it started have exited.

    Each process's CPU time is sampled from /proc every ``poll_s`` until it is reaped; orphans (a Ray worker whose
    raylet exited) are adopted and reaped here after their last sample, so none escapes the count or outlives the
    call. ``RUSAGE_CHILDREN`` misses most of Ray's: 9.5 s against 29.7 s sampled for one ``parksim batch``. A
    process that lives less than ``poll_s``, and the last ``poll_s`` of each, may go uncounted.

    Args:
        command: the command line.
        env: variables set on top of this process's environment.
        poll_s: sampling period.
        settle_s: how long the processes it started may outlive it; then they are killed and ``RuntimeError``
            names them.

    Returns:
        CPU seconds of all the processes; ``RuntimeError`` with the command's output when it exits non-zero.
    """
    me = os.getpid()
    with _child_subreaper(), tempfile.TemporaryFile("w+") as log:
        proc = subprocess.Popen(list(command), stdout=log, stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, **(env or {})})
        tree, cpu = {proc.pid}, dict[int, float]()
        exited = time.monotonic()
        while True:
            stats = _stats()
            for pid, (ppid, seconds) in stats.items():
                if pid in tree or ppid in tree:
                    tree.add(pid)
                    cpu[pid] = max(cpu.get(pid, 0.0), seconds)
            proc.poll()   # after sampling: a zombie still shows its CPU
            for pid in tree - {proc.pid}:
                if stats.get(pid, (0, 0.0))[0] == me:   # adopted
                    with contextlib.suppress(ChildProcessError):
                        os.waitpid(pid, os.WNOHANG)
            if proc.returncode is None:
                exited = time.monotonic()
            else:
                alive = [pid for pid in tree if Path(f"/proc/{pid}").exists()]
                if not alive:
                    break
                if time.monotonic() - exited > settle_s:
                    for pid in alive:
                        with contextlib.suppress(ProcessLookupError):
                            os.kill(pid, signal.SIGKILL)
                    raise RuntimeError(f"{' '.join(command)} left {len(alive)} process(es) running "
                                       f"{settle_s:g} s after it exited: {[process_name(p) for p in alive]}")
            time.sleep(poll_s)
        if proc.returncode != 0:
            log.seek(0)
            raise RuntimeError(f"{' '.join(command)} exited {proc.returncode}:\n{log.read()}")
    return sum(cpu.values())


@dataclass(frozen=True)
class Server:
    """A running server: its base URL (always 127.0.0.1) and process id."""

    base: str
    pid: int


@contextlib.contextmanager
def serve_bundle(scenes: Path, args: Sequence[str] = (), startup_s: float = 300.0,
                 log: Path | None = None) -> Iterator[Server]:
    """``parksim serve --scenes SCENES ARGS`` on a free 127.0.0.1 port in a subprocess; yields once /healthz answers.

    The server is stopped with SIGTERM (with ``--ray``, its Serve app and any Ray it started go down too), killed
    if it has not exited a minute later.

    Args:
        scenes: a bundle folder or a folder of them.
        args: more ``parksim serve`` options (``--reply-budget-mib``, ``--ray --address ...``).
        startup_s: how long the scenes may take to load.
        log: a file the server's stderr is written to and kept (default: a temporary file, gone after).

    Returns:
        The running server; ``RuntimeError`` with its stderr when it exits or does not answer in time.
    """
    import httpx

    port = free_port()
    cmd = [sys.executable, "-m", "parksim.cli", "serve", "--scenes", str(scenes), "--port", str(port), *args]
    base = f"http://127.0.0.1:{port}"
    with open(log, "w+") if log else tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True)
        try:
            deadline = time.monotonic() + startup_s
            while True:
                with contextlib.suppress(httpx.HTTPError):   # not listening yet
                    if httpx.get(f"{base}/healthz", timeout=5).status_code == 200:
                        break
                if proc.poll() is not None or time.monotonic() > deadline:
                    err.seek(0)
                    raise RuntimeError(f"{' '.join(cmd)} did not start (exit code {proc.poll()}):\n{err.read()}")
                time.sleep(0.2)
            yield Server(base, proc.pid)
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@contextlib.contextmanager
def local_ray(cpus: int) -> Iterator[None]:
    """The Ray instance of this process: the one already running here (used, left running, and checked to have
    ``cpus`` CPUs), else a local one with ``cpus`` CPUs, a ``RAY_OBJECT_STORE_MIB`` object store and no dashboard,
    shut down when the block ends, whatever happens in it. Either way its daemons are this process's descendants,
    so ``descendants``/``tree_cpu_seconds`` see them.

    Args:
        cpus: Ray CPUs.
    """
    import logging

    import ray

    if ray.is_initialized():
        have = int(ray.cluster_resources().get("CPU", 0))
        if have < cpus:
            raise ValueError(f"the running Ray instance has {have} CPUs, the suite needs {cpus}")
        yield
        return
    ray.init(num_cpus=cpus, object_store_memory=RAY_OBJECT_STORE_MIB * 2**20, include_dashboard=False,
             logging_level=logging.ERROR, log_to_driver=False)
    try:
        yield
    finally:
        ray.shutdown()
