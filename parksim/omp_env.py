"""OpenMP's wait policy for our processes (the CLI and the server), set before torch loads OpenMP."""

from __future__ import annotations

import os

__all__ = ["prefer_sleeping_omp_threads"]


def prefer_sleeping_omp_threads() -> None:
    """Waiting OpenMP threads sleep instead of spinning: spinning steals the core numba's kernels need on a small
    machine (measured: 4.6 s -> 0.76 s for a four-camera render under load, benchmarks/RESULTS.md). Call it
    before torch is imported; a user's own ``OMP_WAIT_POLICY`` wins."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
