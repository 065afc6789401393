"""``parksim scenarios``: make a graded scenario set from a scene bundle (``make``), run a planner over a set and
score it (``run``), print the scenario file format's JSON Schema (``schema``)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from ..device import DEVICE_HELP
from .argtypes import integer, number

__all__ = ["add_parser", "run"]

_PLANNERS = ("geometric", "hybrid", "perception")   # parksim.planners.scenario_planners.PLANNERS, unimported


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``scenarios make``, ``scenarios run`` and ``scenarios schema`` (cheap: no heavy imports)."""
    p = sub.add_parser("scenarios", help="make graded scenario sets, run planners over them and score them",
                       description="Closed-loop parking scenarios (docs/scenarios.md): YAML files that fix a scene, "
                                   "the ego's start, the target slot, parked cars and moving actors.")
    modes = p.add_subparsers(dest="mode", metavar="MODE", required=True)
    make = modes.add_parser(
        "make", help="write a graded set (easy, medium, hard) on a scene bundle's map",
        description="Write COUNT scenarios on BUNDLE's slot map, split evenly over easy (a free slot, nothing "
                    "moving), medium (the target's neighbours taken by parked cars) and hard (medium plus cars "
                    "driving and backing out, pedestrians crossing), each checked to fit the map, plus a BEV "
                    "thumbnail each (thumbnails/NAME.png: the first frame from above, actors drawn in). Same "
                    "bundle, COUNT and SEED: the same files. OUTPUT appears only when complete.")
    make.add_argument("bundle", type=Path, help="scene bundle folder (with a map.json)")
    make.add_argument("-o", "--output", type=Path, required=True, help="set folder to write")
    make.add_argument("--count", type=integer(1, 10_000), default=30, help="scenarios in the set (default: 30)")
    make.add_argument("--seed", type=integer(0), default=0, help="seed of the set (default: 0)")
    make.add_argument("--name", help="the set's name (default: SCENE-graded, SCENE the bundle's folder name)")
    make.add_argument("--no-thumbnails", dest="thumbnails", action="store_false",
                      help="skip the BEV thumbnails (they render the scene once per scenario)")
    make.add_argument("--device", default="cpu", help=DEVICE_HELP + "; for the thumbnails")
    make.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    go = modes.add_parser(
        "run", help="drive a planner through every scenario of a set and score it",
        description="Run each scenario of SET (a set folder or one scenario file) in closed loop with PLANNER and "
                    "write OUTPUT: results.json (the summary per difficulty and every episode's scorecard: the same "
                    "bytes for the same set and planner), timings.json, results.md (the scorecard table) and "
                    "plots/NAME.png (each trajectory over the scene's BEV map). Planners: geometric (privileged "
                    "forward Dubins path, blind to actors), hybrid (privileged Hybrid A* around the actors' "
                    "predicted footprints, yielding), perception (BEV slot detector, dead reckoning; needs "
                    "--detector), or module:Class (your own: see docs/scenarios.md).")
    go.add_argument("set", type=Path, help="scenario set folder, or one scenario file")
    go.add_argument("--planner", default="hybrid",
                    help=f"{', '.join(_PLANNERS)} or module:Class (default: hybrid)")
    go.add_argument("-o", "--output", type=Path, help="results folder (default: SET/runs/PLANNER)")
    go.add_argument("--scenes", type=Path, help="folder of scene bundles the scenarios' scene names are looked up "
                                                "in (after the path as written and relative to SET)")
    go.add_argument("--bundle", type=Path, help="run every scenario on this bundle, whatever its scene says")
    go.add_argument("--detector", type=Path, help="slot detector checkpoint (perception; parksim detector train)")
    go.add_argument("--scale", type=number(0.01, 1.0), default=0.5,
                    help="fisheye render scale of the perception planner's BEV (default: 0.5)")
    go.add_argument("--device", default="cpu", help=DEVICE_HELP + "; for views and plots")
    go.add_argument("--ray", action="store_true", help="run the episodes as Ray tasks (same results)")
    go.add_argument("--address", help="Ray cluster to join with --ray (default: the running one or a new local "
                                      "one)")
    go.add_argument("--no-plots", dest="plots", action="store_false", help="skip the trajectory plots")
    go.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    go.add_argument("--quiet", action="store_true", help="no progress bars")
    modes.add_parser("schema", help="print the scenario file format as JSON Schema",
                     description="Print the JSON Schema (draft 2020-12) of a scenario file, for editors and tools "
                                 "outside Python.")
    return p


