"""Rasterizer speed on this machine: numba tile kernel vs the dense torch reference.

Cases: 320x240 with 1e5 Gaussians (forward, forward+backward, binning included), 640x480 with 2e5
(forward), and a small case where the torch reference runs too. Gaussians have realistic screen sizes
(3-sigma radius mostly 1-10 px, 1% of 20-80 px, anisotropic, random orientation and opacity).
Reports medians after warm-up, Gaussian-pixel pairs evaluated and ns per pair; --out writes markdown.

    .venv/bin/python benchmarks/bench_rasterize.py --out benchmarks/RESULTS_rasterize.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import time
from collections.abc import Callable

import numba
import numpy as np
import torch
from llvmlite import binding as llvm

from parksim.render.rasterize import TILE, rasterize
from parksim.render.rasterize import _kernels as kernels
from parksim.render.rasterize._kernels import _tile_box
from parksim.render.rasterize.tiles import bin_gaussians


def make_scene(n: int, width: int, height: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Random screen-space Gaussians: means, conics, colors, opacities, depths (float32)."""
    rng = np.random.default_rng(seed)
    radius = np.exp(rng.uniform(np.log(1.0), np.log(10.0), n))
    big = rng.random(n) < 0.01
    radius[big] = rng.uniform(20.0, 80.0, big.sum())
    sigma1 = radius / 3.0
    sigma2 = sigma1 * rng.uniform(0.3, 1.0, n)
    theta = rng.uniform(0.0, np.pi, n)
    cos, sin = np.cos(theta), np.sin(theta)
    # conic = R diag(1/s1^2, 1/s2^2) R^T
    i1, i2 = 1.0 / sigma1**2, 1.0 / sigma2**2
    conics = np.stack([cos**2 * i1 + sin**2 * i2, cos * sin * (i1 - i2), sin**2 * i1 + cos**2 * i2], -1)
    means = rng.uniform([-10.0, -10.0], [width + 10.0, height + 10.0], (n, 2))
    colors = rng.random((n, 3))
    opacities = rng.uniform(0.05, 1.0, n)
    depths = rng.uniform(1.0, 50.0, n)
    return tuple(torch.from_numpy(a).float() for a in (means, conics, colors, opacities, depths))


