"""Scenario files and sets: exact round trips, one-line errors naming the key and the value, and a scenario made
concrete on a hand-made map (filled slots, nearest free target, start drawn from the seed)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from parksim.env import slot_pose
from parksim.scenarios import (
    Scenario,
    ScenarioError,
    ScenarioSet,
    dump_scenario,
    load_scenario,
    load_scenarios,
    load_set,
    prepare,
    scenario_schema,
    write_set,
)
from parksim.scenarios.spec import draw, parse_scenario
from parksim.vehicle import Obstacles, VehicleParams, footprint

FULL = {
    "name": "backing-out", "scene": "scene1", "difficulty": "hard", "seed": 7,
    "ego": {"region": {"x": [6.0, 9.0], "y": [-0.4, 0.4], "yaw": [-0.1, 0.1]}},
    "target": 3, "occupy": [2, 4], "time_limit": 40.0, "tolerance": {"position": 0.3, "heading": 6.0},
    "actors": [
        {"name": "parked", "asset": "car", "pose": [30.0, 5.65, 1.5707963267948966]},
        {"name": "leaving", "asset": "car", "pose": [22.5, 5.65, 1.5707963267948966],
         "behaviour": {"type": "path", "waypoints": [[22.5, 1.0, -1], [35.0, 1.0]], "speed": [1.0, 1.5],
                       "start_time": [0.0, 3.0]}},
        {"name": "through", "asset": "assets/van", "box": [-1.0, 4.2, -1.0, 1.0], "pose": [-5.0, -1.5, 0.0],
         "behaviour": {"type": "lane", "waypoints": [[45.0, -1.5]], "speed": 2.5, "headway": 1.2}},
        {"name": "walker", "asset": "pedestrian", "pose": [15.0, -6.0, 1.5707963267948966],
         "behaviour": {"type": "pedestrian", "to": [15.0, 6.0], "speed": [1.0, 1.6],
                       "trigger": {"time": 12.0, "distance": 4.0}}},
    ],
}


def _write(path, data):
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_full_scenario_round_trips_exactly(tmp_path):
    s = load_scenario(_write(tmp_path / "in.yaml", FULL))
    assert [a.behaviour.type for a in s.actors] == ["static", "path", "lane", "pedestrian"]
    assert s.actors[1].behaviour.waypoints[0] == (22.5, 1.0, -1.0) and s.actors[1].behaviour.speed == (1.0, 1.5)
    dump_scenario(s, tmp_path / "out.yaml")
    again = load_scenario(tmp_path / "out.yaml")
    assert again == s
    dump_scenario(again, tmp_path / "out2.yaml")
    assert (tmp_path / "out2.yaml").read_text() == (tmp_path / "out.yaml").read_text()


def test_the_documented_example_is_a_valid_scenario():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "scenarios.md").read_text()
    example = doc.split("```yaml\n", 1)[1].split("```", 1)[0]
    assert parse_scenario(yaml.safe_load(example), "docs/scenarios.md") == parse_scenario(FULL, "full")


def test_floats_survive_the_round_trip_bit_for_bit(tmp_path):
    odd = [math.pi / 3, 0.1 + 0.2, 1e-17 + 5.0, np.nextafter(12.0, 13.0).item()]
    s = parse_scenario({"name": "f", "scene": "x", "ego": {"pose": odd[:3]}, "time_limit": odd[3]}, "f")
    dump_scenario(s, tmp_path / "f.yaml")
    back = load_scenario(tmp_path / "f.yaml")
    assert back.ego.pose == tuple(odd[:3]) and back.time_limit == odd[3]


def test_defaults_grade_as_the_env_does():
    s = parse_scenario({"name": "d", "scene": "x", "ego": {"pose": [0, 0, 0]}}, "d")
    assert s.target == "nearest_free" and s.difficulty == "easy" and s.actors == () and s.occupy == ()
    assert s.tolerance.position == 0.35 and math.radians(s.tolerance.heading) == pytest.approx(0.15, abs=1e-15)


def _bad(change):
    data = json.loads(json.dumps(FULL))
    change(data)
    return data


def _set(path, value):
    def change(data):
        *keys, last = path
        node = data
        for k in keys:
            node = node[k]
        node[last] = value
    return change


@pytest.mark.parametrize("change, expected", [
    (_set(["actors", 1, "behaviour", "speed"], -1), "actors.1.behaviour.speed: must be > 0, got -1"),
    (_set(["actors", 1, "behaviour", "speed"], [2, 1]), "actors.1.behaviour.speed: [2, 1] runs backwards"),
    (_set(["actors", 1, "behaviour", "speed"], "fast"), "actors.1.behaviour.speed: Input should be a valid number"),
    (_set(["actors", 1, "behaviour", "waypoints", 0], [1, 2, 5]),
     "actors.1.behaviour.waypoints.0: must be [x, y] or [x, y, -1] (reversing to it), got [1, 2, 5]"),
    (_set(["actors", 1, "behaviour", "type"], "fly"), "actors.1.behaviour: Input tag 'fly'"),
    (_set(["actors", 2, "behaviour", "headway"], 0), "actors.2.behaviour.headway: Input should be greater than 0"),
    (_set(["actors", 2, "behaviour", "head_way"], 1), "actors.2.behaviour.head_way: Extra inputs are not permitted"),
    (_set(["actors", 2, "box"], [4, 1, -1, 1]), "actors.2.box: [4, 1, -1, 1] is not [x_min, x_max, y_min, y_max]"),
    (_set(["actors", 3, "behaviour", "trigger"], {}), "actors.3.behaviour.trigger: give time, distance or both"),
    (_set(["actors", 3, "behaviour", "to"], [15.0, -6.0]), "actors.3: behaviour.to: [15, -6] repeats the point"),
    (_set(["actors", 3, "name"], "parked"), "actors: names must be unique, repeated: parked"),
    (_set(["actors", 0, "pose", 2], float("nan")), "actors.0.pose.2: Input should be a finite number, got nan"),
    (_set(["ego", "pose"], [1, 2, 3]), "ego: give exactly one of pose: [x, y, yaw] or region"),
    (_set(["ego", "region", "yaw"], [0.1, -0.1]), "ego.region.yaw: [0.1, -0.1] runs backwards"),
    (_set(["tolerance", "heading"], 120), "tolerance.heading: Input should be less than or equal to 90, got 120"),
    (_set(["target"], "nearest"), "target: Input should be a valid integer"),
    (_set(["target"], 2), "target: slot 2 is also in occupy"),
    (_set(["difficulty"], "extreme"), "difficulty: Input should be 'easy', 'medium' or 'hard', got 'extreme'"),
    (_set(["version"], 2), "version: Input should be 1, got 2"),
    (_set(["name"], "two words"), "name: String should match pattern"),
    (lambda d: d.pop("scene"), "scene: Field required"),
])
def test_errors_are_one_line_naming_the_key_and_value(tmp_path, change, expected):
    path = _write(tmp_path / "bad.yaml", _bad(change))
    with pytest.raises(ScenarioError) as e:
        load_scenario(path)
    message = str(e.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    assert expected in message, message


def test_unreadable_or_non_yaml_files_are_one_line(tmp_path):
    for path, text, expected in [(tmp_path / "missing.yaml", None, "cannot read"),
                                 (tmp_path / "broken.yaml", "name: [unclosed\n  x: {", "not valid YAML"),
                                 (tmp_path / "list.yaml", "- 1\n- 2\n", "expected a mapping at the top level")]:
        if text is not None:
            path.write_text(text)
        with pytest.raises(ScenarioError, match=expected) as e:
            load_scenario(path)
        assert "\n" not in str(e.value) and str(path) in str(e.value)


def test_a_set_round_trips_and_its_index_is_checked(tmp_path):
    base = parse_scenario(FULL, "full")
    scenarios = tuple(base.model_copy(update={"name": f"s{i:02d}", "seed": i, "difficulty": d})
                      for i, d in enumerate(["easy", "medium", "hard"]))
    folder = write_set(tmp_path / "set", ScenarioSet("graded", scenarios))
    loaded = load_set(folder)
    assert loaded == ScenarioSet("graded", scenarios)
    assert load_scenarios(folder) == list(scenarios)
    assert load_scenarios(folder / "s01.yaml") == [scenarios[1]]
    with pytest.raises(FileExistsError):
        write_set(folder, loaded)
    dump_scenario(scenarios[1].model_copy(update={"difficulty": "easy"}), folder / "s01.yaml")
    with pytest.raises(ScenarioError, match=r"index.yaml: scenarios.1: lists 's01' \(medium\) but s01.yaml holds "
                                            r"'s01' \(easy\)"):
        load_set(folder)
    with pytest.raises(ScenarioError, match="not a scenario set"):
        load_set(tmp_path)
    with pytest.raises(ValueError, match="names must be unique"):
        write_set(tmp_path / "twice", ScenarioSet("x", scenarios[:1] * 2))


def test_the_json_schema_accepts_the_files_it_describes_and_refuses_a_bad_one(tmp_path):
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(json.dumps(scenario_schema()))
    dump_scenario(parse_scenario(FULL, "full"), tmp_path / "s.yaml")
    jsonschema.validate(yaml.safe_load((tmp_path / "s.yaml").read_text()), schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(_bad(_set(["actors", 1, "behaviour", "accel"], "quick")), schema)


def test_draw_takes_one_draw_whether_a_number_or_a_range():
    a, b = np.random.default_rng(3), np.random.default_rng(3)
    assert draw(2.5, a) == 2.5 and draw((1.0, 1.0), a) == 1.0
    b.random(), b.random()
    u = b.random()
    assert draw((1.0, 3.0), a) == 1.0 + 2.0 * u


# --- a scenario made concrete on a hand-made map -----------------------------------------------------------
def _slot(i: int, x0: float) -> dict:
    """A 2.5 m x 5.3 m perpendicular slot above the aisle y = 0, entrance at y = 3."""
    return {"id": i, "occupied": False,
            "corners": [[x0, 3.0], [x0 + 2.5, 3.0], [x0 + 2.5, 8.3], [x0, 8.3]]}


MAP = {"garage": {"x": [0.0, 40.0], "y": [-10.0, 10.0], "lanes": [0.0]},
       "slots": [_slot(i, 10.0 + 2.5 * i) for i in range(6)],
       "obstacles": [{"kind": "pillar", "center": [9.0, 3.5], "size": [0.6, 0.6], "yaw": 0.0}]}


def test_prepare_fills_slots_and_picks_the_given_target():
    s = parse_scenario(FULL, "full")
    setup = prepare(s, MAP)
    assert setup.slot["id"] == 3 and not setup.slot["occupied"]
    assert [x["occupied"] for x in setup.world_map["slots"]] == [False, False, True, False, True, False]
    assert not any(x["occupied"] for x in MAP["slots"]), "the input map is left as it was"
    cars = setup.world_map["obstacles"][1:]
    for slot_id, car, pose in zip((2, 4), cars, setup.parked):
        centre, yaw = slot_pose(MAP["slots"][slot_id])
        assert car["kind"] == "car" and car["center"] == pytest.approx(centre.tolist(), abs=1e-12)
        assert car["size"] == [4.5, 1.8] and car["yaw"] == yaw and pose == pytest.approx((*centre, yaw), abs=1e-12)
    assert (setup.pos_tol, setup.yaw_tol, setup.max_steps) == (0.3, math.radians(6.0), 400)


def test_prepare_draws_the_same_clear_start_from_the_same_seed():
    s = parse_scenario(FULL, "full")
    starts = {prepare(s.model_copy(update={"seed": seed}), MAP).start for seed in (0, 0, 1, 2)}
    assert len(starts) == 3, "one start per seed, different seeds differ"
    obstacles = Obstacles(prepare(s, MAP).world_map["obstacles"])
    region = s.ego.region
    for seed in range(20):
        x, y, yaw = prepare(s.model_copy(update={"seed": seed}), MAP).start
        assert region.x[0] <= x <= region.x[1] and region.y[0] <= y <= region.y[1]
        assert region.yaw[0] <= yaw <= region.yaw[1]
        assert not obstacles.hits(footprint((x, y, yaw), VehicleParams(), 0.3)).any()


def test_nearest_free_target_is_the_free_slot_nearest_the_ego():
    s = parse_scenario({"name": "n", "scene": "x", "ego": {"pose": [14.0, 0.0, 0.0]}, "occupy": [2]}, "n")
    # body centre at x = 14 + 1.4 = 15.4: slot 2 (centre x 16.25) is filled, slot 1 (13.75) is 1.65 m, slot 3 3.35 m
    assert prepare(s, MAP).slot["id"] == 1


@pytest.mark.parametrize("update, expected", [
    ({"target": 9}, "target: slot 9 is not in the map"),
    ({"occupy": (9,)}, "occupy.0: slot 9 is not in the map"),
    ({"ego": {"pose": (8.0, 3.0, 0.0)}}, "ego.pose: the body at [8.0, 3.0, 0.0] touches"),
    ({"ego": {"region": {"x": (8.5, 9.5), "y": (3.0, 4.0), "yaw": (0.0, 0.0)}}}, "ego.region: no start 0.3 m clear"),
])
def test_prepare_errors_name_the_key(update, expected):
    data = {"name": "e", "scene": "x", "ego": {"pose": [20.0, 0.0, 0.0]}, **update}
    with pytest.raises(ScenarioError, match=f"scenario 'e': {expected.replace('[', '.').replace(']', '.')}"):
        prepare(Scenario.model_validate(data), MAP)


def test_prepare_refuses_an_occupied_target():
    taken = {**MAP, "slots": [{**MAP["slots"][0], "occupied": True}, *MAP["slots"][1:]]}
    s = parse_scenario({"name": "o", "scene": "x", "ego": {"pose": [20.0, 0.0, 0.0]}, "target": 0}, "o")
    with pytest.raises(ScenarioError, match="target: slot 0 is occupied"):
        prepare(s, taken)
