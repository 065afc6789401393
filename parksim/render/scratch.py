"""Reusable scratch arrays for the inference path, kept by the rendering thread between renders.

A 4-camera frame needs ~150 MB of temporaries (projected rows, tile bins, compositor planes). Fresh
allocations of that size come from the OS page by page on each frame (glibc maps and unmaps them), which
cost ~25 ms a frame here; a planner rendering pose after pose reuses the same memory instead.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numpy as np

__all__ = ["Allocator", "fresh", "thread_scratch"]

Allocator = Callable[[str, tuple[int, ...], "np.dtype | type"], np.ndarray]
"""``alloc(name, shape, dtype)``: an uninitialised C-contiguous array for the temporary called ``name``."""

_LOCAL = threading.local()
"""Per-thread ``buffers``: name -> the largest uint8 block asked for under that name."""


def fresh(_name: str, shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """A new array every call: for callers that keep what they get (e.g. bins saved for a backward pass)."""
    return np.empty(shape, dtype)


def thread_scratch() -> Allocator:
    """Arrays from the calling thread's reusable buffers, one per name.

    An array stays valid until the same thread hands out that name again, so it is only for data that does
    not outlive the render that asked for it. Buffers grow to the largest request and are kept for the
    thread's life: for four 640x480 cameras and 2e5 Gaussians, ~32 MB in the thread that calls ``render``
    and ~30 MB in each compositor thread.
    """
    buffers: dict[str, np.ndarray] = _LOCAL.__dict__.setdefault("buffers", {})

    def alloc(name: str, shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
        dtype = np.dtype(dtype)
        nbytes = math.prod(shape) * dtype.itemsize
        buf = buffers.get(name)
        if buf is None or buf.nbytes < nbytes:
            buf = buffers[name] = np.empty(nbytes, np.uint8)
        return buf[:nbytes].view(dtype).reshape(shape)

    return alloc
