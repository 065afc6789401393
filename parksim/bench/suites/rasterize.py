"""``parksim bench rasterize``: the numba tile rasterizer alone (binning included), on all numba threads and on
one, with the Gaussian-pixel pairs its forward kernel evaluates; and against the dense torch reference on a case
small enough for it.

Cases: ``--width`` (320x240) with 1e5 Gaussians, forward and forward + backward (a fixed random weighting of rgb,
alpha and depth); ``--large-width`` (640x480) with 2e5, forward; ``--reference-width`` (64x48) with 2e3, forward
and forward + backward, numba and torch. Heights are 3/4 of the widths. The Gaussians have realistic screen sizes:
3-sigma radius mostly 1-10 px, 1 % of 20-80 px, anisotropic, random orientation and opacity.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..cases import count_text
from ..common import Timing, progress, time_medians
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["RasterizeSuite", "RasterizeOptions", "make_scene"]

Scene = tuple[Any, Any, Any, Any, Any]


@dataclass(frozen=True)
class RasterizeOptions:
    """Options of ``parksim bench rasterize``."""

    width: int = field(default=320, metadata={"help": "image width of the forward and forward+backward case",
                                              "low": 16, "quick": 80})
    gaussians: int = field(default=100_000, metadata={"help": "its Gaussians", "low": 1, "quick": 4_000})
    large_width: int = field(default=640, metadata={"help": "image width of the forward-only case", "low": 16,
                                                    "quick": 160})
    large_gaussians: int = field(default=200_000, metadata={"help": "its Gaussians", "low": 1, "quick": 8_000})
    reference_width: int = field(default=64, metadata={
        "help": "image width of the case the dense torch reference runs too", "low": 16, "quick": 32})
    reference_gaussians: int = field(default=2_000, metadata={"help": "its Gaussians", "low": 1, "quick": 200})
    repeats: int = field(default=7, metadata={"help": "timed calls per case (median)", "low": 1, "quick": 1})
    warmup: int = field(default=2, metadata={"help": "untimed calls first", "low": 0, "quick": 1})


def make_scene(n: int, width: int, height: int, seed: int) -> Scene:
    """Random screen-space Gaussians: means ``(n, 2)``, conics ``(n, 3)``, colours ``(n, 3)``, opacities and depths
    ``(n,)``, float32 tensors."""
    import numpy as np
    import torch

    rng = np.random.default_rng(seed)
    radius = np.exp(rng.uniform(np.log(1.0), np.log(10.0), n))
    big = rng.random(n) < 0.01
    radius[big] = rng.uniform(20.0, 80.0, big.sum())
    sigma1 = radius / 3.0
    sigma2 = sigma1 * rng.uniform(0.3, 1.0, n)
    theta = rng.uniform(0.0, np.pi, n)
    cos, sin = np.cos(theta), np.sin(theta)
    i1, i2 = 1.0 / sigma1**2, 1.0 / sigma2**2   # conic = R diag(1/s1^2, 1/s2^2) R^T
    conics = np.stack([cos**2 * i1 + sin**2 * i2, cos * sin * (i1 - i2), sin**2 * i1 + cos**2 * i2], -1)
    means = rng.uniform([-10.0, -10.0], [width + 10.0, height + 10.0], (n, 2))
    colors = rng.random((n, 3))
    opacities = rng.uniform(0.05, 1.0, n)
    depths = rng.uniform(1.0, 50.0, n)
    return tuple(torch.from_numpy(a).float() for a in (means, conics, colors, opacities, depths))  # type: ignore


def forward_fn(scene: Scene, width: int, height: int, backend: str) -> Callable[[], None]:
    """Closure: forward only, no autograd graph."""
    import torch

    from ...render.rasterize import rasterize

    means2d, conics, colors, opacities, depths = scene

    def run() -> None:
        with torch.no_grad():
            rasterize(means2d, conics, colors, opacities, depths, width, height, backend=backend)
    return run


def train_fn(scene: Scene, width: int, height: int, backend: str) -> Callable[[], None]:
    """Closure: forward and backward of a fixed random weighting of rgb, alpha and depth."""
    import torch

    from ...render.rasterize import rasterize

    means2d, conics, colors, opacities, depths = (t.clone().requires_grad_(i < 4) for i, t in enumerate(scene))
    weights = [torch.rand(height, width, 3), torch.rand(height, width), torch.rand(height, width)]

    def run() -> None:
        for leaf in (means2d, conics, colors, opacities):
            leaf.grad = None
        out = rasterize(means2d, conics, colors, opacities, depths, width, height, backend=backend)
        torch.stack([(o * w).sum() for o, w in zip(out, weights)]).sum().backward()
    return run


@dataclass(frozen=True)
class _Case:
    """One scene: its width (height 3/4 of it), Gaussians, whether the backward and the torch reference run."""

    width: int
    n: int
    backward: bool
    with_torch: bool

    @property
    def height(self) -> int:
        return self.width * 3 // 4

    @property
    def size(self) -> str:
        return f"{self.width}x{self.height}, {count_text(self.n)} Gaussians"


def _timed_row(c: _Case, scene: Scene, backend: str, threads: int | None, pairs: dict[str, int],
               options: RasterizeOptions) -> dict[str, Any]:
    """Median forward (and forward + backward) of one backend on the case, calls alternating."""
    fns = [forward_fn(scene, c.width, c.height, backend)]
    fns += [train_fn(scene, c.width, c.height, backend)] if c.backward else []
    timed = time_medians(fns, options.repeats, options.warmup)
    return {"size": c.size, "backend": backend, "threads": threads, "forward": timed[0],
            "forward_backward": timed[1] if c.backward else None, **pairs,
            "forward_ns_per_pair": timed[0].wall_ms * 1e6 / max(pairs["evaluated"], 1)}


class RasterizeSuite(Suite):
    """The numba tile rasterizer: forward and backward latency, pairs evaluated, against the torch reference."""

    name = "rasterize"
    help = "numba tile rasterizer: fwd and fwd+bwd on all threads and one, ns per pair, vs the torch reference"
    description = ("The rasterizer alone on random screen-space Gaussians of realistic sizes (binning included): "
                   "320x240 with 1e5 Gaussians forward and forward+backward, 640x480 with 2e5 forward, on all numba "
                   "threads and on one; forward ns per Gaussian-pixel pair evaluated; and a 64x48 case with 2e3 "
                   "Gaussians where the dense torch reference runs too (the reference of its figures).")
    Options = RasterizeOptions

    def run(self, options: RasterizeOptions, context: Context) -> Outcome:
        """Time every case on every thread count."""
        import numba

        from ..pairs import count_pairs

        o = options
        cases = [_Case(o.width, o.gaussians, True, False), _Case(o.large_width, o.large_gaussians, False, False),
                 _Case(o.reference_width, o.reference_gaussians, True, True)]
        all_threads = numba.get_num_threads()
        thread_counts = sorted({all_threads, 1}, reverse=True)
        figures: list[Figure] = []
        rows: list[dict[str, Any]] = []
        with progress(len(cases) * len(thread_counts), "bench rasterize", context.quiet) as bar:
            for c in cases:
                scene = make_scene(c.n, c.width, c.height, context.seed)
                means2d, conics, colors, opacities, depths = (t.numpy() for t in scene)
                pairs = count_pairs(means2d, conics, colors, opacities, depths, c.width, c.height)
                case_rows = []
                for threads in thread_counts:
                    numba.set_num_threads(threads)
                    case_rows.append(_timed_row(c, scene, "numba", threads, pairs, o))
                    bar.update(1)
                numba.set_num_threads(all_threads)
                if c.with_torch:   # torch's own threads: once
                    case_rows.append(_timed_row(c, scene, "torch", None, pairs, o))
                figures += _figures(c, case_rows)
                rows += case_rows
        return Outcome(figures, {"all_threads": all_threads, "rows": rows})


def _figures(c: _Case, rows: list[dict[str, Any]]) -> list[Figure]:
    """The case's rows as figures: latency per pass and thread count, ns per pair, numba against torch."""
    figures = []
    torch_row = next((r for r in rows if r["backend"] == "torch"), None)
    for r in (r for r in rows if r["backend"] == "numba"):
        threads = "1 thread" if r["threads"] == 1 else "all threads"
        passes = [("fwd", "forward")] + ([("fwd+bwd", "forward_backward")] if c.backward else [])
        for name, key in passes:
            t: Timing = r[key]
            ref: Timing | None = torch_row[key] if torch_row else None
            figures.append(Figure(
                f"rasterize {name}, {c.size}, numba {threads}", t.wall_ms, "ms", cpu=t.cpu_ms,
                reference=None if ref is None else ref.wall_ms, reference_cpu=None if ref is None else ref.cpu_ms,
                reference_label=None if ref is None else "dense torch reference, same run"))
        if not c.with_torch:
            figures.append(Figure(f"rasterize fwd per Gaussian-pixel pair evaluated, {c.size}, numba {threads}",
                                  r["forward_ns_per_pair"], "ns"))
    return figures
