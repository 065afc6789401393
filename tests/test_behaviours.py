"""Actor behaviours and the world that steps them: speed profiles against their closed forms, IDM keeping its gap
and never passing, pedestrians setting off at the right step, determinism and predictions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from parksim.plugins import instantiate
from parksim.scenarios import BEHAVIOURS, Behaviour, World, ego_actor
from parksim.scenarios.behaviours import LANE_RESOLUTION
from parksim.scenarios.shapes import overlaps, polygon_distance
from parksim.scenarios.spec import ActorSpec

FAR = ego_actor((-100.0, -100.0, 0.0), 0.0)
"""An ego nowhere near the actors."""
HALF_CAR = 2.25


def _actor(name, pose, behaviour=None, asset="car"):
    return ActorSpec.model_validate({"name": name, "asset": asset, "pose": pose,
                                     **({"behaviour": behaviour} if behaviour else {})})


def _run(world, steps, ego=FAR):
    """States after each of ``steps`` steps: ``[steps + 1]`` tuples, time 0 first."""
    out = [world.states]
    for _ in range(steps):
        out.append(world.step(ego(world.t) if callable(ego) else ego))
    return out


def test_every_registered_behaviour_is_named_as_its_parameters():
    for name in BEHAVIOURS:
        b = instantiate(BEHAVIOURS, name, "parksim.scenarios", Behaviour, "behaviour")
        assert b.name == name and b.Options.model_fields["type"].annotation.__args__ == (name,)
    with pytest.raises(ValueError, match="unknown behaviour 'fly'"):
        instantiate(BEHAVIOURS, "fly", "parksim.scenarios", Behaviour, "behaviour")


def test_static_stands():
    world = World([_actor("s", [3.0, 4.0, 0.5])])
    assert all(s[0].pose == (3.0, 4.0, 0.5) and s[0].speed == 0 for s in _run(world, 20))


def test_path_follows_its_trapezoid():
    # 10 m at 2 m/s, accel 1, decel 2: 2 s and 2 m up, 1 s and 1 m down, 7 m cruising in 3.5 s: 6.5 s in all
    world = World([_actor("p", [0.0, 0.0, 0.0], {"type": "path", "waypoints": [[10.0, 0.0]], "speed": 2.0,
                                                 "accel": 1.0, "decel": 2.0})])
    states = [s[0] for s in _run(world, 80)]
    x = np.array([s.pose[0] for s in states])
    v = np.array([s.speed for s in states])
    t = np.arange(81) * 0.1
    expected = np.where(t < 2, 0.5 * t ** 2, np.where(t < 5.5, 2 + 2 * (t - 2), 10 - np.maximum(6.5 - t, 0) ** 2))
    np.testing.assert_allclose(x, expected, atol=64 * np.spacing(10.0))
    assert v.max() <= 2.0 and (v >= 0).all() and v[-1] == 0 and states[-1].pose == (10.0, 0.0, 0.0)


def test_a_short_leg_peaks_below_cruise():
    world = World([_actor("p", [0.0, 0.0, 0.0], {"type": "path", "waypoints": [[1.0, 0.0]], "speed": 5.0,
                                                 "accel": 1.0, "decel": 2.0})])
    peak = max(s[0].speed for s in _run(world, 40))
    assert peak <= math.sqrt(4 / 3) + 1e-12 and peak > math.sqrt(4 / 3) - 0.1 * 2.0


def test_path_reverses_out_then_drives_forward():
    world = World([_actor("p", [0.0, 0.0, math.pi / 2], {"type": "path", "waypoints": [[0.0, -5.0, -1], [5.0, -5.0]],
                                                         "speed": 1.0})])
    states = [s[0] for s in _run(world, 200)]
    backing = [s for s in states if s.speed < 0]
    forward = [s for s in states if s.speed > 0]
    assert backing and forward and all(s.pose[2] == pytest.approx(math.pi / 2, abs=1e-15) for s in backing)
    assert all(s.pose[2] == 0.0 for s in forward)
    switch = max(i for i, s in enumerate(states) if s.speed < 0)
    assert states[switch + 1].speed == 0.0 or states[switch + 1].pose[1] == pytest.approx(-5.0, abs=1e-12)
    assert states[-1].pose == (5.0, -5.0, 0.0) and states[-1].speed == 0.0


def _gap(follower, leader):
    """Bumper-to-bumper distance between two cars on the x axis, follower behind."""
    return (leader.pose[0] - HALF_CAR) - (follower.pose[0] + HALF_CAR)


LANE = {"type": "lane", "waypoints": [[80.0, 0.0]], "speed": 3.0, "initial_speed": 3.0, "min_gap": 2.0,
        "headway": 1.5}


def test_idm_stops_behind_a_standing_car_at_its_min_gap_and_never_touches_it():
    world = World([_actor("follower", [0.0, 0.0, 0.0], LANE), _actor("leader", [30.0, 0.0, 0.0])])
    states = _run(world, 400)
    gaps = np.array([_gap(*s) for s in states])
    x = np.array([s[0].pose[0] for s in states])
    assert (np.diff(x) >= 0).all() and gaps.min() > 0
    assert not any(overlaps(s[0].polygon(), s[1].polygon()) for s in states)
    # IDM stops near min_gap: discrete steps overshoot it by centimetres, and the gap it sees is short by up to
    # LANE_RESOLUTION (so it stops early by as much)
    assert abs(gaps[-1] - 2.0) < 0.01 + LANE_RESOLUTION and states[-1][0].speed < 1e-2


def test_idm_settles_behind_a_slower_car_at_its_time_gap_and_never_passes():
    slow = {"type": "path", "waypoints": [[400.0, 0.0]], "speed": 1.0, "accel": 10.0, "decel": 10.0}
    world = World([_actor("follower", [0.0, 0.0, 0.0], LANE), _actor("leader", [12.0, 0.0, 0.0], slow)])
    states = _run(world, 600)
    gaps = np.array([_gap(*s) for s in states])
    assert gaps.min() > 0
    # IDM's steady state behind a leader at v: s0 + v T (the free-road term (v / v0)^4 widens it a little)
    v, s0, T, v0 = 1.0, 2.0, 1.5, 3.0
    steady = (s0 + v * T) / math.sqrt(1 - (v / v0) ** 4)
    assert abs(gaps[-1] - steady) < LANE_RESOLUTION + 0.01 and states[-1][0].speed == pytest.approx(1.0, abs=1e-2)


def test_idm_keeps_its_gap_to_the_ego():
    world = World([_actor("follower", [0.0, 0.0, 0.0], LANE)])
    ego = ego_actor((20.0, 0.3, 0.0), 0.0)          # body from x = 19.05 to 23.75, in the lane
    states = _run(world, 300, ego)
    front = np.array([s[0].pose[0] + HALF_CAR for s in states])
    assert front.max() < 19.05 and 19.05 - front[-1] == pytest.approx(2.0, abs=LANE_RESOLUTION)


def test_idm_too_weak_to_brake_in_time_still_stops_at_contact():
    """accel 0.01 m/s^2 with no gap wanted: IDM alone would drive through; the step stops it at the leader."""
    weak = {**LANE, "accel": 0.01, "headway": 0.01, "min_gap": 0.0, "decel": 1e6}
    world = World([_actor("follower", [0.0, 0.0, 0.0], weak), _actor("leader", [30.0, 0.0, 0.0])])
    states = _run(world, 200)
    assert not any(overlaps(s[0].polygon(), s[1].polygon()) for s in states)
    assert 0 < _gap(*states[-1]) <= LANE_RESOLUTION and states[-1][0].speed == 0


def test_idm_stops_short_of_a_pedestrian_stepping_out_in_front():
    """Too close to brake comfortably: it still never moves its footprint into the pedestrian's."""
    walker = {"type": "pedestrian", "to": [7.0, 6.0], "speed": 1.5, "trigger": {"time": 0.0}}
    world = World([_actor("follower", [0.0, 0.0, 0.0], LANE), _actor("walker", [7.0, -3.0, math.pi / 2], walker,
                                                                      "pedestrian")])
    states = _run(world, 100)
    assert not any(overlaps(s[0].polygon(), s[1].polygon()) for s in states)
    assert min(s[0].speed for s in states[1:30]) < 1.0, "it braked"
    assert states[-1][0].pose[0] > 20, "and drove on once the pedestrian had crossed"


