"""``parksim bench scenarios``: the planner scorecard over graded scenario sets, one set per scene.

For each preset (``--presets``) a bundle of surface Gaussians is made on its synth garage
(``parksim.bench.scenes.surface_bundle``), a graded set of ``--count`` scenarios is made on its map
(``parksim.scenarios.make``, seed ``--seed``: a third each easy, medium and hard) and every planner of
``--planners`` drives every scenario (``parksim.planners.scenario_runs``):

- ``geometric``: the privileged forward Dubins planner, blind to the actors;
- ``hybrid``: privileged Hybrid A* around the actors' predicted footprints, yielding while it tracks;
- ``perception``: the BEV slot detector with dead reckoning (trained here on the bundle's own rendered BEVs, as
  ``parksim bench planner`` does), geometric paths with Hybrid A* where the geometric planner finds none.

Figures: the share parked per scene, planner and difficulty (against Hybrid A* in the same run; Hybrid A*'s easy
and medium against the goal of 90 %) and the median episode time per planner. The record's details are the full
scorecard tables (``benchmarks/RESULTS_scenarios.md``) with Hybrid A*'s misses on easy and medium by cause; the plot
draws every trajectory over each scene's BEV map, coloured by outcome.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from statistics import median
from typing import Any

from ..common import progress, pyplot, save_figure, set_threads
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["ScenariosSuite", "ScenariosOptions"]

_PLANNERS = ("geometric", "hybrid", "perception")
_GOAL = ">= 90 %"
_COLOURS = {"parked": "#2ca02c", "collision": "#d62728", "no path found": "#7f7f7f", "not parked in time": "#ff7f0e"}


@dataclass(frozen=True)
class ScenariosOptions:
    """Options of ``parksim bench scenarios``."""

    presets: list[str] = field(default_factory=lambda: ["scene1", "worn", "busy"], metadata={
        "help": "synth presets, one scene and one set each", "quick": ["tiny"]})
    count: int = field(default=30, metadata={"help": "scenarios per scene (a third each easy, medium, hard)",
                                             "low": 3, "quick": 3})
    planners: list[str] = field(default_factory=lambda: list(_PLANNERS), metadata={
        "help": "planners to score: geometric, hybrid, perception", "quick": ["geometric", "hybrid"]})
    gaussians: int = field(default=150_000, metadata={"help": "surface Gaussians of each scene's bundle", "low": 1,
                                                      "quick": 3000})
    scale: float = field(default=0.5, metadata={"help": "fisheye render scale of the perception planner's BEV",
                                                "low": 0.01, "high": 1.0})
    train_bevs: int = field(default=120, metadata={"help": "rendered BEVs the perception detector trains on",
                                                   "low": 1, "quick": 4})
    train_steps: int = field(default=1200, metadata={"help": "detector training steps", "low": 1, "quick": 3})
    input_size: int = field(default=256, metadata={"help": "detector input side in px (a multiple of 32)",
                                                   "low": 32})
    train_seed: int = field(default=1000, metadata={"help": "seed of the detector's training poses and weights"})
    threads: int = field(default=2, metadata={"help": "torch/numba threads", "low": 1})

    def __post_init__(self) -> None:
        unknown = [p for p in self.planners if p not in _PLANNERS]
        if unknown or not self.planners:
            raise ValueError(f"--planners: choose from {', '.join(_PLANNERS)}, got {','.join(self.planners)!r}")
        if self.input_size % 32:
            raise ValueError(f"--input-size must be a multiple of 32, got {self.input_size}")


class ScenariosSuite(Suite):
    """Scorecards of every planner over a graded scenario set per scene."""

    name = "scenarios"
    help = "scorecards of the planners over graded scenario sets (easy, medium, hard) per scene"
    description = ("Make a graded set of --count scenarios on each preset's garage (easy: a free slot; medium: its "
                   "neighbours parked in; hard: cars and pedestrians moving) and drive each with every planner of "
                   "--planners. Figures: the share parked per scene, planner and difficulty (Hybrid A* the "
                   "reference; its easy and medium against 90 %), the median episode time. Details: the full "
                   "scorecard tables and Hybrid A*'s misses by cause. Plot: every trajectory over the scene's BEV "
                   "map, coloured by outcome.")
    Options = ScenariosOptions

    def run(self, options: ScenariosOptions, context: Context) -> Outcome:
        """Make or reuse each scene's bundle, set and detector; run every planner over every set."""
        from ...bundle import is_bundle, read_map
        from ...planners.scenario_runs import run_set
        from ...scenarios import write_set
        from ...scenarios.make import make_set
        from ..scenes import surface_bundle
        from .planner import train_detector

        set_threads(options.threads)
        runs: dict[str, dict[str, Any]] = {}
        data: dict[str, Any] = {"scenes": {}}
        bundles: dict[str, Path] = {}
        for preset in options.presets:
            folder = context.work / "scenarios" / f"{preset}_{options.gaussians}_seed{context.seed}"
            bundle = bundles[preset] = folder / "bundle"
            if not is_bundle(bundle):
                surface_bundle(bundle, preset, options.gaussians, context.seed)
            world_map = read_map(bundle) or {}
            set_dir = folder / f"set_{options.count}_seed{context.seed}"
            made = make_set(world_map, os.path.relpath(bundle, set_dir), options.count, context.seed, preset)
            write_set(set_dir, made, overwrite=True)
            detector = None
            if "perception" in options.planners:
                _, cost = train_detector(bundle, folder, bevs=options.train_bevs, steps=options.train_steps,
                                         input_size=options.input_size, seed=options.train_seed,
                                         scale=options.scale, quiet=context.quiet)
                detector = cost["model"]
                data["scenes"].setdefault(preset, {})["detector"] = cost
                set_threads(options.threads)
            runs[preset] = {}
            for planner in options.planners:
                with progress(len(made.scenarios), f"{preset} {planner}", context.quiet) as bar:
                    runs[preset][planner] = run_set(set_dir, planner, bundle=bundle, detector=detector,
                                                    scale=options.scale, done=lambda _: bar.update(1))
            data["scenes"].setdefault(preset, {}).update(
                set=str(set_dir), bundle=str(bundle),
                planners={p: r.results() | {"timings": r.timings()} for p, r in runs[preset].items()})
        figures = _figures(runs, options.count)
        return Outcome(figures, data, lambda png: _plot(runs, bundles, png), _details(runs))


