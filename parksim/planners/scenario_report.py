"""A scenario set run written down: ``results.json``, ``timings.json``, a markdown scorecard table, trajectory plots.

``results.json`` holds only what the episodes did, so the same set, planner and seeds give the same bytes;
``timings.json`` holds what took how long. ``results.md`` is the card table (per difficulty, then per episode) and
``plots/NAME.png`` each episode's trajectory over the scene's BEV map (the simulator's own BEVs stitched,
``parksim.scenarios.pictures``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np

from ..fileio import atomic_directory
from ..scenarios.score import Scorecard
from .scenario_runs import OUTCOMES, EpisodeRun, SetRun, by_difficulty

__all__ = ["markdown", "write_run", "summary_table", "SUMMARY_HEADER"]

SUMMARY_HEADER = ("| set | episodes | parked | collision | no path | out of time | final dist. p50 (cm) | "
                  "heading p50 (deg) | time p50 (s) | path p50 (m) | dir. changes p50 | jerk p90 (m/s^3) |")
"""The summary table's header (``summary_table`` puts the rows under it)."""


def _p50(cards: Sequence[Scorecard], field: str, scale: float = 1.0) -> str:
    """The median of a card field, or a dash without episodes."""
    values = [getattr(c, field) * scale for c in cards]
    return f"{median(values):.1f}" if values else "-"


def _summary_rows(runs: Sequence[EpisodeRun], label: str = "") -> list[str]:
    """The summary table's rows: all episodes, then each difficulty present, each named after ``label``."""
    rows = []
    for group, chosen in by_difficulty(runs).items():
        cards = [r.card for r in chosen]
        n = len(chosen)
        counts = [sum(r.outcome == o for r in chosen) for o in OUTCOMES]
        share = " | ".join(f"{c} ({100 * c / n:.0f} %)" for c in counts)
        parked = [r.card for r in chosen if r.outcome == "parked"]
        jerk = float(np.percentile([c.peak_jerk for c in cards], 90))
        rows.append(f"| {label}{group} | {n} | {share} | {_p50(parked, 'final_distance', 100)} | "
                    f"{_p50(parked, 'final_heading_error')} | {_p50(cards, 'time')} | {_p50(cards, 'path_length')} | "
                    f"{_p50(cards, 'direction_changes')} | {jerk:.1f} |")
    return rows


def summary_table(runs: Mapping[str, Sequence[EpisodeRun]]) -> str:
    """The summary table: ``SUMMARY_HEADER``, its rule and the rows of each group of runs (all, per difficulty).

    Args:
        runs: label -> episodes; each group's rows start with its label ("" for one group).

    Returns:
        Markdown lines.
    """
    rule = "| --- " * (SUMMARY_HEADER.count("|") - 1) + "|"
    return "\n".join([SUMMARY_HEADER, rule, *(row for label, group in runs.items()
                                                for row in _summary_rows(group, label))])


def _clearance(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def markdown(result: SetRun, plots: bool = True) -> str:
    """``results.md``: the summary per difficulty, then one row per episode (linking its plot).

    Args:
        result: the set run.
        plots: link each episode's plot.

    Returns:
        The markdown text.
    """
    lines = [f"# {result.planner} on scenario set {result.name}", "",
             "Parked, collision, no path, out of time: episodes (share). Final distance and heading: medians over "
             "the parked episodes; time, path length and direction changes: medians over all.", "",
             summary_table({"": result.runs}), "",
             "| scenario | difficulty | outcome | final dist. (cm) | heading (deg) | contacts static / actors | "
             "min. clearance static / actors (m) | time (s) | path (m) | dir. changes | peak jerk (m/s^3) |",
             "| --- " * 11 + "|"]
    for r in result.runs:
        c = r.card
        name = f"[{r.scenario}](plots/{r.scenario}.png)" if plots else r.scenario
        lines.append(f"| {name} | {r.difficulty} | {r.outcome} | {100 * c.final_distance:.1f} | "
                     f"{c.final_heading_error:.1f} | {c.static_collisions} / {c.actor_collisions} | "
                     f"{_clearance(c.min_clearance_static)} / {_clearance(c.min_clearance_actors)} | {c.time:.1f} | "
                     f"{c.path_length:.1f} | {c.direction_changes} | {c.peak_jerk:.1f} |")
    return "\n".join(lines) + "\n"


def write_run(result: SetRun, out: str | Path, *, plots: bool = True, overwrite: bool = False,
              device: str = "cpu", done: Callable[[str], None] | None = None) -> Path:
    """Write a set run's folder; it appears only when complete.

    Args:
        result: the set run.
        out: the folder to write.
        plots: draw ``plots/NAME.png`` per episode over each scene's BEV map (renders the map once per scene).
        overwrite: replace ``out`` if it exists.
        device: where the BEV map renders.
        done: called with each plot's scenario name as it is written (progress).

    Returns:
        The folder.

    Raises:
        FileExistsError: ``out`` exists and ``overwrite`` is False.
    """
    with atomic_directory(Path(out), overwrite=overwrite) as tmp:
        (tmp / "results.json").write_text(result.results_json())
        (tmp / "timings.json").write_text(json.dumps({"episodes": result.timings()}, indent=1) + "\n")
        (tmp / "results.md").write_text(markdown(result, plots))
        if plots:
            _plot(result, tmp / "plots", device, done)
    return Path(out)


def _plot(result: SetRun, folder: Path, device: str, done: Callable[[str], None] | None) -> None:
    """One trajectory plot per episode over its scene's BEV map."""
    from ..bundle import read_map
    from ..scenarios.pictures import bev_mosaic, plot_episode
    from ..sim import LocalSim

    folder.mkdir()
    maps: dict[str, Any] = {}
    for r in result.runs:
        scene = r.scene
        if scene not in maps:
            bundle = result.scenes[scene]
            maps[scene] = bev_mosaic(LocalSim(bundle, device=device), read_map(bundle) or {})
        plot_episode(r.log, r.card, maps[scene], folder / f"{r.scenario}.png",
                     f"{result.planner}: {r.scenario} ({r.difficulty}), {r.outcome}")
        if done is not None:
            done(r.scenario)

