"""``parksim bench render``: end-to-end ``render()`` speed on a garage-like scene, the speed issue's cases, each
timed against a copy of the package (``--reference MODULE``) in the same process; optionally case (b) stage by
stage, and what serving a scene through each projection (EWA, UT) costs.

Parts (``--cases``):

- ``a``: one camera (default 320 px wide), 1e5 Gaussians, forward and forward + backward (target 150 ms);
- ``b``: every camera (640 px) + a 512 px BEV, 2e5 Gaussians, forward (target 200 ms);
- ``c``: (b)'s variations: one camera + BEV, four cameras without BEV, and (b) with culling and with early
  termination switched off (what each skip saves);
- ``stages`` (off by default): case (b) on one numba thread split into projection, binning, compositing, epilogue
  and BEV, each package's stages called alternately, with the compositor's Gaussian-pixel pairs evaluated
  against blended (``parksim.bench.pairs``);
- ``serve``: ``LocalSim.render`` (what ``parksim serve`` runs: every camera, no BEV) of one scene served through
  EWA and through UT at the dataset's test poses, alternately; ms per render (quality of each projection:
  ``parksim eval SCENE DATA --projection``).

The scene is the dataset's surface points densified to N Gaussians (``parksim.bench.cases``); forward cases run
under ``torch.no_grad()``, the one-pass inference path. A reference copy is a package importable as MODULE (e.g.
``git archive COMMIT parksim | tar -x -C /tmp/ab`` renamed ``/tmp/ab/parksim_prev``, with ``PYTHONPATH=/tmp/ab``);
its calls alternate with this tree's (``time_medians``), so a change of load hits both alike. Skips are switched
off by ``render(cull=False)`` (keep-all through the cull kernel in older copies) and by compositing with
``t_min = 0``; copies without that rasterizer option get no early-stop reference.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import inspect
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..cases import CAMERA, Case, CaseSizes, bev_rig, case, load_pose, render_case
from ..common import Timing, progress, time_medians
from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["RenderSuite", "RenderOptions", "PARTS", "STAGES"]

PARTS = ("a", "b", "c", "stages", "serve")
"""What ``--cases`` selects from."""
STAGES = ("projection", "binning", "compositing", "epilogue", "BEV", "whole render")
"""Case (b)'s stages, as the stage table times them."""
SH_DEGREE = 3


@dataclass(frozen=True)
class RenderOptions(CaseSizes):
    """Options of ``parksim bench render``."""

    dataset: Path | None = field(default=None, metadata={
        "help": "synth dataset whose points, rig, trajectory and test poses are used (default: synth scene1 at "
                "320x240 under --work; synth tiny under --quick)"})
    reference: str | None = field(default=None, metadata={
        "help": "module name of a package copy to time alongside this tree (importable, e.g. via PYTHONPATH)",
        "metavar": "MODULE"})
    cases: list[str] = field(default_factory=lambda: ["a", "b", "c", "serve"], metadata={
        "help": f"parts to run, of {', '.join(PARTS)} (stages: case (b) stage by stage on one thread)"})
    repeats: int = field(default=7, metadata={"help": "timed rounds per case (median)", "low": 1, "quick": 1})
    frame: int = field(default=50, metadata={"help": "frame of the trajectory giving the pose (modulo its length)",
                                             "low": 0})
    torch_threads: int = field(default=1, metadata={
        "help": "torch intra-op threads (1: with 2, torch's small ops stall badly on a loaded machine)", "low": 1})
    numba_threads: int | None = field(default=None, metadata={
        "help": "numba threads (default: numba's NUMBA_NUM_THREADS; 1 on a loaded machine, where each parallel "
                "launch waits for a second core)", "low": 1})
    serve_bundle: Path | None = field(default=None, metadata={
        "help": "scene bundle the serve part serves through each projection (default: case (b)'s garage scene "
                "on the dataset's rig)"})
    serve_repeats: int = field(default=5, metadata={"help": "timed rounds over every test pose in the serve part",
                                                    "low": 1, "quick": 1})

    def __post_init__(self) -> None:
        unknown = sorted(set(self.cases) - set(PARTS))
        if unknown or not self.cases:
            raise ValueError(f"bench render: --cases takes {', '.join(PARTS)}; got {','.join(self.cases)}")