def _share(runs: list[Any], difficulty: str | None = None) -> tuple[float, int]:
    """Percent parked among the episodes of ``difficulty`` (all: None), and how many there are."""
    chosen = [r for r in runs if difficulty in (None, r.difficulty)]
    return 100.0 * sum(r.outcome == "parked" for r in chosen) / max(len(chosen), 1), len(chosen)


def _figures(runs: dict[str, dict[str, Any]], count: int) -> list[Figure]:
    """Parked share per scene, planner and difficulty; median episode time per scene and planner."""
    figures = []
    for preset, by_planner in runs.items():
        for planner, result in by_planner.items():
            reference = by_planner.get("hybrid") if planner != "hybrid" else None
            for difficulty in ("easy", "medium", "hard", None):
                share, n = _share(result.runs, difficulty)
                what = difficulty or "all"
                ref = None if reference is None else _share(reference.runs, difficulty)[0]
                figures.append(Figure(
                    f"{preset}, {planner}: parked, {what} ({n} of {count} scenarios)", share, "%", reference=ref,
                    reference_label=None if ref is None else "Hybrid A* on the same scenarios", better="higher",
                    goal=_GOAL if planner == "hybrid" and difficulty in ("easy", "medium") else None))
            wall = [r.wall_s for r in result.runs]
            cpu = [r.cpu_s for r in result.runs]
            figures.append(Figure(f"{preset}, {planner}: one episode (median of {len(wall)})", 1e3 * median(wall),
                                  "ms", cpu=1e3 * median(cpu)))
    return figures


def _details(runs: dict[str, dict[str, Any]]) -> str:
    """The scorecard tables per scene (every planner), and Hybrid A*'s misses on easy and medium by cause."""
    from ...planners.scenario_report import summary_table

    lines = ["Every planner drove the same scenarios. Parked, collision, no path, out of time: episodes (share). "
             "Final distance and heading: medians over the parked episodes; time, path length and direction changes: "
             "medians over all; jerk: the 90th percentile of the episodes' peak jerk.", ""]
    for preset, by_planner in runs.items():
        lines += [f"## {preset}", "", summary_table({f"{p}: ": r.runs for p, r in by_planner.items()})]
        hybrid = by_planner.get("hybrid")
        if hybrid is not None:
            missed = [r for r in hybrid.runs if r.difficulty in ("easy", "medium") and r.outcome != "parked"]
            lines += ["", f"Hybrid A* on easy and medium: {len(missed)} not parked" + (":" if missed else ".")]
            lines += [f"- {r.scenario} ({r.difficulty}): {r.status or r.outcome}" for r in missed]
        lines.append("")
    return "\n".join(lines)


def _plot(runs: dict[str, dict[str, Any]], bundles: dict[str, Path], png: Path) -> None:
    """A grid, scenes by planners: each scene's BEV map with every trajectory coloured by outcome."""
    from ...bundle import read_map
    from ...scenarios.pictures import bev_mosaic
    from ...sim import LocalSim

    plt = pyplot()
    presets, planners = list(runs), list(next(iter(runs.values())))
    fig, axes = plt.subplots(len(presets), len(planners), figsize=(4.2 * len(planners), 3.0 * len(presets)),
                             squeeze=False)
    for i, preset in enumerate(presets):
        bev = bev_mosaic(LocalSim(bundles[preset]), read_map(bundles[preset]) or {})
        for j, planner in enumerate(planners):
            ax = axes[i][j]
            ax.imshow(bev.image, extent=bev.extent, origin="upper")
            for r in runs[preset][planner].runs:
                xy = r.log.poses[:, :2]
                ax.plot(xy[:, 0], xy[:, 1], color=_COLOURS[r.outcome], lw=0.8, alpha=0.9)
                ax.plot(*xy[-1], marker="o", ms=2, color=_COLOURS[r.outcome])
            parked, n = _share(runs[preset][planner].runs)
            ax.set_title(f"{preset}: {planner} ({parked:.0f} % of {n} parked)", fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
    handles = [plt.Line2D([], [], color=c, label=o) for o, c in _COLOURS.items()]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8)
    fig.subplots_adjust(bottom=0.08)
    save_figure(fig, png)
