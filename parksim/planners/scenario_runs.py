"""Run a planner over a scenario set: every episode in closed loop, scored, in order or spread over Ray workers.

``run_scenarios`` drives ``Episode``s (``parksim.scenarios.episode``) with a planner of ``scenario_planners``; the
episode renders only for a planner that looks (its BEV on the steps it asks for), so privileged planners run on the
map alone. Everything an episode does follows from its scenario's seed and the planner's own deterministic code, so
a set run twice, or on Ray, gives the same results (``results.json``); the time each episode took is kept apart
(``timings.json``), as it is the one thing that differs.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..bundle import Bundle, is_bundle, read_map
from ..scenarios.episode import Episode
from ..scenarios.score import EpisodeLog, Scorecard, aggregate
from ..scenarios.spec import Scenario, ScenarioError
from ..vehicle import VehicleParams
from .scenario_planners import ScenarioPlanner, check_planner, make_planner

__all__ = ["EpisodeRun", "SetRun", "drive", "run_scenarios", "run_set", "resolve_scene", "summarise", "by_difficulty",
           "OUTCOMES"]

OUTCOMES = ("parked", "collision", "no path found", "not parked in time")
"""How an episode ends, in the order tables list them."""


@dataclass(frozen=True)
class EpisodeRun:
    """One scenario driven to its end.

    Attributes:
        scenario: the scenario's name.
        scene: its scene.
        difficulty: its grade.
        outcome: one of ``OUTCOMES``.
        status: the planner's own word on why it gave up ("" when it did not).
        card: its scorecard.
        log: what happened (for plots).
        wall_s: seconds it took.
        cpu_s: process-CPU seconds it took.
    """

    scenario: str
    scene: str
    difficulty: str
    outcome: str
    status: str
    card: Scorecard
    log: EpisodeLog
    wall_s: float
    cpu_s: float

    def to_dict(self) -> dict[str, Any]:
        """What ``results.json`` keeps of it (no times: those go to ``timings.json``).

        Returns:
            ``scenario``, ``scene``, ``difficulty``, ``outcome``, ``status`` and the ``scorecard`` as plain JSON
            types.
        """
        return {"scenario": self.scenario, "scene": self.scene, "difficulty": self.difficulty, "outcome": self.outcome,
                "status": self.status, "scorecard": self.card.to_dict()}


def drive(episode: Episode, planner: ScenarioPlanner) -> str:
    """Drive a begun episode with ``planner`` until it ends or the planner gives up.

    Args:
        episode: the episode, begun (``begin``); made with the renderer, BEV and privilege the planner needs.
        planner: the planner.

    Returns:
        The outcome (``OUTCOMES``).
    """
    world = episode if planner.privileged else None
    planner.start(world, episode.observe(episode.frame()))
    view = None
    while not episode.done:
        obs = view if view is not None else episode.observe(None) if planner.privileged else None
        action = planner.act(world, obs)
        if action is None:
            break
        if planner.wants_view:
            view, _, _, _ = episode.step(action)
        else:
            episode.advance(action)
            view = None
    card = episode.result()
    if card.success:
        return "parked"
    if card.collided:
        return "collision"
    return "no path found" if planner.status else "not parked in time"


def run_scenarios(scenarios: Sequence[Scenario], world_map: dict[str, Any], bundle: Bundle | str | Path | None,
                  planner: str, *, detector: str | Path | None = None, device: str = "cpu", scale: float = 0.5,
                  asset_root: str | Path | None = None, vehicle: VehicleParams = VehicleParams(),
                  done: Callable[[EpisodeRun], None] | None = None) -> list[EpisodeRun]:
    """Drive each scenario with a fresh planner, in order.

    Args:
        scenarios: the scenarios (all on the scene of ``world_map``).
        world_map: the scene's map.
        bundle: the scene bundle, rendered only for a planner that looks (None: privileged planners only).
        planner: ``make_planner``'s spec.
        detector: the slot detector checkpoint (``perception``).
        device: where a looking planner's views render (``LocalSim``).
        scale: fisheye render scale its BEV is made from.
        asset_root: the folder actors' relative asset paths are read from.
        vehicle: the ego.
        done: called with each run as it ends (progress).

    Returns:
        One run per scenario, in order.

    Raises:
        ValueError: an unknown planner, or one that looks without a bundle.
        ScenarioError: a scenario that does not fit the map.
    """
    sim = None
    if planner == "perception" or make_planner(planner, vehicle).bev:
        if bundle is None:
            raise ValueError(f"planner {planner!r} looks at the views: give the scene bundle")
        from ..sim import LocalSim

        sim = LocalSim(bundle, device=device)
    bev_spec = sim.bundle.rig.bev if sim is not None else None
    model: Any = detector
    if planner == "perception" and detector is not None:   # read once, shared by every episode's fresh planner
        from ..recon.detectors import load_detector

        model = load_detector(Path(detector))
    runs = []
    for scenario in scenarios:
        agent = make_planner(planner, vehicle, model, bev_spec)
        wall, cpu = time.perf_counter(), time.process_time()
        episode = Episode(scenario, world_map, sim if agent.bev else None, cameras=[], bev=agent.bev, scale=scale,
                          privileged=agent.privileged, vehicle=vehicle, asset_root=asset_root)
        outcome = drive(episode, agent)
        run = EpisodeRun(scenario.name, scenario.scene, scenario.difficulty, outcome, agent.status, episode.result(),
                         episode.log, time.perf_counter() - wall, time.process_time() - cpu)
        runs.append(run)
        if done is not None:
            done(run)
    return runs


def resolve_scene(scene: str, set_folder: Path, scenes: Path | None = None) -> Path:
    """The bundle folder a scenario's ``scene`` names.

    Tried in order: the path as written (absolute, or relative to the working directory), relative to the set's
    folder, and under ``scenes``.

    Args:
        scene: ``Scenario.scene``.
        set_folder: the folder of the scenario files.
        scenes: a folder of bundles (``parksim serve --scenes``'s layout).

    Returns:
        The bundle folder (it holds ``bundle.json``).

    Raises:
        ScenarioError: no bundle there.
    """
    candidates = [Path(scene), set_folder / scene] + ([scenes / scene] if scenes is not None else [])
    for path in candidates:
        if is_bundle(path):
            return path
    tried = ", ".join(str(p) for p in dict.fromkeys(candidates))
    raise ScenarioError(f"scene {scene!r}: no scene bundle (bundle.json) at {tried}; give --scenes or --bundle")


def summarise(runs: Sequence[EpisodeRun]) -> dict[str, Any]:
    """The set's summary, over all episodes and per difficulty.

    Args:
        runs: the episodes.

    Returns:
        ``{"all": ..., "easy": ..., ...}``, each ``aggregate``'s card summary with ``outcomes`` counts.
    """
    return {name: aggregate([r.card for r in group]) | {
        "outcomes": {o: n for o in OUTCOMES if (n := Counter(r.outcome for r in group)[o])}}
        for name, group in by_difficulty(runs).items()}


def by_difficulty(runs: Sequence[EpisodeRun]) -> dict[str, list[EpisodeRun]]:
    """The runs grouped as the summaries show them.

    Args:
        runs: the episodes.

    Returns:
        ``"all"``, then each difficulty in the order it first appears -> its runs.
    """
    groups: dict[str, list[EpisodeRun]] = {"all": list(runs)}
    for run in runs:
        groups.setdefault(run.difficulty, []).append(run)
    return groups


@dataclass(frozen=True)
class SetRun:
    """A planner's runs over a scenario set.

    Attributes:
        name: the set's name (a file's scenario name for one file).
        planner: the planner's spec.
        runs: one per scenario, in the set's order.
        scenes: the bundle folder of each scene the set names.
    """

    name: str
    planner: str
    runs: list[EpisodeRun]
    scenes: dict[str, Path]

    def results(self) -> dict[str, Any]:
        """What ``results.json`` holds: the set, the planner, the summary and every episode (no times, no paths).

        Returns:
            Plain JSON types, the same for the same runs.
        """
        return {"set": self.name, "planner": self.planner, "scenes": sorted(self.scenes),
                "summary": summarise(self.runs), "episodes": [r.to_dict() for r in self.runs]}

    def timings(self) -> list[dict[str, Any]]:
        """What ``timings.json`` holds: each episode's wall and process-CPU seconds.

        Returns:
            ``{"scenario", "wall_s", "cpu_s"}`` per episode, in order.
        """
        return [{"scenario": r.scenario, "wall_s": r.wall_s, "cpu_s": r.cpu_s} for r in self.runs]

    def results_json(self) -> str:
        """``results.json``'s text.

        Returns:
            ``results()`` as indented JSON.
        """
        return json.dumps(self.results(), indent=1) + "\n"


def _slot_map(bundle: Path) -> dict[str, Any]:
    """A bundle's map, which scenarios need (``ScenarioError`` when it has none)."""
    world_map = read_map(bundle)
    if not world_map:
        raise ScenarioError(f"{bundle}: the scene has no map.json (scenarios need its slot map)")
    return world_map


