"""End-to-end ``render()`` speed on a garage-like scene (not uniform random): the issue's cases (a)-(c),
timed against an older copy of the package. The (d) sweeps are ``parksim bench scaling``.

The scene is a ``parksim synth`` dataset's surface points densified to N flat, surface-aligned Gaussians
(``parksim.bench.scenes.garage_scene``); the rig is the dataset's, scaled to the case's resolution, at a
pose of its trajectory; the BEV is 512x512 over the rig's 10 m. Timings are medians of repeats after a
warm-up (``parksim.bench.common.time_medians``). ``--reference MODULE``
times a copy of the package (importable as MODULE, e.g. an unmodified ``parksim`` copied to
``/tmp/before/parksim_before``) alternately with this one in the same process, for before/after
tables under the same load. Skips switched off: culling by ``render(cull=False)`` (keep-all through the
cull kernel in older copies), early termination by compositing with ``t_min = 0``, camera selection by
rendering all four. Forward cases run under ``torch.no_grad()``, i.e. the one-pass inference path where
the copy has one.

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
import os
import platform
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numba
import torch

from parksim.bench.common import time_medians
from parksim.bench.scenes import garage_scene

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


def garage_arrays(dataset: Path, n: int) -> SceneArrays:
    """N garage-like Gaussians on the dataset's surfaces, as package-independent tensors."""
    scene = garage_scene(dataset, n, sh_degree=SH_DEGREE)
    return SceneArrays(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh)


@dataclasses.dataclass
class Stack:
    """One importable copy of the package: its ``render``, rig and scene classes, and its kernel modules."""

    name: str

    @property
    def render(self) -> Callable[..., object]:
        """The package's ``render`` (looked up on each use, so the skip switches' patches apply)."""
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
        """Within the block every Gaussian is projected into every camera (culling switched off).

        Copies whose ``render`` takes ``cull`` get ``cull=False``; older ones keep-all through their cull kernel.
        """
        api = importlib.import_module(f"{self.name}.render.api")
        if "cull" in inspect.signature(api.render).parameters:
            with _patched(api, "render", functools.partial(api.render, cull=False)):
                yield
            return
        pk = importlib.import_module(f"{self.name}.render.project_kernels")
        with _patched(pk, "cull", lambda means, log_scales, lens, opts, keep: keep.fill(True)):
            yield

    def supports(self, skip_off: str) -> bool:
        """Whether this copy can switch ``skip_off`` off (older copies have no ``t_min`` rasterizer option)."""
        cpu = importlib.import_module(f"{self.name}.render.rasterize.cpu")
        return skip_off != "early_stop" or "t_min" in inspect.signature(cpu.rasterize_cpu).parameters

    @contextlib.contextmanager
    def no_early_stop(self) -> Iterator[None]:
        """Within the block the CPU rasterizer composites every Gaussian (``t_min = 0``: no early termination),
        on the differentiable path and, where the copy has it, the one-pass inference path."""
        cpu = importlib.import_module(f"{self.name}.render.rasterize.cpu")
        api = importlib.import_module(f"{self.name}.render.api")
        with contextlib.ExitStack() as stack:
            stack.enter_context(_patched(cpu, "rasterize_cpu", functools.partial(cpu.rasterize_cpu, t_min=0.0)))
            if hasattr(api, "composite_many"):
                stack.enter_context(_patched(api, "composite_many", functools.partial(api.composite_many, t_min=0.0)))
            yield


@contextlib.contextmanager
def _patched(module: object, name: str, value: object) -> Iterator[None]:
    """``module.name = value`` within the block."""
    original = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, original)


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
        with switch():
            render_case(stack.render, scene, rig, pose, case, weights)

    return once


