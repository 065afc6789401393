"""Keep freed memory in glibc's heap during training, so each step's large tensors reuse pages already mapped.

A training step allocates and frees the same large buffers every iteration (gradients, Adam's temporaries,
the SH gradient: tens of MB each). glibc serves blocks over its mmap threshold (at most 32 MB) with a fresh
``mmap`` and unmaps them on free, so every step pays a page fault per page it touches again. On a
200k-Gaussian 640x480 step: 18345 minor faults a step before, 0 after, and 1.03-1.16x faster
(``docs/benchmarks.md#render``); the render path, which keeps its own scratch buffers, gained nothing.
The cost: the process keeps its peak heap until it exits.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

__all__ = ["keep_freed_memory"]

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_MAX = -1, -2, -4   # glibc's mallopt parameters (malloc.h)
_TOP_PAD = 256 << 20
"""Heap growth per ``brk``: a step's worth of buffers in a few system calls instead of one per block."""


@functools.cache
def keep_freed_memory() -> bool:
    """Serve every block from the heap (no mmap), never trim it, grow it 256 MB at a time; process-wide, once.

    Returns whether glibc took the settings (False on another C library, where this does nothing)."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in
               ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1), (_M_TOP_PAD, _TOP_PAD)))
