"""Helpers the benchmark suites share: thread control, medians after a warm-up (wall and process CPU), growth
exponents, progress bars and plots. A record's metadata (machine, commit, load) is ``parksim.bench.record``'s.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Timing", "set_threads", "time_medians", "fit_exponent", "progress", "pyplot", "save_figure"]


@dataclass(frozen=True)
class Timing:
    """Median wall-clock and process-CPU milliseconds of repeated calls (CPU sums threads, excludes waiting)."""

    wall_ms: float
    cpu_ms: float
    repeats: int


def set_threads(n: int) -> None:
    """Use ``n`` threads in numba kernels and torch ops (numba resets the count torch reads, so set both)."""
    import numba
    import torch

    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]  # set at import
    torch.set_num_threads(n)


def time_medians(fns: Sequence[Callable[[], Any]], repeats: int, warmup: int = 1,
                 tick: Callable[[], Any] = lambda: None) -> list[Timing]:
    """Median time of each closure, called in turn per round so a change of load hits all of them alike, in
    reverse order every other round (the first of a round was measured to read up to 10 % slower);
    ``warmup`` untimed rounds first; ``tick`` is called after every round (progress)."""
    for _ in range(warmup):
        for fn in fns:
            fn()
        tick()
    samples: list[list[tuple[float, float]]] = [[] for _ in fns]
    for r in range(repeats):
        for k in range(len(fns)) if r % 2 == 0 else reversed(range(len(fns))):
            t0, c0 = time.perf_counter(), time.process_time()
            fns[k]()
            samples[k].append((1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)))
        tick()
    return [Timing(statistics.median(w for w, _ in ts), statistics.median(c for _, c in ts), repeats) for ts in samples]


def fit_exponent(xs: Sequence[float], ys: Sequence[float]) -> float:
    """Slope of log y against log x (least squares): y ~ x^slope."""
    return float(np.polyfit(np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float)), 1)[0])


def progress(total: int, desc: str, quiet: bool) -> Any:
    """A tqdm bar on stderr (hidden with ``quiet``)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="pt", disable=quiet, dynamic_ncols=True)


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, png: Path) -> None:
    """Lay out ``fig``, save it as ``png`` and close it (the record beside it says where and when it was made)."""
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    pyplot().close(fig)
