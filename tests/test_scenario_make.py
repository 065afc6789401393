"""Graded scenario sets made from a scene's map (``parksim.scenarios.make``): deterministic, split by level, every
scenario valid on its map, easy free, medium's neighbours filled, hard's actors moving without starting on anything
and never running into an ego that stays put, unusable slots skipped, one-line errors."""

from __future__ import annotations

import copy
import functools
import itertools
import json
import math
from typing import Any

import numpy as np
import pytest

from parksim.planners import HybridAStarParker
from parksim.scenarios import ScenarioSet, World, ego_actor, load_set, make_set, prepare, write_set
from parksim.scenarios.resolve import START_MARGIN
from parksim.scenarios.shapes import box_polygon, overlap_matrix, overlaps
from parksim.scenarios.task import slot_pose
from parksim.synth.generate import scene_map
from parksim.synth.layout import build_garage
from parksim.synth.presets import get_preset
from parksim.vehicle import Obstacles, VehicleParams, footprint

PRESETS = ("tiny", "scene1", "worn", "busy")
VEHICLE = VehicleParams()


@functools.cache
def _map(preset: str) -> dict[str, Any]:
    """The preset's world map as ``map.json`` holds it (through JSON, as the command reads it)."""
    return json.loads(json.dumps(scene_map(build_garage(get_preset(preset).layout)), default=float))


def world_map(preset: str) -> dict[str, Any]:
    """A fresh copy of the preset's map (the tests may change it)."""
    return copy.deepcopy(_map(preset))


@functools.cache
def graded(preset: str) -> ScenarioSet:
    """A 12-scenario set of the preset (4 of each level)."""
    return make_set(world_map(preset), preset, 12, 0)


def _region_bodies(region) -> np.ndarray:
    """``[9, 4, 2]`` the ego's bodies, grown by the start margin, at the corners and the middle of a start region."""
    poses = [*itertools.product(region.x, region.y, region.yaw),
             tuple((a + b) / 2 for a, b in (region.x, region.y, region.yaw))]
    return np.stack([footprint(p, VEHICLE, START_MARGIN) for p in poses])


