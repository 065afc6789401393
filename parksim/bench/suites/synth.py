"""``parksim bench synth``: ``parksim synth`` serially and with the process pool, in the same run.

Each worker count renders the same frames into a fresh dataset (the generator's own ``generate``, as ``parksim
synth`` calls it), in turn per round and in reverse order every other round. Wall time includes the pool's start-up
(each worker imports and builds its renderer once); CPU time is user + system of this process and of its reaped pool
workers. Figures are per frame, so the goal (``parksim synth`` of 100 frames x 4 cameras at 640x480 under 300 s)
reads directly.
"""

from __future__ import annotations

import dataclasses
import os
import resource
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..common import progress
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["SynthSuite", "SynthOptions", "GOAL_MS_PER_FRAME"]

GOAL_MS_PER_FRAME = 3000.0
"""The goal at 640x480: 100 frames x 4 cameras in under 300 s."""


@dataclass(frozen=True)
class SynthOptions:
    """Options of ``parksim bench synth``."""

    preset: str = field(default="scene1", metadata={"help": "synth preset", "quick": "tiny"})
    frames: int = field(default=12, metadata={"help": "frames per run", "low": 1, "quick": 4})
    workers: list[int] = field(default_factory=lambda: [1, 2], metadata={
        "help": "worker counts to compare (1 = serial; the first is the reference)", "low": 1})
    repeats: int = field(default=1, metadata={"help": "runs per worker count, interleaved (median)", "low": 1})

    def __post_init__(self) -> None:
        if not self.workers or len(set(self.workers)) != len(self.workers):
            raise ValueError(f"--workers: distinct worker counts, got {self.workers}")


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its reaped children (the pool's workers)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


class SynthSuite(Suite):
    """Synthetic dataset generation time, serial against the process pool."""

    name = "synth"
    help = "parksim synth time, serial against the process pool"
    description = ("Generate the same frames of a synth preset with each worker count, interleaved; wall (pool "
                   "start-up included) and CPU (this process and its pool workers) per frame, each count beside the "
                   "first.")
    Options = SynthOptions

    def run(self, options: SynthOptions, context: Context) -> Outcome:
        """Generate with each worker count in turn, ``repeats`` rounds."""
        from ...synth import generate, get_preset

        preset = dataclasses.replace(get_preset(options.preset), frames=options.frames)
        runs: dict[int, list[dict[str, float]]] = {w: [] for w in options.workers}
        context.work.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=context.work) as tmp, \
                progress(options.repeats * len(options.workers), "bench synth", context.quiet) as bar:
            for r in range(options.repeats):
                for w in options.workers if r % 2 == 0 else options.workers[::-1]:
                    load0, cpu0, t0 = os.getloadavg()[0], _cpu_seconds(), time.perf_counter()
                    generate(preset, Path(tmp) / f"run{r}_w{w}", workers=w)
                    wall, cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
                    runs[w].append({"wall_s": wall, "cpu_s": cpu, "load_before": load0,
                                    "load_after": os.getloadavg()[0]})
                    bar.update(1)
        per_frame = {w: (1e3 * statistics.median(x["wall_s"] for x in rs) / options.frames,
                         1e3 * statistics.median(x["cpu_s"] for x in rs) / options.frames) for w, rs in runs.items()}
        first = options.workers[0]
        size = f"{preset.width}x{preset.height}"
        figures = []
        for w, (wall, cpu) in per_frame.items():
            ref: dict[str, Any] = {} if w == first else {
                "reference": per_frame[first][0], "reference_cpu": per_frame[first][1],
                "reference_label": f"{first} worker{'s' if first > 1 else ''}"}
            figures.append(Figure(
                f"synth {options.preset}, {options.frames} frames at {size}: time per frame, "
                f"{w} worker{'s' if w > 1 else ''}", wall, "ms", cpu=cpu,
                goal=f"<= {GOAL_MS_PER_FRAME:g} ms (100 frames in 300 s)" if size == "640x480" else None, **ref))
        data = {"preset": options.preset, "frames": options.frames, "width": preset.width, "height": preset.height,
                "runs": {str(w): rs for w, rs in runs.items()}}
        return Outcome(figures, data)
