"""The scenario ``Episode`` in closed loop and ``ParkingEnv(scenario=)``: Hybrid A* parks an easy scenario, a
pedestrian crossing behind the reversing ego is hit when the planner ignores it, runs repeat exactly, the env
equals the bare ``Episode``, actors are drawn into the views, and the env without a scenario is as before.

The scene is scene1's garage as a 300-Gaussian bundle; the scenario files are written with ``parksim.scenarios``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from parksim.env import ParkingEnv
from parksim.planners import HybridAStarParker
from parksim.render.actors import Actor
from parksim.scenarios import ActorSpec, Scenario, ScenarioSet, dump_scenario, write_set
from parksim.scenarios.episode import Episode, load_actor_asset
from parksim.scenarios.spec import EgoStart, PedestrianSpec, Region, TriggerSpec
from parksim.scenarios.task import slot_pose
from parksim.sim import LocalSim
from parksim.vehicle import VehicleParams, car_centre
from sim_fixtures import easy_scenario, make_bundle

SEED = 2
"""A scene1 start from which Hybrid A* reverses all the way into its slot (tests/test_hybrid_astar.py)."""


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("episode") / "scene1", preset="scene1", n=300, bev_px=64)


@pytest.fixture(scope="module")
def sim(bundle):
    return LocalSim(bundle)


@pytest.fixture(scope="module")
def easy(sim):
    """The env's random start of ``SEED`` and the slot Hybrid A* picks from it, as a scenario."""
    return easy_scenario(sim, SEED)


def _park(env: ParkingEnv) -> tuple[list[np.ndarray], dict]:
    """Reset with seed 0 and drive the episode with Hybrid A* (``_drive``)."""
    obs, _ = env.reset(seed=0)
    return _drive(env, obs)


def _drive(env: ParkingEnv, obs: dict) -> tuple[list[np.ndarray], dict]:
    """From the reset observation, plan into the env's target slot with Hybrid A* (no actors: it ignores them)
    and track the path until the episode ends; the actions and the last info."""
    parker = HybridAStarParker()
    x, y, yaw = (float(v) for v in obs["pose"])
    path = parker.plan((x, y, yaw), env.slot, env.obstacles)
    assert path is not None, parker.result
    parker.follow(path)
    actions, terminated, truncated = [], False, False
    while not (terminated or truncated):
        actions.append(parker.act(obs))
        obs, _, terminated, truncated, info = env.step(actions[-1])
    return actions, info


@pytest.fixture(scope="module")
def parked(sim, easy, tmp_path_factory):
    """The easy scenario driven in the env: (actions, last info, the episode)."""
    path = tmp_path_factory.mktemp("easy") / "easy.yaml"
    dump_scenario(easy, path)
    env = ParkingEnv(sim=sim, cameras=[], privileged=True, scenario=path)
    actions, info = _park(env)
    return actions, info, env.episode


def test_hybrid_astar_parks_the_easy_scenario(parked, easy):
    actions, info, episode = parked
    card = info["scorecard"]
    assert info["is_success"] and not info["truncated"] and card.success, card
    assert card.final_distance < easy.tolerance.position and card.final_heading_error < easy.tolerance.heading
    assert card.steps == len(actions) and card.static_collisions == card.actor_collisions == 0
    assert card.min_clearance_actors is None and card.min_clearance_static > 0
    assert card.direction_changes == 0 and (episode.log.speeds < 0).any(), "it reversed in, in one go"
    assert card.to_dict() == episode.result().to_dict()
    assert math.isclose(card.time, len(actions) * VehicleParams().dt, rel_tol=0, abs_tol=1e-12)


def _walker(parked, easy) -> tuple[Scenario, float]:
    """The easy scenario plus a pedestrian that crosses the ego's path behind it, reaching the point under the
    ego's body centre at step k (on the way in, reversing) exactly when the ego gets there: 3 m at 1 m/s."""
    _, _, episode = parked
    log = episode.log
    k = int(0.6 * (len(log.t) - 1))
    assert log.speeds[k] < 0, "the ego reverses there"
    x, y, yaw = log.poses[k]
    p = car_centre((x, y, yaw), VehicleParams())
    side = np.array([-math.sin(yaw), math.cos(yaw)])
    start, to = p + 3.0 * side, p - 3.0 * side
    heading = math.atan2(*(to - start)[::-1])
    walker = ActorSpec(name="walker", asset="pedestrian", pose=(*start.tolist(), heading),
                       behaviour=PedestrianSpec(type="pedestrian", to=tuple(to.tolist()), speed=1.0,
                                                trigger=TriggerSpec(time=round(float(log.t[k]) - 3.0, 1))))
    return easy.model_copy(update={"name": "walker", "difficulty": "hard", "actors": (walker,)}), float(log.t[k])


def test_a_pedestrian_crossing_behind_is_hit_when_the_planner_ignores_it(sim, parked, easy, tmp_path):
    scenario, when = _walker(parked, easy)
    dump_scenario(scenario, tmp_path / "walker.yaml")
    env = ParkingEnv(sim=sim, cameras=[], privileged=True, scenario=tmp_path / "walker.yaml")
    actions, info = _park(env)
    card = info["scorecard"]
    assert info["actor_collision"] and info["collision"] and not info["is_success"] and not info["truncated"]
    assert not card.success and card.actor_collisions == 1 and card.static_collisions == 0
    assert card.min_clearance_actors == 0.0
    assert card.first_actor_collision <= when + 1e-9, "the ego drives as in the easy run until it hits the walker"
    np.testing.assert_array_equal(actions, parked[0][:len(actions)])
    with pytest.raises(RuntimeError, match="is over"):
        env.episode.step(np.zeros(2))


