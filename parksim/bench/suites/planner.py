"""``parksim bench planner``: how often each planner parks in ``ParkingEnv`` from the same seeded random starts.

Planners (``--planners``):

- ``geometric``: the privileged baseline (``parksim.planners.run_episode``): world pose and map, picks the free slot
  with the shortest collision-free forward path and drives it in closed loop; renders nothing.
- ``hybrid``: the same privileged episode with ``HybridAStarParker``: Hybrid A* over Reeds-Shepp curves (forward and
  reverse, head-in or reversed in), tracked with its cusps; renders nothing.
- ``perception``: no world pose (``parksim.planners.perception``): a DMPR-style detector on the rendered BEV every
  ``--every`` steps, dead reckoning, the geometric planner's path and controller. It is told the slot the geometric
  planner chose at the same start (in the ego frame, as the non-privileged observation gives it); run alone, it
  takes the env's own target slot of that seed. Its detector is trained here on the simulator's own BEVs of the
  bundle (``parksim.planners.slot_data``: random aisle and slot-entry poses drawn from ``--train-seed``, labelled
  from the map), reused from the work folder when trained before with the same options.

The scene is a bundle of surface Gaussians on a synth garage (``parksim.bench.scenes.surface_bundle``), or
``--bundle``. Episode ``k`` uses seed ``--seed + k``; both planners get the same start. Every episode ends by 500
steps (50 s simulated).
"""

from __future__ import annotations

import hashlib
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from statistics import median
from typing import Any

from ..common import Timing, progress, set_threads
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["PlannerSuite", "PlannerOptions", "PLANNERS", "train_detector"]

PLANNERS = {"geometric": "privileged geometric planner (world pose + map)",
            "perception": "perception planner (BEV detector + dead reckoning)",
            "hybrid": "privileged Hybrid A* planner (world pose + map, reverses)"}
"""The planners this suite drives, with how figures name them."""


@dataclass(frozen=True)
class PlannerOptions:
    """Options of ``parksim bench planner``."""

    planners: list[str] = field(default_factory=lambda: ["geometric", "perception"], metadata={
        "help": "planners to run on the same starts: geometric (privileged), perception (the geometric one is its "
                "reference), hybrid (privileged Hybrid A*, opt-in)"})
    episodes: int = field(default=30, metadata={"help": "episodes (seeds --seed .. --seed + episodes - 1)", "low": 1,
                                                "quick": 2})
    bundle: Path | None = field(default=None, metadata={
        "help": "scene bundle with a slot map (default: --gaussians surface Gaussians of synth --preset, made under "
                "--work)"})
    preset: str = field(default="scene1", metadata={"help": "synth preset the bundle is made from without --bundle",
                                                    "quick": "tiny"})
    gaussians: int = field(default=150_000, metadata={
        "help": "Gaussians of the bundle made without --bundle (only the perception planner renders them)", "low": 1,
        "quick": 3000})
    scale: float = field(default=0.5, metadata={"help": "fisheye render scale the BEV is made from", "low": 0.01,
                                                "high": 1.0})
    every: int = field(default=5, metadata={"help": "steps between the perception planner's BEVs", "low": 1})
    train_bevs: int = field(default=120, metadata={"help": "rendered BEVs the detector trains on", "low": 1,
                                                   "quick": 4})
    train_steps: int = field(default=1200, metadata={"help": "detector training steps", "low": 1, "quick": 3})
    input_size: int = field(default=256, metadata={"help": "detector input side in px (a multiple of 32)", "low": 32})
    train_seed: int = field(default=1000, metadata={
        "help": "seed of the training poses and weights (not an episode seed)"})
    threads: int = field(default=2, metadata={
        "help": "torch/numba threads of the episodes (the detector trains on one: on a loaded 2-core machine a "
                "second one mostly spins)", "low": 1})

    def __post_init__(self) -> None:
        unknown = [p for p in self.planners if p not in PLANNERS]
        if unknown or not self.planners:
            raise ValueError(f"--planners: choose from {', '.join(PLANNERS)}, got {','.join(self.planners)!r}")
        if self.input_size % 32:
            raise ValueError(f"--input-size must be a multiple of 32, got {self.input_size}")