def _chunk(scenarios: Sequence[Scenario], world_map: dict[str, Any], bundle: str, planner: str,
           options: dict[str, Any]) -> list[EpisodeRun]:
    """``run_scenarios`` in a Ray worker (the bundle is read there, from a path every node can read)."""
    return run_scenarios(scenarios, world_map, bundle, planner, **options)


def run_set(path: str | Path, planner: str, *, scenes: str | Path | None = None, bundle: str | Path | None = None,
            detector: str | Path | None = None, device: str = "cpu", scale: float = 0.5, ray: bool = False,
            address: str | None = None, done: Callable[[EpisodeRun], None] | None = None) -> SetRun:
    """Run ``planner`` over a scenario file or set folder, each scene's scenarios on its bundle.

    Args:
        path: a scenario file or set folder.
        planner: ``make_planner``'s spec.
        scenes: a folder of bundles the scenarios' ``scene`` names are looked up in (``resolve_scene``).
        bundle: the one bundle every scenario runs on, whatever its ``scene`` says.
        detector: the slot detector checkpoint (``perception``).
        device: where views render.
        scale: fisheye render scale of a looking planner's BEV.
        ray: spread the scenarios over Ray workers (one task per scenario; the running Ray instance, the cluster
            at ``address``, or a new local one); results are the same as in order.
        address: the Ray cluster to join.
        done: called with each run as it ends (progress; with Ray, in the order they end).

    Returns:
        The runs, in the set's order.

    Raises:
        ScenarioError: an invalid set, a scene without a bundle, or a scenario that does not fit its map.
        ValueError: an unknown planner.
    """
    from ..scenarios.spec import load_scenarios, load_set

    path = Path(path)
    scenarios = load_scenarios(path)
    name = load_set(path).name if path.is_dir() else scenarios[0].name
    folder = path if path.is_dir() else path.parent
    check_planner(planner, detector)   # before any bundle is read
    root = None if scenes is None else Path(scenes)
    bundles = {s.scene: resolve_scene(s.scene if bundle is None else str(bundle), folder, root) for s in scenarios}
    maps = {scene: _slot_map(b) for scene, b in bundles.items()}
    options: dict[str, Any] = {"detector": None if detector is None else str(Path(detector).resolve()),
                               "device": device, "scale": scale, "asset_root": str(folder.resolve())}
    if not ray:
        runs = [run for scene in bundles for run in run_scenarios(
            [s for s in scenarios if s.scene == scene], maps[scene], bundles[scene], planner, done=done, **options)]
        order = {s.name: i for i, s in enumerate(scenarios)}
        return SetRun(name, planner, sorted(runs, key=lambda r: order[r.scenario]), bundles)
    import ray as ray_module

    from ..recon.batch import ray_session

    with ray_session(address):
        task = ray_module.remote(num_cpus=1)(_chunk)
        pending = {task.remote([s], maps[s.scene], str(bundles[s.scene].resolve()), planner, options): i
                   for i, s in enumerate(scenarios)}
        results: dict[int, EpisodeRun] = {}
        while pending:
            ready, _ = ray_module.wait(list(pending), num_returns=1)
            run = ray_module.get(ready[0])[0]
            results[pending.pop(ready[0])] = run
            if done is not None:
                done(run)
    return SetRun(name, planner, [results[i] for i in range(len(scenarios))], bundles)