def test_same_set_same_seed_same_scorecards_and_the_env_is_the_episode(sim, parked, easy, tmp_path):
    walker, _ = _walker(parked, easy)
    wandering = walker.model_copy(update={
        "name": "wandering", "seed": 11, "ego": EgoStart(pose=None, region=Region(
            x=(easy.ego.pose[0] - 0.2, easy.ego.pose[0] + 0.2), y=(-0.2, 0.2),
            yaw=(easy.ego.pose[2] - 0.05, easy.ego.pose[2] + 0.05))),
        "actors": (walker.actors[0].model_copy(update={"behaviour": walker.actors[0].behaviour.model_copy(
            update={"speed": (0.6, 1.4)})}),)})
    folder = write_set(tmp_path / "set", ScenarioSet("two", (easy, wandering)))
    cards, names = [], []
    for _ in range(2):
        env = ParkingEnv(sim=sim, cameras=[], privileged=True, scenario=folder)
        for seed in (0, 1):
            obs, info = env.reset(seed=seed)
            names.append(info["scenario"])
            _, last = _drive(env, obs)
            cards.append(last["scorecard"].to_dict())
    assert cards[:2] == cards[2:] and names[:2] == names[2:]
    assert names[:2] == ["wandering", "easy"], "the env's seed samples the set"
    episode = Episode(wandering, sim.info()["map"])      # state-only, no env
    env = ParkingEnv(sim=sim, cameras=[], privileged=True, scenario=folder)
    obs, info = env.reset(seed=0)
    assert info["scenario"] == "wandering" and env.state.pose != tuple(easy.ego.pose), "drawn from the region"
    actions, last = _drive(env, obs)
    replayed = [episode.reset()]
    for a in actions:
        replayed.append(episode.step(a)[0])
    assert episode.done and episode.result().to_dict() == last["scorecard"].to_dict()


def test_actors_and_parked_cars_are_drawn_into_the_views(sim, easy, tmp_path):
    slots = sim.info()["map"]["slots"]
    start = np.array(easy.ego.pose[:2])
    near = min((s for s in slots if s["id"] != easy.target and not s.get("occupied")),
               key=lambda s: float(np.linalg.norm(slot_pose(s)[0] - start)))
    standing = ActorSpec(name="standing", asset="pedestrian", pose=(start[0] + 6.0, start[1] + 1.5, 0.0))
    scenario = easy.model_copy(update={"occupy": (near["id"],), "actors": (standing,)})
    dump_scenario(scenario, tmp_path / "drawn.yaml")
    env = ParkingEnv(sim=sim, cameras=[], bev=True, scale=0.25, scenario=tmp_path / "drawn.yaml")
    obs, _ = env.reset(seed=0)
    filled = next(s for s in env.world_map["slots"] if s["id"] == near["id"])
    assert filled["occupied"] and len(env.obstacles) == len(ParkingEnv(sim=sim, cameras=[]).obstacles) + 1, \
        "the filled slot is an obstacle"
    pose = env.state.pose
    bare = sim.render(pose, [], bev=True, scale=0.25).bev
    car_pose = env.episode.setup.parked[0]
    drawn = sim.render(pose, [], bev=True, scale=0.25, actors=[
        Actor(load_actor_asset("car"), car_pose), Actor(load_actor_asset("pedestrian"), standing.pose)]).bev
    assert (obs["bev"] != bare).any(axis=-1).sum() > 20, "the parked car and the pedestrian show in the BEV"
    np.testing.assert_array_equal(obs["bev"], drawn)
    state_only = ParkingEnv(sim=sim, cameras=[], scenario=tmp_path / "drawn.yaml")
    assert set(state_only.reset(seed=0)[0]) == {"state"}
    with pytest.raises(ValueError, match="do not apply with scenario="):
        env.reset(options={"slot": near["id"]})


def test_without_a_scenario_the_env_is_as_before(sim):
    """Random start and slot, no scenario keys in the info, never truncated, the documented reward."""
    env = ParkingEnv(sim=sim, cameras=[], privileged=True)
    _, info = env.reset(seed=5)
    assert env.episode is None and env.scenarios == ()
    keys = {"slot", "distance", "heading_error", "collision", "is_success", "speed", "pose"}
    assert set(info) == keys
    rng = np.random.default_rng(0)
    before = info["distance"] + 0.5 * info["heading_error"]
    for _ in range(30):
        _, r, terminated, truncated, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        assert set(info) == keys and not truncated
        after = info["distance"] + 0.5 * info["heading_error"]
        expected = before - after - 0.01 + 10.0 * info["is_success"] - 10.0 * info["collision"]
        assert abs(r - expected) <= 4 * np.spacing(max(abs(before), abs(after), 10.0)), (r, expected)
        before = after
        if terminated:
            break


def test_the_hybrid_scenario_planner_yields_to_the_walker_and_parks(sim, parked, easy):
    """The same walker, against ``scenarios run``'s hybrid planner: it plans around the walker's predicted footprints
    and stands while the walker is on the path just ahead, so it parks without touching it (where the blind run
    above hits it), and its run repeats exactly."""
    from parksim.planners.scenario_planners import make_planner
    from parksim.planners.scenario_runs import run_scenarios

    scenario, _ = _walker(parked, easy)
    first, again = (run_scenarios([scenario], sim.info()["map"], None, "hybrid")[0] for _ in range(2))
    assert first.outcome == "parked", first.card
    assert first.card.actor_collisions == 0 and first.card.min_clearance_actors > 0
    assert first.card.to_dict() == again.card.to_dict()
    assert make_planner("hybrid").privileged and not make_planner("hybrid").bev