@numba.njit(cache=True)
def _rows_evaluated(offsets, gauss_ids, packed, tiles_x, last, width, height):
    """Tile rows the forward kernel evaluates (TILE pairs each), per tile up to its last contributor + 1."""
    total = 0
    for tile in range(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(tile, tiles_x, width, height)
        stop = offsets[tile]
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                stop = max(stop, last[py, px] + 2)
        for k in range(offsets[tile], min(stop, offsets[tile + 1])):
            p = packed[gauss_ids[k]]
            total += max(0, min(y1, np.int64(p[11])) - max(y0, np.int64(p[10])) + 1)
    return total


def count_pairs(scene: tuple[torch.Tensor, ...], width: int, height: int) -> tuple[int, int]:
    """(Gaussian-pixel pairs the forward evaluates, tile intersections) for a scene."""
    arrays = [t.numpy() for t in scene]
    bins = bin_gaussians(*arrays, width, height)
    order = np.argsort(-np.diff(bins.offsets), kind="stable")
    outs = (np.empty((height, width, 3), np.float32), np.empty((height, width), np.float32),
            np.empty((height, width), np.float32), np.empty((height, width), np.int64))
    kernels.forward(bins.offsets, bins.gauss_ids, bins.packed, bins.tiles_x, order, numba.get_num_threads(),
                    width, height, *outs)
    rows = _rows_evaluated(bins.offsets, bins.gauss_ids, bins.packed, bins.tiles_x, outs[3], width, height)
    return int(rows) * TILE, int(bins.gauss_ids.shape[0])


def median_ms(fn: Callable[[], None], repeats: int, warmup: int = 2) -> tuple[float, float, float]:
    """(median wall ms, median process CPU ms, fastest wall ms) of fn after warm-up calls.

    On a shared machine the wall time swings with other jobs; CPU time summed over threads is the steadier
    measure of the work itself (CPU ms / threads approximates the wall time on an idle machine).
    """
    for _ in range(warmup):
        fn()
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        walls.append((time.perf_counter() - wall) * 1e3)
        cpus.append((time.process_time() - cpu) * 1e3)
    return statistics.median(walls), statistics.median(cpus), min(walls)


def forward_fn(scene: tuple[torch.Tensor, ...], width: int, height: int, backend: str) -> Callable[[], None]:
    """Closure: forward only, no autograd graph."""
    def run() -> None:
        with torch.no_grad():
            rasterize(*scene, width, height, backend=backend)
    return run


def train_fn(scene: tuple[torch.Tensor, ...], width: int, height: int, backend: str) -> Callable[[], None]:
    """Closure: forward + backward of a fixed random loss on rgb, alpha and depth."""
    leaves = [t.clone().requires_grad_(i < 4) for i, t in enumerate(scene)]
    weights = [torch.rand(height, width, 3), torch.rand(height, width), torch.rand(height, width)]

    def run() -> None:
        for leaf in leaves[:4]:
            leaf.grad = None
        out = rasterize(*leaves, width, height, backend=backend)
        sum((o * w).sum() for o, w in zip(out, weights)).backward()
    return run


def _fmt(times: tuple[float, float, float] | None) -> str:
    """"median wall / median CPU / fastest wall" in ms, or a dash for a case that was not run."""
    return "-" if times is None else f"{times[0]:.1f} / {times[1]:.1f} / {times[2]:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=str, default="", help="write a markdown report here")
    args = parser.parse_args()

    rows = []
    all_threads = numba.get_num_threads()
    cases = [
        ("320x240, 1e5 Gaussians", 320, 240, 100_000, ("numba",), True),
        ("640x480, 2e5 Gaussians", 640, 480, 200_000, ("numba",), False),
        ("64x48, 2e3 Gaussians (reference comparison)", 64, 48, 2_000, ("numba", "torch"), True),
    ]
    for name, width, height, n, backends, with_backward in cases:
        scene = make_scene(n, width, height)
        pairs, isects = count_pairs(scene, width, height)
        runs = [(b, t) for b in backends for t in sorted({all_threads, 1}, reverse=True) if b == "numba" or t > 1]
        for backend, threads in runs:
            numba.set_num_threads(threads)
            fwd = median_ms(forward_fn(scene, width, height, backend), args.repeats)
            both = median_ms(train_fn(scene, width, height, backend), args.repeats) if with_backward else None
            rows.append((name, backend, threads, fwd, both, pairs, isects))
            print(f"{name:46s} {backend:6s} threads {threads} fwd {_fmt(fwd)} ms  fwd+bwd {_fmt(both)} ms  "
                  f"pairs {pairs:>10d}  isect {isects:>8d}  fwd ns/pair (wall) {fwd[0] * 1e6 / max(pairs, 1):7.2f}",
                  flush=True)
        numba.set_num_threads(all_threads)

    if args.out:
        lines = [
            "# Rasterizer benchmark",
            "",
            f"- command: `.venv/bin/python benchmarks/bench_rasterize.py --out {args.out}`",
            f"- date: {datetime.date.today().isoformat()}",
            f"- machine: {platform.machine()} ({llvm.get_host_cpu_name()}), {os.cpu_count()} cores, "
            f"numba threads {all_threads} (and 1), torch {torch.__version__}, numba {numba.__version__}; "
            f"shared with other jobs (load average {os.getloadavg()[0]:.1f} at the end), so wall times are noisy",
            f"- medians of {args.repeats} runs after 2 warm-up runs; binning included; pairs = Gaussian-pixel pairs "
            "the forward kernel evaluates (16-pixel tile rows reached by each ellipse, per tile up to its "
            "early stop); times are median wall / median process CPU (summed over threads) / fastest wall; "
            "ns/pair = median forward wall time / pairs",
            "",
            "| case | backend | numba threads | forward ms | forward+backward ms | pairs "
            "| tile intersections | forward ns/pair |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for name, backend, threads, fwd, both, pairs, isects in rows:
            lines.append(f"| {name} | {backend} | {threads} | {_fmt(fwd)} | {_fmt(both)} | {pairs} | {isects} "
                         f"| {fwd[0] * 1e6 / max(pairs, 1):.2f} |")
        with open(args.out, "w") as handle:
            handle.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
