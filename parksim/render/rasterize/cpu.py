"""CPU backend: binning + numba kernels wrapped in a torch.autograd.Function (float32 inside)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple, TypeVar

import numba
import numpy as np
import torch
from torch import Tensor

from ..project_fast import keep_torch_threads
from ..scratch import Allocator, fresh, thread_scratch
from . import _kernels as kernels
from .constants import T_MIN
from .tiles import TileBins, bin_gaussians

__all__ = ["rasterize_cpu", "composite", "composite_many", "Image"]


def _f32(t: Tensor) -> np.ndarray:
    """Detached, contiguous float32 numpy array of a tensor (copied to the CPU if needed)."""
    return np.ascontiguousarray(t.detach().cpu().to(torch.float32).numpy())


def _heaviest_first(bins: TileBins) -> np.ndarray:
    """Tile order for round-robin dealing to threads: most intersections first, for load balance."""
    return np.argsort(-np.diff(bins.offsets), kind="stable")


def composite(means2d: np.ndarray, conics: np.ndarray, colors: np.ndarray, opacities: np.ndarray,
              depths: np.ndarray, width: int, height: int, t_min: float = T_MIN, alloc: Allocator = fresh
              ) -> tuple[TileBins, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bin and composite float32 Gaussians: ``(bins, tile order, rgb, depth sum, final T, last index)``.

    Rows with opacity below ``ALPHA_MIN`` (or a non-positive-definite conic) are skipped and never read.
    ``alloc`` gives every returned array (new ones by default; see ``parksim.render.scratch``).
    """
    rgb = alloc("composite.rgb", (height, width, 3), np.float32)
    depth = alloc("composite.depth", (height, width), np.float32)
    t_final = alloc("composite.t_final", (height, width), np.float32)
    last = alloc("composite.last", (height, width), np.int64)
    with keep_torch_threads():
        bins = bin_gaussians(means2d, conics, colors, opacities, depths, width, height, alloc)
        order = _heaviest_first(bins)
        kernels.forward(bins.offsets, bins.gauss_ids, bins.packed, bins.tiles_x, order, numba.get_num_threads(),
                        width, height, rgb, depth, t_final, last, np.float32(t_min))
    return bins, order, rgb, depth, t_final, last


R = TypeVar("R")


class Image(NamedTuple):
    """One image's float32 Gaussian rows for ``composite_many`` (opacity 0 = not drawn) and its size."""

    means2d: np.ndarray
    conics: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    depths: np.ndarray
    width: int
    height: int


_POOL: tuple[int, ThreadPoolExecutor] | None = None
"""The compositor's worker threads and how many there are."""
_POOL_LOCK = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    """The compositor's worker threads (made once, grown when more are asked for)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] < workers:
            _POOL = (workers, ThreadPoolExecutor(max_workers=workers, thread_name_prefix="parksim-composite"))
        return _POOL[1]


Finish = Callable[[int, np.ndarray, np.ndarray, np.ndarray], R]
"""``finish(k, rgb, depth sum, final T)``: turns image ``k``'s compositor output into what the caller keeps."""


def _composite_alone(k: int, image: Image, t_min: float, finish: Finish[R]) -> R:
    """Image ``k`` composited on this thread only (numba's thread count is per thread), then ``finish``-ed."""
    numba.set_num_threads(1)
    return finish(k, *composite(*image, t_min, thread_scratch())[2:5])


def composite_many(images: Sequence[Image], finish: Finish[R], t_min: float = T_MIN) -> list[R]:
    """``finish(k, rgb, depth sum, final T)`` of several images, each composited whole on one of numba's threads.

    Binning, depth sorting and bucketing are serial per image, so on a few cores giving each image its own
    core (largest first) keeps them all busy where splitting every image across cores would not (measured:
    binning side by side, then each image's tiles over all cores, was no faster; letting an idle thread take
    chunks of another image's tiles balanced the threads but was 7-11 % slower). ``finish`` (masking,
    background) runs on the same thread, so it should release the GIL (numpy, torch). The arrays it gets
    are that thread's scratch memory (``parksim.render.scratch``): it must copy whatever it keeps.
    """
    workers = min(numba.get_num_threads(), len(images))
    if workers <= 1:
        return [finish(k, *composite(*image, t_min, thread_scratch())[2:5]) for k, image in enumerate(images)]
    order = sorted(range(len(images)), key=lambda k: -int(np.count_nonzero(images[k].opacities)))
    futures = {k: _pool(workers).submit(_composite_alone, k, images[k], t_min, finish) for k in order}
    return [futures[k].result() for k in range(len(images))]


class _RasterizeCPU(torch.autograd.Function):
    """Forward renders with the tile kernels and keeps (bins, T_final, last index) for the backward."""

    @staticmethod
    def forward(ctx: Any, means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor,
                width: int, height: int, bg: Tensor | None, t_min: float) -> tuple[Tensor, Tensor, Tensor]:
        bins, order, rgb, depth, t_final, last = composite(_f32(means2d), _f32(conics), _f32(colors),
                                                           _f32(opacities), _f32(depths), width, height, t_min)
        bg32 = np.zeros(3, np.float32) if bg is None else _f32(bg).reshape(3)
        ctx.state = (bins, order, t_final, last, bg32, width, height)
        ctx.like = [(t.dtype, t.device) for t in (means2d, conics, colors, opacities, depths)]
        out_rgb = torch.from_numpy(rgb + t_final[..., None] * bg32 if bg is not None else rgb)
        return out_rgb.to(means2d), torch.from_numpy(1.0 - t_final).to(means2d), torch.from_numpy(depth).to(means2d)

    @staticmethod
    def backward(ctx: Any, g_rgb: Tensor, g_alpha: Tensor, g_depth: Tensor) -> tuple[Tensor | None, ...]:
        bins, order, t_final, last, bg32, width, height = ctx.state
        grad_isect = np.empty((bins.gauss_ids.shape[0], kernels.N_GRAD), np.float32)
        grads = np.zeros((bins.packed.shape[0], kernels.N_GRAD), np.float32)
        with keep_torch_threads():
            kernels.backward(bins.offsets, bins.gauss_ids, bins.slot_of, bins.packed, bins.tiles_x, order,
                             numba.get_num_threads(), width, height, t_final, last,
                             _f32(g_rgb), _f32(g_alpha), _f32(g_depth), bg32, grad_isect)
            kernels.reduce_by_gaussian(bins.starts, grad_isect, grads)
        out = torch.from_numpy(grads)
        parts = (out[:, 0:2], out[:, 2:5], out[:, 5:8], out[:, 8], out[:, 9])
        grads_in = (p.to(dtype=dtype, device=device) for p, (dtype, device) in zip(parts, ctx.like))
        return (*grads_in, None, None, None, None)


def rasterize_cpu(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor,
                  width: int, height: int, bg: Tensor | None = None,
                  t_min: float = T_MIN) -> tuple[Tensor, Tensor, Tensor]:
    """Numba tile rasterizer; same contract as `parksim.render.rasterize.rasterize` (CPU tensors).

    ``t_min`` is the early-termination transmittance (0 switches early termination off, for measuring it).
    """
    return _RasterizeCPU.apply(means2d, conics, colors, opacities, depths, width, height, bg, t_min)
