"""Baseline geometric planner: Dubins paths are exact, and it parks in closed loop through the env API."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from parksim.env import ParkingEnv
from parksim.planners import dubins_paths, run_episode
from parksim.vehicle import wrap_angle
from sim_fixtures import make_bundle

_coord = st.floats(-15, 15)


@settings(max_examples=30, deadline=None)
@given(gx=_coord, gy=_coord, gyaw=st.floats(-math.pi, math.pi), syaw=st.floats(-math.pi, math.pi))
def test_dubins_paths_reach_the_goal_with_bounded_curvature(gx, gy, gyaw, syaw):
    paths = dubins_paths((0.0, 0.0, syaw), (gx, gy, gyaw), 4.0, step=0.1)
    assert paths, "some Dubins word always exists"
    for p in paths:
        assert np.hypot(*(p[-1, :2] - (gx, gy))) < 0.05 and abs(wrap_angle(p[-1, 2] - gyaw)) < 0.02
        turn = np.abs(wrap_angle(np.diff(p[:, 2])))
        step = np.hypot(*np.diff(p[:, :2], axis=0).T)
        assert (turn <= step / 4.0 + 1e-6).all()


def test_dubins_zero_arc_rounded_below_zero_is_not_a_full_loop():
    """A quarter turn whose straight and second arc are zero up to rounding (-1e-16) is a quarter circle, pi r / 2,
    not that plus a 2 pi r loop."""
    shortest = dubins_paths((0.0, 0.0, 0.0), (2.0, 2.0, math.pi / 2), 2.0, step=0.01)[0]
    length = np.hypot(*np.diff(shortest[:, :2], axis=0).T).sum()
    assert abs(length - math.pi) < 1e-3, length


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    bundle = make_bundle(tmp_path_factory.mktemp("planner") / "tiny", n=300, bev_px=64)
    return gym.make("ParkSim-v0", bundle=bundle, cameras=[], privileged=True, max_episode_steps=400)


def test_planner_parks_in_a_test_episode(env):
    result = run_episode(env, seed=1)
    assert result["planned"] and result["is_success"] and not result["collision"], result
    assert result["distance"] < env.unwrapped.pos_tol and result["heading_error"] < env.unwrapped.yaw_tol
    assert 0 < result["steps"] < 400


def test_planner_refuses_an_env_without_the_world_pose(env):
    blind = ParkingEnv(sim=env.unwrapped.sim, cameras=[])
    with pytest.raises(ValueError, match="privileged=True"):
        run_episode(blind, seed=1)