def _outcome(r: dict[str, Any]) -> str:
    """How an episode ended."""
    return ("parked" if r["is_success"] else "collision" if r["collision"] else
            "no path found" if not r["planned"] else "not parked in time")


def _episode(r: dict[str, Any], wall_s: float, cpu_s: float) -> dict[str, Any]:
    """The fields of an episode's final info the record keeps, with its outcome and time."""
    keep = {"outcome": _outcome(r), "slot": r.get("slot"), "steps": r["steps"], "distance": r["distance"],
            "heading_error": r["heading_error"], "wall_s": wall_s, "cpu_s": cpu_s}
    return keep | {k: r[k] for k in ("perceived", "views") if k in r}


def _summary(episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """Parked count, outcomes and, over the parked episodes, steps and final errors (median and max)."""
    parked = [e for e in episodes if e["outcome"] == "parked"]
    out: dict[str, Any] = {"parked": len(parked), "episodes": len(episodes),
                           "outcomes": dict(sorted(Counter(e["outcome"] for e in episodes).items())),
                           "wall_s": sum(e["wall_s"] for e in episodes), "cpu_s": sum(e["cpu_s"] for e in episodes),
                           "episode_ms": Timing(1e3 * median(e["wall_s"] for e in episodes),
                                                1e3 * median(e["cpu_s"] for e in episodes), len(episodes))}
    if parked:
        for key in ("steps", "distance", "heading_error"):
            out[key] = {"median": median(e[key] for e in parked), "max": max(e[key] for e in parked)}
    return out


def _timed(fn: Any, *args: Any, **kwargs: Any) -> tuple[dict[str, Any], float, float]:
    """``fn(*args, **kwargs)`` and its wall and process-CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = fn(*args, **kwargs)
    return result, time.perf_counter() - wall, time.process_time() - cpu


def train_detector(bundle: Path, folder: Path, *, bevs: int, steps: int, input_size: int, seed: int, scale: float,
                   quiet: bool) -> tuple[Any, dict[str, Any]]:
    """Render ``bevs`` training BEVs of ``bundle`` at fisheye scale ``scale`` and train a DMPR detector ``steps``
    steps from ``seed`` (each reused when ``folder`` has it from the same options); the model and what making it
    cost here (wall and process-CPU seconds; zero when reused)."""
    from ...planners.slot_data import write_training_bevs
    from ...recon.detectors import load_detector
    from ...recon.detectors.train import TrainOptions
    from .detectors import train_stages

    wall, cpu = time.perf_counter(), time.process_time()
    data = folder / f"bevs_{bevs}_seed{seed}_scale{scale:g}"
    if not data.is_dir():
        write_training_bevs(bundle, data, bevs, seed=seed, scale=scale)
    model = folder / f"dmpr_{input_size}px_on_{data.name}"
    train = TrainOptions(arch="dmpr", input_size=input_size, lr=3e-3, seed=seed, threads=1)
    meta = train_stages([data], model, [steps], train, progress=not quiet)
    cost = {"model": str(model), "bevs": str(data), "train_seconds": meta["total_train_seconds"],
            "made_here": {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}}
    return load_detector(model), cost


class PlannerSuite(Suite):
    """Parked / total of the geometric and perception planners from the same random starts."""

    name = "planner"
    help = "parked/total of the geometric and perception planners from the same starts"
    description = ("Drive ParkingEnv from --episodes seeded random starts with each of --planners: the privileged "
                   "geometric planner, and the perception planner (BEV detector trained here on the bundle's "
                   "rendered BEVs, dead reckoning), told the slot the geometric planner chose; with --planners "
                   "hybrid also the privileged Hybrid A* planner. Figures: the share of episodes parked per planner "
                   "(the reference of the others: the geometric one on the same starts), and the median time of an "
                   "episode (wall and process CPU). Data: every episode's outcome, steps, final centre and heading "
                   "errors, and the detector's training cost.")
    Options = PlannerOptions

    def run(self, options: PlannerOptions, context: Context) -> Outcome:
        """Make or reuse the bundle (and detector), then run every episode with each planner in turn."""
        import gymnasium as gym

        from ...env import MAX_EPISODE_STEPS, ParkingEnv
        from ...planners import HybridAStarParker, run_episode
        from ...planners.perception import PerceptionParker, run_perception_episode
        from ...sim import LocalSim
        from ..scenes import surface_bundle

        set_threads(options.threads)
        if options.bundle is None:
            folder = context.work / "planner" / f"{options.preset}_{options.gaussians}_seed{context.seed}"
            bundle, scene = folder / "bundle", options.preset
            if not (bundle / "bundle.json").is_file():
                surface_bundle(bundle, options.preset, options.gaussians, context.seed)
        else:   # the detector's training data of a given bundle go to the work folder, one folder per bundle
            bundle, scene = options.bundle, options.bundle.name
            key = hashlib.sha256(str(bundle.resolve()).encode()).hexdigest()[:8]
            folder = context.work / "planner" / f"{scene}_{key}"
        data: dict[str, Any] = {"bundle": str(bundle)}
        privileged = perception = None
        if {"geometric", "hybrid"} & set(options.planners):   # one privileged env drives both, episode by episode
            privileged = gym.wrappers.TimeLimit(ParkingEnv(bundle=bundle, cameras=[], privileged=True),
                                               MAX_EPISODE_STEPS)
        if "perception" in options.planners:
            detector, data["detector"] = train_detector(
                bundle, folder, bevs=options.train_bevs, steps=options.train_steps, input_size=options.input_size,
                seed=options.train_seed, scale=options.scale, quiet=context.quiet)
            set_threads(options.threads)   # the detector trained on one thread
            perception = ParkingEnv(bundle=bundle, cameras=[], bev=True, scale=options.scale)
            assert isinstance(perception.sim, LocalSim)   # made from a bundle
            spec = perception.sim.bundle.rig.bev
            data["bev"] = {"width": spec.width, "m_per_px": spec.m_per_px}
        runs: dict[str, list[dict[str, Any]]] = {p: [] for p in options.planners}
        seeds = range(context.seed, context.seed + options.episodes)
        with progress(options.episodes, "bench planner", context.quiet) as bar:
            for seed in seeds:
                slot = None
                if "geometric" in runs:
                    r, wall, cpu = _timed(run_episode, privileged, seed)
                    runs["geometric"].append(_episode(r, wall, cpu))
                    slot = r.get("slot")
                if "hybrid" in runs:
                    r, wall, cpu = _timed(run_episode, privileged, seed, HybridAStarParker())
                    runs["hybrid"].append(_episode(r, wall, cpu))
                if perception is not None:
                    r, wall, cpu = _timed(run_perception_episode, perception, seed,
                                          PerceptionParker(detector, spec, every=options.every),
                                          options=None if slot is None else {"slot": slot},
                                          max_steps=MAX_EPISODE_STEPS)
                    runs["perception"].append(_episode(r, wall, cpu))
                bar.update(1)
        summaries = {p: _summary(episodes) for p, episodes in runs.items()}
        data.update(seeds=list(seeds), summaries=summaries, episodes=runs)
        if "geometric" in runs and "perception" in runs:
            data["both_parked"] = sum(g["outcome"] == p["outcome"] == "parked"
                                      for g, p in zip(runs["geometric"], runs["perception"]))
        return Outcome(_figures(summaries, scene, options.episodes), data)


def _figures(summaries: dict[str, dict[str, Any]], scene: str, episodes: int) -> list[Figure]:
    """Share parked per planner (the others against the geometric one) and the median episode time."""
    share = {p: 100.0 * s["parked"] / s["episodes"] for p, s in summaries.items()}
    figures = []
    for planner, s in summaries.items():
        where = f"{PLANNERS[planner]} on {scene}"
        ref = share.get("geometric") if planner != "geometric" else None
        figures.append(Figure(f"{where}: parked, {episodes} random starts", share[planner], "%", reference=ref,
                              reference_label=None if ref is None else PLANNERS["geometric"], better="higher"))
        figures.append(Figure(f"{where}: one episode (median of {episodes})", s["episode_ms"].wall_ms, "ms",
                              cpu=s["episode_ms"].cpu_ms))
    return figures