@dataclass(frozen=True)
class SceneArrays:
    """Package-independent Gaussian tensors (float32), wrapped per package by ``Stack.scene``."""

    means: Any
    quats: Any
    log_scales: Any
    opacity_logits: Any
    sh: Any


def garage_arrays(dataset: Path, n: int, seed: int) -> SceneArrays:
    """N garage-like Gaussians on the dataset's surfaces, as package-independent tensors."""
    from ..scenes import garage_scene

    scene = garage_scene(dataset, n, seed, sh_degree=SH_DEGREE)
    return SceneArrays(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh)


@contextlib.contextmanager
def _patched(module: object, name: str, value: object) -> Iterator[None]:
    """``module.name = value`` within the block."""
    original = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, original)


@dataclass
class Stack:
    """One importable copy of the package: its ``render``, rig and scene classes, and its kernel modules."""

    name: str

    @property
    def render(self) -> Callable[..., Any]:
        """The package's ``render`` (looked up on each use, so the skip switches' patches apply)."""
        return importlib.import_module(f"{self.name}.render.api").render

    def rig(self, dataset: Path, bev_px: int) -> Any:
        """The dataset's rig as this package's ``Rig``, with a ``bev_px`` square BEV over the same ground extent."""
        return bev_rig(importlib.import_module(f"{self.name}.rig").Rig.load(dataset / "rig.json"), bev_px)

    def scene(self, arrays: SceneArrays, requires_grad: bool = False) -> Any:
        """The arrays as this package's ``GaussianScene`` (fresh leaves when ``requires_grad``)."""
        cls = importlib.import_module(f"{self.name}.gaussians").GaussianScene
        tensors = [t.detach().clone().requires_grad_(requires_grad) for t in dataclasses.astuple(arrays)]
        return cls(*tensors, sh_degree=SH_DEGREE)

    @contextlib.contextmanager
    def no_cull(self) -> Iterator[None]:
        """Within the block every Gaussian is projected into every camera (culling switched off): ``cull=False``
        where ``render`` takes it, else keep-all through an older copy's cull kernel."""
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
        """Within the block the CPU rasterizer composites every Gaussian (``t_min = 0``: no early termination), on
        the differentiable path and, where the copy has it, the one-pass inference path."""
        cpu = importlib.import_module(f"{self.name}.render.rasterize.cpu")
        api = importlib.import_module(f"{self.name}.render.api")
        with contextlib.ExitStack() as stack:
            stack.enter_context(_patched(cpu, "rasterize_cpu", functools.partial(cpu.rasterize_cpu, t_min=0.0)))
            if hasattr(api, "composite_many"):
                stack.enter_context(_patched(api, "composite_many", functools.partial(api.composite_many, t_min=0.0)))
            yield


def _case_closure(stack: Stack, c: Case, arrays: SceneArrays, rig: Any, pose: Any,
                  threads: int) -> Callable[[], None]:
    """A closure that renders the case once with ``threads`` torch threads (and back-propagates a fixed loss)."""
    import torch

    scene = stack.scene(arrays, requires_grad=c.backward)
    switches: dict[str, Callable[[], contextlib.AbstractContextManager[Any]]] = {
        "": contextlib.nullcontext, "cull": stack.no_cull, "early_stop": stack.no_early_stop}
    switch = switches[c.skip_off]
    weights: dict[str, Any] = {}

    def once() -> None:
        torch.set_num_threads(threads)  # numba kernels of an older copy leave torch at numba's count
        with switch():
            render_case(stack.render, scene, rig, pose, c, weights)

    return once


def _cases(options: RenderOptions, rig: Any) -> list[Case]:
    """Cases (a)-(c) of the parts asked for, with the stated targets where the sizes are the issue's."""
    o = options
    a = [case("a", "case (a)", o.gaussians_a, o.width_a, rig, (CAMERA,), False, backward=bwd) for bwd in (False, True)]
    b = [case("b", "case (b)", o.gaussians_b, o.width_b, rig, None, True)]
    c = [case("c", "case (c)", o.gaussians_b, o.width_b, rig, (CAMERA,), True),
         case("c", "case (c)", o.gaussians_b, o.width_b, rig, None, False),
         case("c", "case (c)", o.gaussians_b, o.width_b, rig, None, True, skip_off="cull"),
         case("c", "case (c)", o.gaussians_b, o.width_b, rig, None, True, skip_off="early_stop")]
    chosen = [x for x in a + b + c if x.group in o.cases]
    return [dataclasses.replace(x, goal=_goal(o, x)) for x in chosen]