def _bar(total: int, desc: str, quiet: bool) -> Any:
    """A tqdm bar on stderr."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=quiet, dynamic_ncols=True)


def _make(args: argparse.Namespace) -> int:
    """``scenarios make``: the set, its thumbnails, one line saying what was written."""
    from collections import Counter

    from ..bundle import read_map
    from ..imageio import write_image
    from ..scenarios import write_set
    from ..scenarios.make import make_set
    from .outputs import check_output_folder

    check_output_folder(args.output, overwrite=args.overwrite)
    world_map = read_map(args.bundle)
    if not world_map:
        raise ValueError(f"{args.bundle}: no map.json (a scene bundle with a slot map is needed)")
    scene = os.path.relpath(args.bundle.resolve(), args.output.resolve())   # the set moves with its scene
    made = make_set(world_map, scene, args.count, args.seed, args.name)

    def thumbnails(folder: Path) -> None:
        from ..scenarios.episode import Episode
        from ..scenarios.pictures import thumbnail
        from ..sim import LocalSim

        sim = LocalSim(args.bundle, device=args.device)
        (folder / "thumbnails").mkdir()
        with _bar(len(made.scenarios), "thumbnails", False) as bar:
            for s in made.scenarios:
                episode = Episode(s, world_map, sim, cameras=[], bev=True, asset_root=folder)
                write_image(folder / "thumbnails" / f"{s.name}.png", thumbnail(episode))
                bar.update(1)

    write_set(args.output, made, overwrite=args.overwrite, extra=thumbnails if args.thumbnails else None)
    counts = Counter(s.difficulty for s in made.scenarios)
    print(f"wrote {args.output}: set {made.name!r}, {len(made.scenarios)} scenarios ("
          + ", ".join(f"{n} {d}" for d, n in counts.items()) + f") on {args.bundle}")
    return 0


def _run(args: argparse.Namespace) -> int:
    """``scenarios run``: every episode with progress, the results folder, the summary table on stdout."""
    from ..planners.scenario_report import summary_table, write_run
    from ..planners.scenario_runs import run_set
    from ..scenarios import load_scenarios
    from .outputs import check_output_folder

    out = args.output or (args.set if args.set.is_dir() else args.set.parent) / "runs" / args.planner.replace(
        ":", "_")
    check_output_folder(out, overwrite=args.overwrite)
    total = len(load_scenarios(args.set))
    with _bar(total, f"{args.planner} episodes", args.quiet) as bar:
        result = run_set(args.set, args.planner, scenes=args.scenes, bundle=args.bundle, detector=args.detector,
                         device=args.device, scale=args.scale, ray=args.ray, address=args.address,
                         done=lambda _: bar.update(1))
    with _bar(total if args.plots else 0, "plots", args.quiet or not args.plots) as bar:
        write_run(result, out, plots=args.plots, overwrite=args.overwrite, device=args.device,
                  done=lambda _: bar.update(1))
    print(summary_table({"": result.runs}))
    print(f"wrote {out}: results.json, results.md, timings.json" + (", plots/" if args.plots else ""))
    return 0


def run(args: argparse.Namespace) -> int:
    """Dispatch to the mode."""
    if args.mode == "make":
        return _make(args)
    if args.mode == "run":
        return _run(args)
    from ..scenarios import scenario_schema

    print(json.dumps(scenario_schema(), indent=1))
    return 0
