"""Reeds-Shepp paths: exact ends, analytic lengths, the symmetries of the problem, never longer than Dubins."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from parksim.planners.geometric import dubins_paths
from parksim.planners.reeds_shepp import reeds_shepp_length, reeds_shepp_path, reeds_shepp_paths
from parksim.vehicle import wrap_angle

EPS = sys.float_info.epsilon
R = 4.1
_coord = st.floats(-20, 20)
_yaw = st.floats(-math.pi, math.pi)
_pose = st.tuples(_coord, _coord, _yaw)


def _tol(start, goal, ulps=64):
    """``ulps`` float64 spacings at the problem's scale: the coordinates and a full turn of arc."""
    return ulps * EPS * (max(abs(v) for v in (*start[:2], *goal[:2])) + 2 * math.pi * R)


@settings(max_examples=60, deadline=None)
@given(start=_pose, goal=_pose)
def test_every_candidate_ends_on_the_goal(start, goal):
    """Each word the formulas give, integrated in closed form, stops within 1e-9 m and rad of the goal."""
    paths = reeds_shepp_paths(start, goal, R)
    assert paths and paths[0].length == min(p.length for p in paths)
    for p in paths:
        x, y, yaw = p.end()
        assert math.hypot(x - goal[0], y - goal[1]) < 1e-9, (p.word, p.lengths)
        assert abs(wrap_angle(yaw - goal[2])) < 1e-9
        last = p.sample(0.25)[-1]
        assert math.hypot(last[0] - goal[0], last[1] - goal[1]) < 1e-9


@settings(max_examples=40, deadline=None)
@given(start=_pose, goal=_pose)
def test_samples_are_spaced_and_turn_no_tighter_than_the_radius(start, goal):
    step = 0.2
    path = reeds_shepp_path(start, goal, R)
    s = path.sample(step)
    ds = np.hypot(*np.diff(s[:, :2], axis=0).T)
    assert (ds <= step + _tol(start, goal)).all()
    # a chord of an arc of angle a at radius R is 2 R sin(a / 2): the turn between samples is at most ds / R
    # (to first order; 2 asin(ds / 2R) is exact and slightly larger)
    turn = np.abs(np.diff(s[:, 2]))
    assert (turn <= 2 * np.arcsin(np.minimum(ds / (2 * R), 1.0)) + _tol(start, goal) / R).all()
    assert set(np.unique(s[:, 3])) <= {-1.0, 1.0}
    assert np.isclose(ds.sum(), path.length, rtol=(step / R) ** 2 / 24 + 1e-12)


@settings(max_examples=40, deadline=None)
@given(start=_pose, goal=_pose)
def test_never_longer_than_dubins_and_at_least_the_lower_bounds(start, goal):
    """Reeds-Shepp may reverse, so it is never longer than the forward-only Dubins path; and no path is shorter
    than the straight line or than the heading change at the minimum radius."""
    length = reeds_shepp_length(start, goal, R)
    assert length == reeds_shepp_path(start, goal, R).length
    # dubins_paths takes an arc within 1e-6 rad of a full loop for none (its _ZERO_ARC): a goal that needs such a
    # loop, as one turned by a hair, gets a Dubins path without it
    assume(abs(wrap_angle(goal[2] - start[2])) > 1e-5)
    step = 0.01
    chords = min(np.hypot(*np.diff(p[:, :2], axis=0).T).sum() for p in dubins_paths(start, goal, R, step))
    # a chord of an arc is at least the arc times (1 - (step / R)^2 / 24): the sampled Dubins length's deficit
    assert length <= chords / (1 - (step / R) ** 2 / 24) + _tol(start, goal)
    assert length >= math.hypot(goal[0] - start[0], goal[1] - start[1]) - _tol(start, goal)
    assert length >= R * abs(wrap_angle(goal[2] - start[2])) - _tol(start, goal)


@settings(max_examples=40, deadline=None)
@given(x=_coord, y=_coord, phi=_yaw)
def test_symmetries(x, y, phi):
    """Driving a path backward from the goal, mirroring left and right, and flipping time keep the length."""
    origin = (0.0, 0.0, 0.0)
    length = reeds_shepp_length(origin, (x, y, phi), R)
    tol = _tol(origin, (x, y, phi))
    assert abs(reeds_shepp_length((x, y, phi), origin, R) - length) <= tol
    assert abs(reeds_shepp_length(origin, (x, -y, -phi), R) - length) <= tol
    assert abs(reeds_shepp_length(origin, (-x, y, -phi), R) - length) <= tol


@pytest.mark.parametrize("d", [0.5, 3.0, 17.25])
def test_straight_ahead_and_pure_reverse(d):
    for sign in (1.0, -1.0):
        path = reeds_shepp_path((2.0, -1.0, 0.3), (2.0 + sign * d * math.cos(0.3), -1.0 + sign * d * math.sin(0.3),
                                                   0.3), R)
        assert abs(path.length - d) <= 8 * EPS * (d + 3)
        assert path.switches == 0
        assert (path.sample(0.1)[:, 3] == sign).all()


def test_quarter_circle_and_a_turn_on_the_spot():
    quarter = reeds_shepp_path((0.0, 0.0, 0.0), (R, R, math.pi / 2), R)
    assert abs(quarter.length - math.pi * R / 2) <= 8 * EPS * R
    assert [v for v in quarter.lengths if v] == [pytest.approx(math.pi * R / 2, rel=4 * EPS)]
    assert quarter.word[[i for i, v in enumerate(quarter.lengths) if v][0]] == "L"
    turned = reeds_shepp_path((0.0, 0.0, 0.0), (0.0, 0.0, math.pi), R)   # a K-turn: must reverse at least once
    assert turned.switches >= 1 and turned.length >= math.pi * R - 8 * EPS * R
    assert reeds_shepp_path((1.0, 2.0, 3.0), (1.0, 2.0, 3.0), R).length == 0.0
    # a hair of a turn costs a hair of driving: forward, back and forward again (no loop as Dubins needs)
    hair = reeds_shepp_path((0.0, 0.0, 0.0), (0.0, 0.0, 1e-6), R)
    assert hair.switches >= 1 and hair.length < 3e-6 * R


def test_all_48_words_occur():
    """The 18 letter sequences with their forward/backward patterns are Reeds and Shepp's 48 words."""
    rng = np.random.default_rng(0)
    words = set()
    for x, y, phi in zip(rng.uniform(-4, 4, 200), rng.uniform(-4, 4, 200), rng.uniform(-math.pi, math.pi, 200)):
        for p in reeds_shepp_paths((0.0, 0.0, 0.0), (x, y, phi), 1.0):
            if all(p.lengths):
                words.add((p.word, tuple(v > 0 for v in p.lengths)))
    assert len(words) == 48
    assert len({w for w, _ in words}) == 18


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="radius"):
        reeds_shepp_path((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.0)
    with pytest.raises(ValueError, match="finite"):
        reeds_shepp_length((0.0, 0.0, 0.0), (math.nan, 0.0, 0.0), 1.0)
    with pytest.raises(ValueError, match="step"):
        reeds_shepp_path((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1.0).sample(0.0)