def _goal(options: RenderOptions, c: Case) -> str | None:
    """The stated target of ``c`` (README, RESULTS.md) when it runs at the sizes the target was set at."""
    o = options
    if c.group == "a" and c.backward and (o.gaussians_a, o.width_a) == (100_000, 320):
        return "<= 150 ms"
    if c.group == "b" and (o.gaussians_b, o.width_b, o.bev_px) == (200_000, 640, 512):
        return "<= 200 ms"
    return None


class _Frame:
    """One package's case (b) frame split into its stages; each method runs one stage on the frame's data (the
    package's private kernels, as its ``render`` calls them)."""

    def __init__(self, pkg: str, rig: Any, scene: Any, pose: Any, scale: float) -> None:
        import numpy as np

        mod = {name: importlib.import_module(f"{pkg}.{name}") for name in (
            "render.api", "render.project_fast", "render.projection", "render.rasterize.tiles",
            "render.rasterize._kernels", "render.scratch", "geometry")}
        self.mod, self.rig, self.scene, self.pose, self.scale = mod, rig, scene, pose, scale
        api, proj = mod["render.api"], mod["render.projection"]
        view = api._rig_view(rig, scale, tuple(rig.names))
        self.cams = [view.rig.cameras[n] for n in rig.names]
        self.lenses = [view.lens_mask(n).numpy() for n in rig.names]
        T = mod["geometry"].as_pose(pose)
        self.T_cam_world = [mod["geometry"].invert_transform(T @ c.T_vehicle_camera) for c in self.cams]
        self.cfgs = [proj.fused_config(proj.UTParams(), proj.NEAR_M, proj.FAR_M,
                                       float(max(c.model.width, c.model.height)), True) for c in self.cams]
        self.alloc = mod["render.scratch"].thread_scratch()
        self.images: dict[str, Any] = {}
        self.projection()
        self.binning()
        self.planes = [(np.empty((c.model.height, c.model.width, 3), np.float32),
                        *(np.empty((c.model.height, c.model.width), t) for t in (np.float32, np.float32, np.int64)))
                       for c in self.cams]
        self.compositing()
        self.epilogue()

    def projection(self) -> None:
        import torch

        s = self.scene
        self.proj = self.mod["render.project_fast"].project_views_fused(
            s.means, s.quats, s.log_scales, torch.sigmoid(s.opacity_logits), s.sh, s.sh_degree, self.T_cam_world,
            [c.model for c in self.cams], self.cfgs, alloc=self.alloc)

    def _image(self, k: int) -> tuple[Any, ...]:
        p, m = self.proj, self.cams[k].model
        return p.means2d[k], p.conics[k], p.colors[k], p.opacities[k], p.depths[k], m.width, m.height

    def binning(self) -> None:
        tiles = self.mod["render.rasterize.tiles"]
        self.bins = [tiles.bin_gaussians(*self._image(k)) for k in range(len(self.cams))]

    def compositing(self) -> None:
        import numpy as np

        kernels = self.mod["render.rasterize._kernels"]
        for b, c, planes in zip(self.bins, self.cams, self.planes):
            order = np.argsort(-np.diff(b.offsets), kind="stable")
            kernels.forward(b.offsets, b.gauss_ids, b.packed, b.tiles_x, order, 1, c.model.width, c.model.height,
                            *planes)

    def epilogue(self) -> None:
        import numpy as np
        import torch

        kernels = self.mod["render.rasterize._kernels"]
        for name, (rgb, depth, t_final, _), lens in zip(self.rig.names, self.planes, self.lenses):
            image, alpha, out_depth = np.empty_like(rgb), np.empty_like(t_final), np.empty_like(t_final)
            kernels.finish_image(rgb, depth, t_final, lens, np.zeros(3, np.float32), np.float32(1e-4),
                                 image, alpha, out_depth)
            self.images[name] = torch.from_numpy(image)

    def bev(self) -> None:
        self.mod["render.api"].bev_ipm(self.rig, self.scale, tuple(self.rig.names))(self.images)

    def whole(self) -> None:
        import torch

        with torch.no_grad():
            self.mod["render.api"].render(self.scene, self.rig, self.pose, bev=True, scale=self.scale)

    def stage_fns(self) -> list[Callable[[], None]]:
        """The stages in ``STAGES`` order."""
        return [self.projection, self.binning, self.compositing, self.epilogue, self.bev, self.whole]

    def pairs(self) -> dict[str, int]:
        """Tile intersections and compositor pairs evaluated and blended over the frame's images."""
        from ..pairs import count_binned

        total = {"intersections": 0, "evaluated": 0, "blended": 0}
        for b, c, planes in zip(self.bins, self.cams, self.planes):
            for key, value in count_binned(b, planes[3], c.model.width, c.model.height).items():
                total[key] += value
        return total


