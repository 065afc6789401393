"""Per-thread scratch arrays for the inference path, kept between renders.

A 4-camera frame needs ~150 MB of temporaries (projected rows, tile bins, compositor planes). Fresh
allocations of that size come from the OS page by page on each frame (glibc maps and unmaps them), which
cost ~25 ms a frame here; a planner rendering pose after pose reuses the same memory instead.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numpy as np

_LOCAL = threading.local()


def scratch(name: str, shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """An uninitialised C-contiguous array owned by this thread under ``name``.

    It stays valid until this thread asks for ``name`` again, so it is only for data that does not outlive
    the call that asked for it. The buffer grows to the largest request and is kept for the thread's life.
    """
    dtype = np.dtype(dtype)
    nbytes = math.prod(shape) * dtype.itemsize
    buffers: dict[str, np.ndarray] = _LOCAL.__dict__.setdefault("buffers", {})
    buf = buffers.get(name)
    if buf is None or buf.nbytes < nbytes:
        buf = buffers[name] = np.empty(nbytes, np.uint8)
    return buf[:nbytes].view(dtype).reshape(shape)


def _fresh(_name: str, shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """A new uninitialised array (``scratch``'s signature, for callers that keep what they get)."""
    return np.empty(shape, dtype)


def allocator(reuse: bool) -> Callable[[str, tuple[int, ...], np.dtype | type], np.ndarray]:
    """``scratch`` when ``reuse``, else a function of the same signature that returns new arrays."""
    return scratch if reuse else _fresh