def test_lane_stops_at_its_end():
    world = World([_actor("f", [0.0, 0.0, 0.0], {**LANE, "waypoints": [[10.0, 0.0], [10.0, 10.0]]})])
    last = _run(world, 400)[-1][0]
    assert last.pose[:2] == pytest.approx((10.0, 10.0), abs=0.02) and last.pose[2] == pytest.approx(math.pi / 2)


def test_pedestrian_sets_off_at_the_trigger_time_step():
    walker = {"type": "pedestrian", "to": [20.0, 5.0], "speed": 1.4, "trigger": {"time": 1.0}}
    world = World([_actor("w", [20.0, -5.0, math.pi / 2], walker, "pedestrian")])
    states = [s[0] for s in _run(world, 120)]
    assert all(s.pose == (20.0, -5.0, math.pi / 2) and s.speed == 0 for s in states[:11])      # t = 0 .. 1.0
    assert states[11].pose[1] == pytest.approx(-5.0 + 1.4 * 0.1, abs=8 * np.spacing(5.0)) and states[11].speed == 1.4
    assert states[-1].pose[:2] == (20.0, 5.0) and states[-1].speed == 0


def test_pedestrian_sets_off_when_the_ego_comes_within_its_distance():
    walker = {"type": "pedestrian", "to": [20.0, 5.0], "speed": 1.4, "trigger": {"distance": 4.0}}
    world = World([_actor("w", [20.0, -5.0, math.pi / 2], walker, "pedestrian")])

    def ego(t):                       # along y = -5 at 1 m/s: front bumper at k / 10 + 3.75
        return ego_actor((round(t * 10) / 10, -5.0, 0.0), 1.0)
    states = [s[0] for s in _run(world, 160, ego)]
    # the walker spans x in [19.7, 20.3]: the gap is 19.7 - (k / 10 + 3.75), first <= 4 at k = 120
    k = next(k for k in range(160) if float(polygon_distance(ego(k / 10).polygon(), states[k].polygon())) <= 4.0)
    assert k == 120
    assert states[k].pose == (20.0, -5.0, math.pi / 2) and states[k + 1].pose[1] > -5.0


