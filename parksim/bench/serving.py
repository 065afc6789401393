"""What the serving suites share: a bundle to serve, aisle poses, and the two client loads on ``GET /render``
(sequential latency, and N concurrent clients retrying a 503 after its Retry-After).

The default bundle is ``N`` Gaussians sampled on a synth garage's surfaces with its rig and map, not trained
(``parksim.bench.scenes.surface_bundle``): a render's cost depends on the Gaussian count and the image sizes, which
it shares with a trained scene of that size. It is written once under the work folder and reused.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .suite import Context

__all__ = ["garage_bundle", "ServedScene", "scene_bundle", "aisle_pose", "latency", "client_load", "warm"]


def garage_bundle(context: Context, preset: str, size: tuple[int, int] | None, gaussians: int) -> Path:
    """A bundle of ``gaussians`` Gaussians sampled on the surfaces of synth ``preset``'s garage with its rig and map
    (``parksim.bench.scenes.surface_bundle``; the tiny garage at its own size under --quick), made under
    ``context.work/bundles`` if missing.

    Args:
        context: the run's context (work folder, seed, quick).
        preset: synth preset of a full run (``scene1`` ...).
        size: camera ``(width, height)`` of a full run (None: the preset's own).
        gaussians: number of Gaussians.

    Returns:
        The bundle folder (alone in its parent folder, so either can be served as ``--scenes``).
    """
    from ..fileio import atomic_directory
    from .datasets import QUICK_SCENE
    from .scenes import surface_bundle

    preset, size = (QUICK_SCENE, None) if context.quick else (preset, size)
    shape = f"{size[0]}x{size[1]}" if size else "native"
    out = context.work / "bundles" / f"surface_{preset}_{shape}_{gaussians}_seed{context.seed}" / preset
    if not (out / "bundle.json").is_file():
        with atomic_directory(out) as tmp:
            surface_bundle(tmp, preset, gaussians, context.seed, size)
    return out


@dataclass(frozen=True)
class ServedScene:
    """A bundle a serving suite measures: its folder, the words that name it in targets
    (``"N Gaussians, 4 x WxH views, WxH BEV"``) and its garage's length along x (m; the aisle poses run along it)."""

    bundle: Path
    label: str
    length: float


def scene_bundle(given: Path | None, context: Context, preset: str, size: tuple[int, int] | None,
                 gaussians: int) -> ServedScene:
    """The bundle a serving suite measures: ``given``, or ``garage_bundle``'s.

    Args:
        given: a bundle folder the user passed (``--bundle``), or None.
        context, preset, size, gaussians: as ``garage_bundle``'s.

    Returns:
        The scene; ``ValueError`` for a bundle without a map of its garage.
    """
    from ..bundle import load

    bundle = given or garage_bundle(context, preset, size, gaussians)
    loaded = load(bundle)
    garage = (loaded.map or {}).get("garage")
    if not garage:
        raise ValueError(f"{bundle}: the serving benchmarks need a bundle with a map of its garage (map.json)")
    sizes = sorted({(c.model.width, c.model.height) for c in loaded.rig.cameras.values()})
    views = ", ".join(f"{w}x{h}" for w, h in sizes)
    bev = loaded.rig.bev
    label = f"{len(loaded.scene):,} Gaussians, {len(loaded.rig.names)} x {views} views, {bev.width}x{bev.height} BEV"
    return ServedScene(bundle, label, float(garage["x"][1] - garage["x"][0]))


def aisle_pose(rng: np.random.Generator, length: float) -> str:
    """A random ego pose ``x,y,yaw`` in the aisle, at least 8 m from either end of a garage ``length`` m long."""
    return f"{rng.uniform(8, length - 8):.3f},{rng.uniform(-0.5, 0.5):.3f},{rng.uniform(-0.3, 0.3):.4f}"


def latency(client: Any, params: dict[str, str], n: int, length: float, seed: int,
            server_pid: int | None = None) -> dict[str, Any]:
    """``n`` sequential GET /render with ``params`` at random aisle poses.

    Args:
        client: an ``httpx.Client`` on the server's base URL.
        params: query parameters besides ``pose``.
        n: requests.
        length: garage length (m), for the poses.
        seed: seed of the poses.
        server_pid: the server's process, whose CPU time per request is read from /proc (None: not measured).

    Returns:
        ``n``, p50/p95/p99 and mean latency (ms), the same percentiles of the server's CPU ms per request
        (``cpu_p50`` ...; None without ``server_pid``), every latency (``ms``) and CPU time (``cpu_ms``).
    """
    from .procs import cpu_seconds

    rng = np.random.default_rng(seed)
    times, cpu = [], []
    for _ in range(n):
        pose = aisle_pose(rng, length)
        c0 = cpu_seconds(server_pid) if server_pid else 0.0
        start = time.perf_counter()
        r = client.get("/render", params={**params, "pose": pose})
        r.raise_for_status()
        times.append((time.perf_counter() - start) * 1000)
        if server_pid:
            cpu.append(1000 * (cpu_seconds(server_pid) - c0))
    out: dict[str, Any] = {"n": n, "mean": float(np.mean(times)), "ms": times, "cpu_ms": cpu}
    for q in (50, 95, 99):
        out[f"p{q}"] = float(np.percentile(times, q))
        out[f"cpu_p{q}"] = float(np.percentile(cpu, q)) if cpu else None
    return out


def client_load(base: str, params: dict[str, str], clients: int, duration: float, length: float) -> dict[str, Any]:
    """``clients`` threads sending GET /render with ``params`` for ``duration`` s, a 503 retried after its
    Retry-After; latency runs from a render's first try to its 200 (retries included), as a client sees it. Each
    client's poses come from its own seed, so every server measured gets the same requests.

    Args:
        base: the server's base URL.
        params: query parameters besides ``pose``.
        clients: concurrent clients.
        duration: seconds of load.
        length: garage length (m), for the poses.

    Returns:
        Renders answered (``ok``), 503s and other errors, seconds, renders/s (``throughput``), p50 and p99 ms.
    """
    import httpx

    latencies: list[float] = []
    counts = {"busy_503": 0, "errors": 0}
    lock = threading.Lock()
    stop = time.monotonic() + duration

    def worker(i: int) -> None:
        rng = np.random.default_rng(100 + i)
        with httpx.Client(base_url=base, timeout=300) as c:
            while time.monotonic() < stop:
                first, query = time.perf_counter(), {**params, "pose": aisle_pose(rng, length)}
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
    p50, p99 = (float(v) for v in np.percentile(latencies, [50, 99]) * 1000) if latencies else (float("nan"),) * 2
    return {"ok": len(latencies), **counts, "seconds": seconds, "throughput": len(latencies) / seconds,
            "p50": p50, "p99": p99}


def warm(base: str, params: dict[str, str], n: int = 1, rounds: int = 1, patience_s: float = 600.0) -> None:
    """``rounds`` rounds of ``n`` concurrent renders, so every replica (or render thread) has compiled its kernels
    and built its per-scale grids before anything is timed. A cold kernel cache on a loaded machine can make the
    first render outlast the server's render timeout (503): such a render is retried after its Retry-After, for up
    to ``patience_s`` seconds."""
    import concurrent.futures

    import httpx

    deadline = time.monotonic() + patience_s

    def render(c: httpx.Client, i: int) -> None:
        while True:
            r = c.get("/render", params={**params, "pose": f"{20 + i},0,0"})
            if r.status_code != 503 or time.monotonic() > deadline:
                r.raise_for_status()
                return
            time.sleep(float(r.headers.get("retry-after", 1)))

    with concurrent.futures.ThreadPoolExecutor(n) as pool, httpx.Client(base_url=base, timeout=600) as c:
        for _ in range(rounds):
            list(pool.map(lambda i: render(c, i), range(n)))