def _row_neighbours(slot: dict[str, Any], slots: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Slots sharing an entrance mark with ``slot``, or with an entrance on the same line within 1.5 m."""
    def entrance(s):
        c = np.asarray(s["corners"])
        return float(c[:2, 1].mean()), float(c[:2, 0].min()), float(c[:2, 0].max())
    y, lo, hi = entrance(slot)
    near = []
    for s in slots:
        sy, slo, shi = entrance(s)
        if s["id"] != slot["id"] and ({s["p1"], s["p2"]} & {slot["p1"], slot["p2"]}
                                      or (abs(sy - y) < 0.01 and max(slo - hi, lo - shi) <= 1.5)):
            near.append(s)
    return near


def test_the_same_map_count_and_seed_give_an_equal_set():
    made = make_set(world_map("scene1"), "scene1", 12, 5)
    assert make_set(world_map("scene1"), "scene1", 12, 5) == made
    assert make_set(world_map("scene1"), "scene1", 12, 6) != made
    # a scenario's draws depend on its level and number only, not on the count or the other levels
    medium = make_set(world_map("scene1"), "scene1", 5, 5, difficulties=("medium",))
    assert medium.scenarios[:4] == made.scenarios[4:8]
    assert len({s.seed for s in made.scenarios}) == 12


def test_the_count_is_split_over_the_levels_in_order():
    made = make_set(world_map("tiny"), "scenes/tiny", 10, 0)
    assert made.name == "tiny-graded"
    assert [s.name for s in made.scenarios] == [
        "easy_000", "easy_001", "easy_002", "easy_003", "medium_000", "medium_001", "medium_002",
        "hard_000", "hard_001", "hard_002"]
    assert [s.difficulty for s in made.scenarios] == ["easy"] * 4 + ["medium"] * 3 + ["hard"] * 3
    assert {s.scene for s in made.scenarios} == {"scenes/tiny"}
    two = make_set(world_map("tiny"), "tiny", 3, 0, name="mine", difficulties=("hard", "easy"))
    assert two.name == "mine"
    assert [s.name for s in two.scenarios] == ["hard_000", "hard_001", "easy_000"]


@pytest.mark.parametrize("preset", PRESETS)
def test_every_scenario_prepares_on_its_map_starting_on_the_lane_towards_the_slot(preset):
    m = world_map(preset)
    lanes = m["garage"]["lanes"]
    for s in graded(preset).scenarios:
        setup = prepare(s, m)
        assert isinstance(s.target, int) and setup.slot["id"] == s.target
        x, y, yaw = setup.start
        assert min(abs(y - lane) for lane in lanes) <= 0.3 + 1e-9
        centre, _ = slot_pose(setup.slot)
        assert math.cos(yaw) * (centre[0] - x) > 0, f"{s.name}: the ego starts facing away from its slot"
        assert s.ego.region is not None and s.ego.region.x[1] - s.ego.region.x[0] <= 1.0 + 1e-9


@pytest.mark.parametrize("preset", PRESETS)
def test_easy_is_free_and_medium_and_hard_fill_the_targets_neighbours(preset):
    m = world_map(preset)
    for s in graded(preset).scenarios:
        setup = prepare(s, m)
        if s.difficulty == "easy":
            assert s.occupy == () and s.actors == ()
            continue
        slots = setup.world_map["slots"]
        neighbours = _row_neighbours(setup.slot, slots)
        assert neighbours, f"{s.name}: target {s.target} has no neighbour"
        assert all(n["occupied"] for n in neighbours), f"{s.name}: a neighbour of {s.target} is free"
        assert set(s.occupy) <= {n["id"] for n in slots if n["occupied"]}
        if s.difficulty == "medium":
            assert s.actors == ()


@pytest.mark.parametrize("preset", PRESETS)
def test_hard_actors_move_and_start_clear_of_the_ego_the_map_and_each_other(preset):
    m = world_map(preset)
    hard = make_set(m, preset, 12, 0, difficulties=("hard",)).scenarios
    assert len(hard) == 12
    for s in hard:
        assert any(a.behaviour.type != "static" for a in s.actors), f"{s.name}: no moving actor"
        assert {a.asset for a in s.actors} <= {"car", "pedestrian"}
        setup = prepare(s, m)
        starts = np.stack([box_polygon(a.pose, a.resolved_box()) for a in s.actors])
        blocked = Obstacles(setup.world_map["obstacles"]).corners()
        assert not overlap_matrix(starts, blocked).any(), f"{s.name}: an actor starts on an obstacle"
        assert not overlap_matrix(starts, _region_bodies(s.ego.region)).any(), f"{s.name}: on the ego's region"
        together = overlap_matrix(starts, starts)
        assert not together[~np.eye(len(starts), dtype=bool)].any(), f"{s.name}: two actors start together"


def test_hard_actors_never_run_into_an_ego_that_stays_put_the_map_or_each_other():
    runs = [(m, s) for preset in ("scene1", "worn", "busy") for m in [world_map(preset)]
            for s in make_set(m, preset, 6, 1, difficulties=("hard",)).scenarios]
    assert {a.name for _, s in runs for a in s.actors} == {"car_through", "car_leaving", "walker_crossing",
                                                           "walker_passing"}
    for m, s in runs:
        setup = prepare(s, m)
        body = footprint(setup.start, VEHICLE)
        blocked = Obstacles(setup.world_map["obstacles"]).corners()
        world = World.from_scenario(s)
        ego = ego_actor(setup.start, 0.0, VEHICLE)
        moved = np.zeros(len(s.actors), bool)
        for _ in range(200):                                  # 20 s: every trigger and start time has passed
            before = world.polygons()
            after = np.stack([a.polygon() for a in world.step(ego)])
            moved |= np.abs(after - before).max((1, 2)) > 1e-6
            assert not overlaps(after, body[None]).any(), f"{s.name}: an actor ran into the standing ego"
            assert not overlap_matrix(after, blocked).any(), f"{s.name}: an actor ran into an obstacle"
            met = overlap_matrix(after, after)
            assert not met[~np.eye(len(after), dtype=bool)].any(), f"{s.name}: two actors ran into each other"
        on_their_own = [a.behaviour.type == "path" or (a.behaviour.type == "pedestrian"
                                                       and a.behaviour.trigger.time is not None) for a in s.actors]
        assert moved[on_their_own].all(), f"{s.name}: an actor that needs no ego to start stood still for 20 s"


def test_every_easy_and_medium_target_of_tiny_has_a_parking_path():
    m = world_map("tiny")
    for s in graded("tiny").scenarios:
        if s.difficulty == "hard":
            continue
        setup = prepare(s, m)
        path = HybridAStarParker().plan(setup.start, setup.slot, Obstacles(setup.world_map["obstacles"]))
        assert path is not None, f"{s.name}: no collision-free path from the start into slot {s.target}"


def test_a_slot_whose_entrance_is_blocked_is_never_a_target_and_none_left_is_an_error():
    m = world_map("tiny")
    targets = {s.target for s in graded("tiny").scenarios}
    blocked = sorted(targets)[0]
    slot = next(s for s in m["slots"] if s["id"] == blocked)
    corners = np.asarray(slot["corners"])
    entrance = corners[:2].mean(0)
    into = corners[2:].mean(0) - entrance
    pillar = entrance - into / np.linalg.norm(into)                      # 1 m out of the slot, in the aisle
    m["obstacles"].append({"kind": "pillar", "center": pillar.tolist(), "size": [0.7, 0.7], "yaw": 0.0})
    assert blocked not in {s.target for s in make_set(m, "tiny", 12, 0).scenarios}
    for s in m["slots"]:
        s["occupied"] = True
    with pytest.raises(ValueError, match="no free slot of the map fits easy scenarios"):
        make_set(m, "tiny", 3, 0)


def test_a_made_set_round_trips_through_its_folder(tmp_path):
    made = graded("scene1")
    write_set(tmp_path / "set", made)
    assert load_set(tmp_path / "set") == made


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"count": 0}, "count must be an integer >= 1, got 0"),
    ({"seed": -1}, "seed must be an integer >= 0"),
    ({"difficulties": ("easy", "extreme")}, "difficulties must be distinct levels of easy, medium, hard"),
    ({"difficulties": ("easy", "easy")}, "difficulties must be distinct"),
    ({"difficulties": ()}, "difficulties must be distinct"),
    ({"name": "bad name"}, "set name 'bad name' must be"),
    ({"scene": ""}, "scene must name a scene bundle"),
])
def test_bad_arguments_are_one_line_errors(kwargs, message):
    args = {"world_map": world_map("tiny"), "scene": "tiny", "count": 3, "seed": 0} | kwargs
    with pytest.raises(ValueError, match=message) as e:
        make_set(**args)
    assert "\n" not in str(e.value)


def test_a_map_without_lanes_is_refused():
    m = world_map("tiny")
    del m["garage"]["lanes"]
    with pytest.raises(ValueError, match=r"no aisle lanes \(garage.lanes\)"):
        make_set(m, "tiny", 3, 0)
