"""End-to-end ``render()`` speed on a garage-like scene (not uniform random): the issue's cases (a)-(d).

The scene is a ``parksim synth`` dataset's surface points (floor, walls, pillars, ceiling, marks)
densified to N flat, surface-aligned Gaussians, sized like a trained scene (tangent sigma ~ the local
spacing at N, normal sigma 10% of it, mostly opaque, SH degree 3 with the points' colours); the rig is
the dataset's, scaled to the case's resolution, at a pose of its trajectory; the BEV is 512x512 over
the rig's 10 m. Timings are medians of wall-clock repeats after a warm-up. ``--reference MODULE``
times a copy of the package (importable as MODULE, e.g. an unmodified ``parksim`` copied to
``/tmp/before/parksim_before``) alternately with this one in the same process, for before/after
tables under the same load. Skips switched off: culling by replacing the fused kernel's cull with
keep-all, early termination by rasterizing with ``t_min = 0``, camera selection by rendering all four.

    PYTHONPATH=/tmp/before .venv/bin/python benchmarks/bench_render.py --dataset data/scene1_320 \
        --reference parksim_before --numba-threads 1 --out benchmarks/RESULTS_render.md
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import functools
import importlib
import inspect
import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numba
import numpy as np
import torch

SH_DEGREE = 3
BEV_PX = 512
CAMERA = "front"


@dataclasses.dataclass(frozen=True)
class SceneArrays:
    """Package-independent Gaussian tensors (float32), wrapped per package by ``Stack.scene``."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor


def read_points(dataset: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, unit normals and RGB in [0, 1] of the dataset's ``points3d.ply``."""
    from plyfile import PlyData

    v = PlyData.read(str(dataset / "points3d.ply"))["vertex"]
    xyz = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64)
    normals = np.stack([v["nx"], v["ny"], v["nz"]], -1).astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    rgb = np.stack([v["red"], v["green"], v["blue"]], -1).astype(np.float64) / 255.0
    return xyz, normals, rgb


def mean_spacing(xyz: np.ndarray, sample: int = 2000, seed: int = 0) -> float:
    """Median nearest-neighbour distance of a sample of the points to all of them."""
    pts = torch.from_numpy(xyz)
    idx = torch.randperm(len(pts), generator=torch.Generator().manual_seed(seed))[:sample]
    d = torch.cdist(pts[idx], pts)
    d[torch.arange(len(idx)), idx] = math.inf
    return float(d.min(dim=1).values.median())