def _stage_figures(stacks: list[Stack], rigs: list[Any], arrays: SceneArrays, pose: Any, b: Case,
                   repeats: int) -> tuple[list[Figure], dict[str, Any]]:
    """Case (b) stage by stage on one numba thread, every package's stages alternating; this tree's pairs."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        frames = [_Frame(s.name, r, s.scene(arrays), pose, b.scale) for s, r in zip(stacks, rigs)]
        timings = time_medians([fn for f in frames for fn in f.stage_fns()], repeats)
    finally:
        numba.set_num_threads(threads)
    n = len(STAGES)
    per_stack = [dict(zip(STAGES, timings[k * n:(k + 1) * n])) for k in range(len(stacks))]
    ref = stacks[1].name if len(stacks) > 1 else None
    pairs = frames[0].pairs()
    figures = [_figure(f"{b.target}: {stage}, 1 numba thread", per_stack[0][stage],
                       per_stack[1][stage] if ref else None, ref) for stage in STAGES]
    figures.append(Figure(f"{b.target}: compositor pairs evaluated per pair blended",
                          pairs["evaluated"] / max(pairs["blended"], 1), "x"))
    return figures, {"timings": dict(zip(("this", "reference"), per_stack)), "pairs": pairs}


def _figure(target: str, this: Timing, ref: Timing | None, ref_name: str | None, goal: str | None = None) -> Figure:
    """This tree's median beside the reference copy's, where that was timed."""
    return Figure(target, this.wall_ms, "ms", cpu=this.cpu_ms, goal=goal,
                  reference=None if ref is None else ref.wall_ms, reference_cpu=None if ref is None else ref.cpu_ms,
                  reference_label=None if ref is None else f"package copy {ref_name}, same process")


def _serve(options: RenderOptions, dataset: Path, arrays: Callable[[], SceneArrays],
           seed: int) -> tuple[list[Figure], dict[str, Any]]:
    """``LocalSim.render`` of one scene through EWA and through UT, alternately, at the dataset's test poses: the
    ``--serve-bundle``, else ``arrays()`` (case (b)'s garage Gaussians) on the dataset's rig."""
    import torch

    from ...bundle import Bundle
    from ...bundle import load as load_bundle
    from ...data import DatasetReader
    from ...gaussians import GaussianScene
    from ...geometry import xy_yaw_from_pose
    from ...rig import Rig
    from ...sim import LocalSim

    if options.serve_bundle is not None:
        bundle = load_bundle(options.serve_bundle)
        what = f"bundle {options.serve_bundle.name} ({len(bundle.scene):,} Gaussians, trained with {bundle.projection})"
    else:
        a = arrays()
        scene = GaussianScene(a.means, a.quats, a.log_scales, a.opacity_logits, a.sh, sh_degree=SH_DEGREE)
        bundle = Bundle(scene, Rig.load(dataset / "rig.json"), meta={"dataset": str(dataset), "seed": seed})
        what = f"garage {len(scene):,} Gaussians"
    reader = DatasetReader(dataset)
    frames = reader.split["test"] or reader.frames
    poses = [[float(v) for v in xy_yaw_from_pose(reader.pose(f))] for f in frames]
    model = bundle.rig.cameras[CAMERA].model
    scale = options.width_b / model.width
    sims = {m: LocalSim(dataclasses.replace(bundle, meta={**bundle.meta, "projection": m}), m) for m in ("ewa", "ut")}

    def closure(sim: LocalSim) -> Callable[[], None]:
        def once() -> None:
            for pose in poses:
                sim.render(pose, scale=scale)
        return once

    with torch.no_grad():
        ewa, ut = time_medians([closure(s) for s in sims.values()], options.serve_repeats)
    n = len(poses)
    size = f"{len(bundle.rig.names)} cameras {options.width_b}x{round(model.height * scale)}"
    figure = Figure(f"serve {size} (LocalSim.render, no BEV) through EWA, {what}", ewa.wall_ms / n, "ms",
                    cpu=ewa.cpu_ms / n, reference=ut.wall_ms / n, reference_cpu=ut.cpu_ms / n,
                    reference_label="the same scene served through UT, same run")
    data = {"input": what, "test_frames": frames, "scale": scale,
            "ms_per_render": {"ewa": {"wall": ewa.wall_ms / n, "cpu": ewa.cpu_ms / n},
                              "ut": {"wall": ut.wall_ms / n, "cpu": ut.cpu_ms / n}}}
    return [figure], data


class RenderSuite(Suite):
    """The speed issue's render cases against a package copy, case (b)'s stages, serving by projection."""

    name = "render"
    help = "render() cases (a)-(c) against a package copy; (b) by stage; serving through EWA vs UT"
    description = (
        "End-to-end render() on a garage-like scene (the dataset's points densified): (a) one camera at 320 px, 1e5 "
        "Gaussians, forward and forward+backward (target 150 ms); (b) every camera at 640 px + a 512 px BEV, 2e5 "
        "Gaussians (target 200 ms); (c) its variations and skips switched off; 'stages': (b) split into its "
        "stages on one numba thread with the compositor's pair counts; 'serve': LocalSim.render through EWA "
        "against UT at the test poses. --reference MODULE times a package copy alternately in the same process. "
        "Figures: median wall ms (process CPU beside), the reference copy's (or UT's) in the same run.")
    Options = RenderOptions

    def run(self, options: RenderOptions, context: Context) -> Outcome:
        """Time the parts asked for."""
        import numba
        import torch

        dataset = options.dataset or ensure_dataset(context, "scene1", "320x240")
        torch.set_num_threads(options.torch_threads)
        numba_threads = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]  # set at import
        numba.set_num_threads(min(options.numba_threads or numba_threads, numba_threads))
        stacks = [Stack("parksim")] + ([Stack(options.reference)] if options.reference else [])
        rigs = [s.rig(dataset, options.bev_px) for s in stacks]
        pose = load_pose(dataset, options.frame)
        cases = _cases(options, rigs[0])
        b = case("b", "case (b)", options.gaussians_b, options.width_b, rigs[0], None, True)
        scenes: dict[int, SceneArrays] = {}

        def arrays(n: int) -> SceneArrays:
            return scenes.setdefault(n, garage_arrays(dataset, n, context.seed))

        figures: list[Figure] = []
        data: dict[str, Any] = {"dataset": str(dataset), "frame": options.frame, "reference": options.reference,
                                "cases": {}}
        steps = len(cases) + ("stages" in options.cases) + ("serve" in options.cases)
        with progress(steps, "bench render", context.quiet) as bar:
            for c in cases:
                able = [(s, r) for s, r in zip(stacks, rigs) if s.supports(c.skip_off)]
                timings = time_medians([_case_closure(s, c, arrays(c.n), r, pose, options.torch_threads)
                                        for s, r in able], options.repeats)
                ref = timings[1] if len(able) > 1 else None
                figures.append(_figure(c.target, timings[0], ref, options.reference, c.goal))
                data["cases"][c.target] = dict(zip(("this", "reference"), timings))
                bar.update(1)
            if "stages" in options.cases:
                stage_figures, data["stages"] = _stage_figures(stacks, rigs, arrays(b.n), pose, b, options.repeats)
                figures += stage_figures
                bar.update(1)
            if "serve" in options.cases:
                serve_figures, data["serve"] = _serve(options, dataset, lambda: arrays(b.n), context.seed)
                figures += serve_figures
                bar.update(1)
        return Outcome(figures, data)