RANDOM = [
    _actor("leaving", [22.5, 5.65, math.pi / 2], {"type": "path", "waypoints": [[22.5, 1.0, -1], [35.0, 1.0]],
                                                  "speed": [1.0, 1.5], "start_time": [0.0, 3.0]}),
    _actor("through", [0.0, 1.0, 0.0], {"type": "lane", "waypoints": [[60.0, 1.0]], "speed": [2.0, 3.0]}),
    _actor("walker", [15.0, -6.0, math.pi / 2], {"type": "pedestrian", "to": [15.0, 6.0], "speed": [1.0, 1.6],
                                                 "trigger": {"time": [2.0, 6.0], "distance": 4.0}}, "pedestrian"),
]


def _trace(actors, seed):
    world = World(actors, seed)
    states = _run(world, 150)
    return {name: [s[i] for s in states] for i, name in enumerate(world.names)}


def test_the_world_is_deterministic_given_the_seed():
    a, b, c = _trace(RANDOM, 5), _trace(RANDOM, 5), _trace(RANDOM, 6)
    assert a == b and a != c
    assert _trace([*RANDOM, _actor("extra", [50.0, -8.0, 0.0])], 5)["walker"] == a["walker"]
    assert _trace(RANDOM[::-1], 5) == a, "actors step together: their order changes nothing"


def test_predictions_follow_the_behaviours_plan():
    world = World(RANDOM, 5)
    _run(world, 40)
    pred = world.predict(3.0)
    assert pred.times == pytest.approx(4.0 + 0.1 * np.arange(1, 31)) and pred.polygons.shape == (30, 3, 4, 2)
    actual = _run(world, 30)[1:]
    leaving = np.array([s[0].pose for s in actual])
    np.testing.assert_allclose(pred.poses[:, 0], leaving, atol=64 * np.spacing(40.0))


def test_constant_velocity_predictions_run_straight():
    world = World([_actor("f", [0.0, 0.0, 0.3], {**LANE, "waypoints": [[50 * math.cos(0.3), 50 * math.sin(0.3)]]})])
    _run(world, 5)
    now = world.states[0]
    pred = world.predict(1.0, "constant_velocity")
    run = now.speed * 0.1 * np.arange(1, 11)
    np.testing.assert_allclose(pred.poses[:, 0, 0], now.pose[0] + run * math.cos(now.pose[2]), atol=1e-12)
    np.testing.assert_allclose(pred.poses[:, 0, 1], now.pose[1] + run * math.sin(now.pose[2]), atol=1e-12)
    with pytest.raises(ValueError, match="mode must be"):
        world.predict(1.0, "psychic")
