"""Footprint geometry and the episode scorecard on hand-made footprints and trajectories: contact exactly at
touching distance, clearances at known distances, direction changes, and a whole episode graded by hand."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from parksim.scenarios import EpisodeLog, Scorecard, aggregate, score_episode
from parksim.scenarios.shapes import box_polygon, nearest_distance, overlap_matrix, overlaps, polygon_distance
from parksim.vehicle import Obstacles, VehicleParams, footprint

UNIT = (-1.0, 1.0, -1.0, 1.0)


def test_box_polygon_places_the_ego_as_the_vehicle_module_does():
    p = VehicleParams()
    for pose in [(0.0, 0.0, 0.0), (12.3, -4.5, 2.1), (-7.0, 3.0, -0.7)]:
        # both round two products and two sums per coordinate: a few spacings at the largest magnitude
        np.testing.assert_allclose(box_polygon(pose, p.extent), footprint(pose, p), rtol=0,
                                   atol=4 * np.spacing(20.0))


def test_axis_aligned_boxes_touching_collide_and_one_spacing_apart_do_not():
    """Unit normals of axis-aligned edges are exact and so are the projections: the test is exact."""
    a = box_polygon((10.0, 0.0, 0.0), UNIT)                  # x in [9, 11]
    left = 11.0
    for steps, expected in [(-1, True), (0, True), (1, False)]:
        x0 = left
        for _ in range(abs(steps)):
            x0 = np.nextafter(x0, x0 + steps)
        b = np.array([[x0 + 2, 1.0], [x0, 1.0], [x0, -1.0], [x0 + 2, -1.0]])
        assert bool(overlaps(a, b)) is expected, (steps, x0)
        assert bool(overlap_matrix(a[None], b[None])[0, 0]) is expected
        assert float(polygon_distance(a, b)) == (x0 - left if steps > 0 else 0.0)


def test_rotated_boxes_collide_within_float_spacing_of_touching():
    """Corners carry at most two roundings of coordinates near 12 m, the unit normals two more, each projection
    (a dot product) a couple: under 8 spacings per projection, 16 between two; at 32 either way the answer is fixed."""
    yaw = math.radians(30)
    axis = np.array([math.cos(yaw), math.sin(yaw)])
    a = box_polygon((10.0, 4.0, yaw), (-2.25, 2.25, -0.9, 0.9))
    eps = 32 * np.spacing(12.0)
    for gap, expected in [(-eps, True), (eps, False)]:
        centre = np.array([10.0, 4.0]) + axis * (4.5 + gap)                  # nose to tail along the x axis
        b = box_polygon((*centre, yaw), (-2.25, 2.25, -0.9, 0.9))
        assert bool(overlaps(a, b)) is expected and bool(overlaps(b, a)) is expected
        assert bool(overlap_matrix(a[None], b[None])[0, 0]) is expected


@pytest.mark.parametrize("b, distance", [
    (box_polygon((2.75, 0.0, 0.0), UNIT), 0.75),                              # face to face
    (box_polygon((1.5 + math.sqrt(2), 0.0, math.pi / 4), UNIT), 0.5),         # a corner pointing at a face
    (box_polygon((5.0, 6.0, 0.0), UNIT), 5.0),                                # corner to corner: 3-4-5
    (box_polygon((0.5, 0.5, 0.3), UNIT), 0.0),                                # overlapping
])
def test_clearance_of_two_boxes_at_a_known_distance(b, distance):
    a = box_polygon((0.0, 0.0, 0.0), UNIT)
    tol = 8 * np.spacing(8.0)
    assert float(polygon_distance(a, b)) == pytest.approx(distance, abs=tol)
    assert float(polygon_distance(b, a)) == pytest.approx(distance, abs=tol)
    far = box_polygon((50.0, 50.0, 0.0), UNIT)
    assert nearest_distance(a[None], np.stack([far, b])) == pytest.approx(distance, abs=tol)


# --- a whole episode ---------------------------------------------------------------------------------------
DT = 0.1
SLOT = np.array([[20.0, -1.25], [26.0, -1.25], [26.0, 1.25], [20.0, 1.25]])     # parallel: axis along +x, centre x 23
PILLAR = {"kind": "pillar", "center": [15.0, 2.5], "size": [1.0, 1.0]}           # y in [2, 3]: 1.1 m off the body


def _episode(xs, speeds, controls=None, actors=None, obstacles=(PILLAR,)):
    n = len(xs)
    poses = np.column_stack([xs, np.zeros(n), np.zeros(n)])
    return EpisodeLog(t=np.arange(n) * DT, poses=poses, speeds=speeds,
                      controls=np.zeros((n - 1, 2)) if controls is None else controls,
                      actors=np.zeros((n, 0, 4, 2)) if actors is None else actors,
                      obstacles=Obstacles(list(obstacles)).corners(), slot=SLOT)


def _drive(*legs):
    """Rear-axle x at 0.1 s steps over legs ``(to, speed)`` driven at constant speed from x = 10, and the speeds."""
    xs, vs = [10.0], [0.0]
    for to, v in legs:
        steps = round(abs(to - xs[-1]) / (abs(v) * DT))
        xs += list(np.linspace(xs[-1], to, steps + 1)[1:])
        vs += [v] * (steps - 1) + [0.0]
    return np.array(xs), np.array(vs)


def test_a_parking_episode_graded_by_hand():
    xs, vs = _drive((25.0, 1.0), (21.6, -1.0))            # 15 m forward, 3.4 m back: body centre at 23.0
    controls = np.zeros((len(xs) - 1, 2))
    controls[10:, 0] = 2.0                                # 0 -> 2: 20 m/s^3
    controls[30:, 0] = -4.0                               # 2 -> -4: 60 m/s^3, the peak
    walker = box_polygon((30.0, 0.0, 0.0), (-0.3, 0.3, -0.3, 0.3))          # x from 29.7: front reaches 28.75
    actors = np.broadcast_to(walker, (len(xs), 1, 4, 2))
    card = score_episode(_episode(xs, vs, controls, actors))
    assert card.success and not card.collided
    assert card.final_distance == pytest.approx(0.0, abs=8 * np.spacing(25.0)) and card.final_heading_error == 0
    assert card.static_collisions == card.actor_collisions == 0
    assert card.first_static_collision is None and card.first_actor_collision is None
    assert card.min_clearance_static == pytest.approx(1.1, abs=8 * np.spacing(4.0))
    assert card.min_clearance_actors == pytest.approx(0.95, abs=8 * np.spacing(32.0))
    assert card.path_length == pytest.approx(18.4, abs=len(xs) * np.spacing(25.0))
    assert card.direction_changes == 1 and card.steps == len(xs) - 1
    assert card.time == pytest.approx((len(xs) - 1) * DT, abs=4 * np.spacing(20.0))
    assert card.peak_jerk == pytest.approx(60.0, rel=8 * np.spacing(1.0))


def test_not_stopped_or_out_of_the_tolerances_is_no_success():
    xs, vs = _drive((25.0, 1.0), (21.6, -1.0))
    assert not score_episode(_episode(xs, np.where(np.arange(len(vs)) == len(vs) - 1, -0.2, vs))).success
    short = score_episode(_episode(xs + np.where(np.arange(len(xs)) == len(xs) - 1, 0.4, 0.0), vs))
    assert not short.success and short.final_distance == pytest.approx(0.4, abs=8 * np.spacing(25.0))
    assert score_episode(_episode(xs + 0.3, vs)).success, "0.3 m off is within the default 0.35 m"
    off = _episode(xs, vs)
    turned = EpisodeLog(off.t, off.poses + [0.0, 0.0, math.radians(5)], off.speeds, off.controls, off.actors,
                        off.obstacles, off.slot)
    card = score_episode(turned, heading_tolerance=4.0)
    assert not card.success and card.final_heading_error == pytest.approx(5.0, abs=1e-12)


def test_collisions_count_contacts_begun_and_the_first_time():
    through = {"kind": "pillar", "center": [15.0, 0.0], "size": [1.0, 1.0]}         # x in [14.5, 15.5]
    xs, vs = _drive((13.0, 1.0))                  # front from 13.75 to 16.75: contact from x = 10.75
    card = score_episode(_episode(xs, vs, obstacles=[through]))
    first = next(k for k, x in enumerate(xs) if x + 3.75 >= 14.5)
    assert card.static_collisions == 1 and card.first_static_collision == pytest.approx(first * DT)
    assert not card.success and card.collided and card.min_clearance_static == 0.0
    xs, vs = _drive((11.0, 1.0), (10.0, -1.0), (11.0, 1.0))         # touches, lets go, touches again
    assert score_episode(_episode(xs, vs, obstacles=[through])).static_collisions == 2


def test_touching_an_obstacle_exactly_is_a_collision_and_a_spacing_away_is_not():
    # the body's front edge at x = 6.25 + 3.75 = 10 exactly; the box spans [10 + gap, 12 + gap]
    for gap, collided in [(0.0, True), (float(np.spacing(10.0)), False)]:
        box = {"kind": "car", "center": [11.0 + gap, 0.0], "size": [2.0, 2.0]}
        card = score_episode(_episode(np.array([6.25]), np.zeros(1), obstacles=[box]))
        assert (card.static_collisions == 1) is collided
        assert card.min_clearance_static == (0.0 if collided else float(np.spacing(10.0)))


def test_an_actor_crossing_the_ego_is_a_collision_at_its_time():
    xs, vs = _drive((12.0, 1.0))
    n = len(xs)
    ys = np.linspace(-6.0, 6.0, n)                             # walks across x = 13 (inside the body: 9.05 to 15.75)
    actors = np.stack([box_polygon((13.0, y, math.pi / 2), (-0.25, 0.25, -0.3, 0.3)) for y in ys])[:, None]
    card = score_episode(_episode(xs, vs, actors=actors, obstacles=()))
    inside = [k for k in range(n) if abs(ys[k]) <= 0.9 + 0.25]
    assert card.actor_collisions == 1 and card.first_actor_collision == pytest.approx(inside[0] * DT)
    assert card.min_clearance_actors == 0.0 and card.min_clearance_static is None


@pytest.mark.parametrize("speeds, changes", [
    ([0, 0.5, 1, 0, 0, -0.5, -1e-3, -1, 0, 1, 1], 2),        # -1e-3 m/s is standing
    ([1, 0, 0, 1], 0),                                        # a stop is no change of direction
    ([-1, 1, -1, 1], 3),
    ([0, 0, 0], 0),
])
def test_direction_changes(speeds, changes):
    xs = 10.0 + 0.01 * np.arange(len(speeds))
    assert score_episode(_episode(xs, np.array(speeds, float))).direction_changes == changes


def test_the_card_is_json_and_the_same_log_gives_the_same_numbers():
    xs, vs = _drive((25.0, 1.0), (21.6, -1.0))
    one, two = score_episode(_episode(xs, vs)), score_episode(_episode(xs, vs))
    text = json.dumps(one.to_dict(), sort_keys=True)
    assert text == json.dumps(two.to_dict(), sort_keys=True)
    assert Scorecard.from_dict(json.loads(text)) == one


def _card(success, distance, actors=None):
    return Scorecard(success=success, final_distance=distance, final_heading_error=1.0, static_collisions=0,
                     first_static_collision=None, actor_collisions=0 if success else 1,
                     first_actor_collision=None if success else 2.0, min_clearance_static=0.5,
                     min_clearance_actors=actors, time=10.0, path_length=20.0, direction_changes=1,
                     peak_jerk=3.0, steps=100)


def test_aggregate_over_a_set():
    cards = [_card(True, 0.1), _card(True, 0.2, 1.5), _card(False, 0.6, 0.0)]
    summary = aggregate(cards)
    assert summary["episodes"] == 3 and summary["success_rate"] == pytest.approx(2 / 3)
    assert summary["collision_rate"] == pytest.approx(1 / 3)
    assert summary["final_distance"] == pytest.approx({"n": 3, "mean": 0.3, "p50": 0.2, "p90": 0.52, "max": 0.6})
    assert summary["min_clearance_actors"] == pytest.approx({"n": 2, "mean": 0.75, "p50": 0.75, "p90": 1.35,
                                                             "max": 1.5})
    assert aggregate(cards[:1])["min_clearance_actors"] == {"n": 0}
    json.dumps(summary)
    with pytest.raises(ValueError, match="at least one"):
        aggregate([])


@pytest.mark.parametrize("change, message", [
    ({"speeds": np.zeros(3)}, r"EpisodeLog.speeds must have shape \(2,\) for 2 steps, got \(3,\)"),
    ({"controls": np.zeros((2, 2))}, r"EpisodeLog.controls must have shape \(1, 2\)"),
    ({"t": np.array([0.0, 0.0])}, "EpisodeLog.t must increase"),
    ({"poses": np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]])}, "NaN or an infinity"),
])
def test_bad_logs_are_refused_in_one_line(change, message):
    fields = {"t": np.array([0.0, 0.1]), "poses": np.zeros((2, 3)), "speeds": np.zeros(2),
              "controls": np.zeros((1, 2)), "actors": np.zeros((2, 0, 4, 2)), "obstacles": np.zeros((0, 4, 2)),
              "slot": SLOT}
    with pytest.raises(ValueError, match=message):
        EpisodeLog(**{**fields, **change})