def render_case(render_fn: Callable[..., Any], scene: Any, rig: object, pose: torch.Tensor, case: Case,
                weights: dict[str, torch.Tensor], **kwargs: Any) -> None:
    """Render ``case`` once; with ``case.backward`` also back-propagate a fixed random weighting of the images
    (drawn once per camera into ``weights``, on the images' device, so every call does the same work)."""
    with torch.set_grad_enabled(case.backward):
        out = render_fn(scene, rig, pose, cameras=case.cameras, bev=case.bev, scale=case.scale, **kwargs)
    if case.backward:
        for name, img in out.images.items():
            if name not in weights:
                weights[name] = torch.rand(img.shape, generator=torch.Generator().manual_seed(1)).to(img)
        sum((img * weights[name]).sum() for name, img in out.images.items()).backward()


def machine_line() -> str:
    """Architecture, cores, threads and the load average right now."""
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"{platform.machine()}, {os.cpu_count()} cores, numba threads {numba.get_num_threads()}, "
            f"torch threads {torch.get_num_threads()}, load average {load}")


def main() -> None:
    """Parse arguments, run cases (a)-(c) against the reference, write markdown."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", type=Path, default=Path("data/scene1_320"))
    ap.add_argument("--reference", default="", help="module name of a package copy to time alongside")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--frame", type=int, default=50)
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="torch intra-op threads (1: with 2, torch's small ops stall badly on a loaded machine)")
    ap.add_argument("--numba-threads", type=int, default=numba.config.NUMBA_NUM_THREADS,
                    help="numba threads (1: on a loaded machine each parallel launch waits for a second core)")
    ap.add_argument("--cases", action="append", default=[],
                    help="label prefix, e.g. '(a)' (repeatable): run only the cases whose label starts so")
    ap.add_argument("--stages", action="store_true",
                    help="also time case (b) stage by stage on one thread and count its Gaussian-pixel pairs")
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
    if args.cases:
        cases = [c for c in cases if c.label.startswith(tuple(args.cases))]
    scenes: dict[int, SceneArrays] = {}
    lines = [f"- machine at start: {machine_line()}"]
    header = "| case | " + " | ".join(f"{s.name} wall / CPU ms" for s in stacks)
    header += " | speed-up wall / CPU |" if len(stacks) > 1 else " |"
    table = [header, "| --- |" + " ---: |" * (len(stacks) + (len(stacks) > 1))]
    for case in cases:
        arrays = scenes.setdefault(case.n, garage_arrays(args.dataset, case.n))
        able = [(s, r) for s, r in zip(stacks, rigs) if s.supports(case.skip_off)]
        meds = dict(zip([s.name for s, _ in able],
                        [(t.wall_ms, t.cpu_ms) for t in time_medians(
                            [run_case(s, case, arrays, r, pose, args.torch_threads) for s, r in able], args.repeats)]))
        cells = [f"{meds[s.name][0]:.0f} / {meds[s.name][1]:.0f}" if s.name in meds else "-" for s in stacks]
        if len(stacks) > 1:
            ratio = [meds[stacks[1].name][k] / meds[stacks[0].name][k] for k in (0, 1)] if len(meds) > 1 else None
            cells.append(f"{ratio[0]:.2f}x / {ratio[1]:.2f}x" if ratio else "-")
        row = f"| {case.label} | " + " | ".join(cells) + " |"
        table.append(row)
        print(row, f"(load {os.getloadavg()[0]:.1f})", flush=True)
    lines.append(f"- machine at end of (a)-(c): {machine_line()}")
    if args.stages:
        from render_stages import stage_table

        table += ["", *stage_table(stacks, rigs, garage_arrays(args.dataset, 200_000), pose, s640, args.repeats)]
    report(args, lines, table)


def report(args: argparse.Namespace, lines: list[str], table: list[str]) -> None:
    """Print the tables and write them as markdown to ``--out`` when given."""
    text = "\n".join([
        "# render() benchmark: garage-like scene",
        "",
        f"- command: `{' '.join(['.venv/bin/python', 'benchmarks/bench_render.py', *sys.argv[1:]])}`",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- python {platform.python_version()}, torch {torch.__version__}, numba {numba.__version__}",
        f"- scene: `{args.dataset}/points3d.ply` densified (see the script's docstring); pose frame {args.frame}; "
        f"medians of {args.repeats} repeats after a warm-up, stacks called alternately",
        *lines, "", *table, ""])
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