def garage_scene(dataset: Path, n: int, seed: int = 0) -> SceneArrays:
    """N Gaussians on the dataset's surfaces: points resampled, jittered in their tangent plane, discs along them."""
    xyz, normals, rgb = read_points(dataset)
    rng = np.random.default_rng(seed)
    spacing = mean_spacing(xyz)
    pick = rng.integers(0, len(xyz), n)
    nrm = normals[pick]
    helper = np.where(np.abs(nrm[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(nrm, helper)
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(nrm, t1)
    spin = rng.uniform(0.0, 2 * math.pi, (n, 1))
    t1, t2 = np.cos(spin) * t1 + np.sin(spin) * t2, -np.sin(spin) * t1 + np.cos(spin) * t2
    radius = spacing * np.sqrt(rng.random((n, 1)))
    angle = rng.uniform(0.0, 2 * math.pi, (n, 1))
    means = xyz[pick] + radius * (np.cos(angle) * t1 + np.sin(angle) * t2)
    sigma = 0.6 * spacing * math.sqrt(len(xyz) / n) * np.exp(0.4 * rng.standard_normal((n, 2)))
    log_scales = np.log(np.concatenate([sigma, 0.1 * sigma.min(-1, keepdims=True)], -1))
    from parksim.geometry import quaternion_from_rotation

    quats = quaternion_from_rotation(torch.from_numpy(np.stack([t1, t2, nrm], -1)))
    sh = 0.05 * rng.standard_normal((n, (SH_DEGREE + 1) ** 2, 3))
    sh[:, 0] = (rgb[pick] - 0.5) / 0.28209479177387814
    opacity_logits = rng.normal(2.5, 1.5, n)
    return SceneArrays(*(torch.as_tensor(a).to(torch.float32).contiguous()
                         for a in (means, quats, log_scales, opacity_logits, sh)))


@dataclasses.dataclass
class Stack:
    """One importable copy of the package: its ``render``, rig and scene classes, and its kernel modules."""

    name: str

    @functools.cached_property
    def render(self) -> Callable[..., object]:
        """The package's ``render``."""
        return importlib.import_module(f"{self.name}.render.api").render

    def rig(self, dataset: Path) -> object:
        """The dataset's rig with a BEV_PX square BEV over the same ground extent."""
        rig_mod = importlib.import_module(f"{self.name}.rig")
        rig = rig_mod.Rig.load(dataset / "rig.json")
        b = rig.bev
        rig.bev = dataclasses.replace(b, width=BEV_PX, height=BEV_PX, m_per_px=b.m_per_px * b.width / BEV_PX)
        return rig

    def scene(self, arrays: SceneArrays, requires_grad: bool = False) -> object:
        """The arrays as this package's ``GaussianScene`` (fresh leaves when ``requires_grad``)."""
        cls = importlib.import_module(f"{self.name}.gaussians").GaussianScene
        tensors = [t.detach().clone().requires_grad_(requires_grad) for t in dataclasses.astuple(arrays)]
        return cls(*tensors, sh_degree=SH_DEGREE)

    @contextlib.contextmanager
    def no_cull(self) -> Iterator[None]:
        """Within the block the fused projection keeps every Gaussian (culling switched off)."""
        pk = importlib.import_module(f"{self.name}.render.project_kernels")
        original = pk.cull
        pk.cull = lambda means, log_scales, lens, opts, keep: keep.fill(True)
        try:
            yield
        finally:
            pk.cull = original

    def supports(self, skip_off: str) -> bool:
        """Whether this copy can switch ``skip_off`` off (older copies have no ``t_min`` rasterizer option)."""
        cpu = importlib.import_module(f"{self.name}.render.rasterize.cpu")
        return skip_off != "early_stop" or "t_min" in inspect.signature(cpu.rasterize_cpu).parameters

    @contextlib.contextmanager
    def no_early_stop(self) -> Iterator[None]:
        """Within the block the CPU rasterizer composites every Gaussian (``t_min = 0``: no early termination)."""
        cpu = importlib.import_module(f"{self.name}.render.rasterize.cpu")
        original = cpu.rasterize_cpu
        cpu.rasterize_cpu = functools.partial(original, t_min=0.0)
        try:
            yield
        finally:
            cpu.rasterize_cpu = original


def load_pose(dataset: Path, frame: int) -> torch.Tensor:
    """``T_world_vehicle`` of one frame of the dataset's trajectory."""
    frames = json.loads((dataset / "poses.json").read_text())["frames"]
    return torch.tensor(frames[frame % len(frames)]["T_world_vehicle"], dtype=torch.float64)


@dataclasses.dataclass(frozen=True)
class Case:
    """One timed configuration of ``render()``."""

    label: str
    n: int
    scale: float
    cameras: tuple[str, ...] | None
    bev: bool
    backward: bool = False
    skip_off: str = ""


def run_case(stack: Stack, case: Case, arrays: SceneArrays, rig: object, pose: torch.Tensor,
             threads: int) -> Callable[[], None]:
    """A closure that renders the case once with ``threads`` torch threads (and back-propagates a fixed loss)."""
    scene = stack.scene(arrays, requires_grad=case.backward)
    switch = {"": contextlib.nullcontext, "cull": stack.no_cull, "early_stop": stack.no_early_stop}[case.skip_off]
    weights: dict[str, torch.Tensor] = {}

    def once() -> None:
        torch.set_num_threads(threads)  # numba kernels of an older copy leave torch at numba's count
        with switch(), torch.set_grad_enabled(case.backward):
            out = stack.render(scene, rig, pose, cameras=case.cameras, bev=case.bev, scale=case.scale)
        if case.backward:
            for name, img in out.images.items():
                if name not in weights:
                    weights[name] = torch.rand(img.shape, generator=torch.Generator().manual_seed(1))
            sum((img * weights[name]).sum() for name, img in out.images.items()).backward()

    return once


def time_alternating(fns: list[Callable[[], None]], repeats: int, warmup: int = 1) -> list[tuple[float, float]]:
    """Median (wall, process CPU) ms of each closure, called in turn per repeat so load changes hit all alike.

    Process CPU time sums all threads and excludes time spent waiting for a core, so on this shared machine
    it is the steadier of the two; on an idle machine wall ~ CPU / threads used.
    """
    for fn in fns:
        for _ in range(warmup):
            fn()
    times: list[list[tuple[float, float]]] = [[] for _ in fns]
    for _ in range(repeats):
        for fn, ts in zip(fns, times):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            ts.append((1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)))
    return [(statistics.median(w for w, _ in ts), statistics.median(c for _, c in ts)) for ts in times]


def machine_line() -> str:
    """Architecture, cores, threads and the load average right now."""
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"{platform.machine()}, {os.cpu_count()} cores, numba threads {numba.get_num_threads()}, "
            f"torch threads {torch.get_num_threads()}, load average {load}")


def fit_exponent(xs: list[float], ys: list[float]) -> float:
    """Slope of log y against log x (least squares)."""
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def main() -> None:
    """Parse arguments, run cases (a)-(c) against the reference and the (d) sweeps, write markdown and the plot."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", type=Path, default=Path("data/scene1_320"))
    ap.add_argument("--reference", default="", help="module name of a package copy to time alongside")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--frame", type=int, default=50)
    ap.add_argument("--sweep", action=argparse.BooleanOptionalAction, default=True, help="run the (d) sweeps")
    ap.add_argument("--figure", type=Path, default=Path("benchmarks/figures/render_scaling.png"))
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="torch intra-op threads (1: with 2, torch's small ops stall badly on a loaded machine)")
    ap.add_argument("--numba-threads", type=int, default=numba.config.NUMBA_NUM_THREADS,
                    help="numba threads (1: on a loaded machine each parallel launch waits for a second core)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.torch_threads)
    numba.set_num_threads(args.numba_threads)

    stacks = [Stack("parksim")]
    if args.reference:
        stacks.append(Stack(args.reference))
    rigs = [s.rig(args.dataset) for s in stacks]
    base_w = rigs[0].cameras[CAMERA].model.width
    pose = load_pose(args.dataset, args.frame)
    s320, s640 = 320 / base_w, 640 / base_w
    cases = [
        Case("(a) 1 cam 320x240, 1e5, fwd", 100_000, s320, (CAMERA,), False),
        Case("(a) 1 cam 320x240, 1e5, fwd+bwd", 100_000, s320, (CAMERA,), False, backward=True),
        Case("(b) 4 cams 640x480 + BEV 512, 2e5, fwd", 200_000, s640, None, True),
        Case("(c) 1 cam 640x480 + BEV, 2e5", 200_000, s640, (CAMERA,), True),
        Case("(c) 4 cams, no BEV, 2e5", 200_000, s640, None, False),
        Case("(c) 4 cams + BEV, culling off", 200_000, s640, None, True, skip_off="cull"),
        Case("(c) 4 cams + BEV, early stop off", 200_000, s640, None, True, skip_off="early_stop"),
    ]
    scenes: dict[int, SceneArrays] = {}
    lines = [f"- machine at start: {machine_line()}"]
    header = "| case | " + " | ".join(f"{s.name} wall / CPU ms" for s in stacks)
    header += " | speed-up wall / CPU |" if len(stacks) > 1 else " |"
    table = [header, "| --- |" + " ---: |" * (len(stacks) + (len(stacks) > 1))]
    for case in cases:
        arrays = scenes.setdefault(case.n, garage_scene(args.dataset, case.n))
        able = [(s, r) for s, r in zip(stacks, rigs) if s.supports(case.skip_off)]
        meds = dict(zip([s.name for s, _ in able],
                        time_alternating([run_case(s, case, arrays, r, pose, args.torch_threads) for s, r in able],
                                         args.repeats)))
        cells = [f"{meds[s.name][0]:.0f} / {meds[s.name][1]:.0f}" if s.name in meds else "-" for s in stacks]
        if len(stacks) > 1:
            ratio = [meds[stacks[1].name][k] / meds[stacks[0].name][k] for k in (0, 1)] if len(meds) > 1 else None
            cells.append(f"{ratio[0]:.2f}x / {ratio[1]:.2f}x" if ratio else "-")
        row = f"| {case.label} | " + " | ".join(cells) + " |"
        table.append(row)
        print(row, f"(load {os.getloadavg()[0]:.1f})", flush=True)
    lines.append(f"- machine at end of (a)-(c): {machine_line()}")

    sweep_lines: list[str] = []
    if args.sweep:
        sweep_lines = sweep(args, stacks[0], rigs[0], pose, base_w)
    report(args, lines, table, sweep_lines)


def sweep(args: argparse.Namespace, stack: Stack, rig: object, pose: torch.Tensor, base_w: int) -> list[str]:
    """(d): forward time of the front camera vs N (at 320x240) and vs resolution (at 1e5); plot and exponents."""
    ns = [1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000]
    widths = [160, 320, 640, 1280]
    repeats = max(3, args.repeats // 2)
    by_n = []
    for n in ns:
        fn = run_case(stack, Case("", n, 320 / base_w, (CAMERA,), False), garage_scene(args.dataset, n), rig, pose,
                      args.torch_threads)
        by_n.append(time_alternating([fn], repeats)[0])
        print(f"N={n}: {by_n[-1]} ms", flush=True)
    arrays = garage_scene(args.dataset, 100_000)
    by_res = []
    for w in widths:
        fn = run_case(stack, Case("", 100_000, w / base_w, (CAMERA,), False), arrays, rig, pose, args.torch_threads)
        by_res.append(time_alternating([fn], repeats)[0])
        print(f"{w}x{w * 3 // 4}: {by_res[-1]} ms", flush=True)
    pixels = [w * w * 3 / 4 for w in widths]
    exp_n = fit_exponent(ns[-3:], [c for _, c in by_n[-3:]])
    exp_px = fit_exponent(pixels[-3:], [c for _, c in by_res[-3:]])

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for ax, xs, ys in ((ax1, ns, by_n), (ax2, pixels, by_res)):
        ax.loglog(xs, [w for w, _ in ys], "o-", label="wall (shared machine)")
        ax.loglog(xs, [c for _, c in ys], "s--", label="process CPU")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    ax1.set(xlabel="Gaussians", ylabel="forward ms (1 camera, 320x240)", title=f"CPU ~ N^{exp_n:.2f} over 1e5..1e6")
    ax2.set(xlabel="pixels (160x120 .. 1280x960)", ylabel="forward ms (1 camera, 1e5 Gaussians)",
            title=f"CPU ~ pixels^{exp_px:.2f} over 320x240..1280x960")
    fig.tight_layout()
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.figure, dpi=110)
    out = ["| Gaussians (1 cam 320x240, fwd) | wall ms | CPU ms |", "| ---: | ---: | ---: |"]
    out += [f"| {n:,} | {w:.1f} | {c:.1f} |" for n, (w, c) in zip(ns, by_n)]
    out += ["", "| resolution (1 cam, 1e5, fwd) | wall ms | CPU ms |", "| --- | ---: | ---: |"]
    out += [f"| {w}x{w * 3 // 4} | {t:.1f} | {c:.1f} |" for w, (t, c) in zip(widths, by_res)]
    out += ["", f"Fitted exponents (process CPU): time ~ N^{exp_n:.2f} (1e5..1e6), time ~ pixels^{exp_px:.2f} "
            f"(320x240..1280x960). Plot: `{args.figure}`. Machine at the end of the sweep: {machine_line()}."]
    return out


def report(args: argparse.Namespace, lines: list[str], table: list[str], sweep_lines: list[str]) -> None:
    """Print the tables and write them as markdown to ``--out`` when given."""
    text = "\n".join([
        "# render() benchmark: garage-like scene",
        "",
        f"- command: `{' '.join(['.venv/bin/python', 'benchmarks/bench_render.py', *sys.argv[1:]])}`",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- python {platform.python_version()}, torch {torch.__version__}, numba {numba.__version__}",
        f"- scene: `{args.dataset}/points3d.ply` densified (see the script's docstring); pose frame {args.frame}; "
        f"medians of {args.repeats} repeats after a warm-up, stacks called alternately",
        *lines, "", *table, "", *sweep_lines, ""])
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
