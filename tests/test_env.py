"""ParkingEnv: gymnasium's env checker, normalised actions, ego-relative observations, episode ends (TimeLimit),
seeding, and the same frames in-process and via the server."""

from __future__ import annotations

import math
from contextlib import closing

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from parksim.env import MAX_EPISODE_STEPS, ParkingEnv, heading_error, slot_pose, to_action, to_controls
from parksim.server import create_app
from parksim.vector_env import BatchRenderVectorEnv
from parksim.vehicle import VehicleParams, wrap_angle
from sim_fixtures import make_bundle, running_server


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("env") / "tiny", n=2000, bev_px=64)


def test_check_env_passes(bundle_dir):
    env = ParkingEnv(bundle=bundle_dir, cameras=["front"], bev=True, scale=0.25, render_mode="rgb_array")
    check_env(env, skip_render_check=False)
    obs, _ = env.reset(seed=0)
    assert obs["front"].shape == (30, 40, 3) and obs["bev"].shape == (64, 64, 3) and obs["state"].shape == (5,)
    top = env.render()
    assert top.ndim == 3 and top.dtype == np.uint8 and (top == (255, 140, 0)).all(-1).any(), "ego footprint drawn"


def test_registered_and_made_with_gym_make(bundle_dir):
    assert gym.spec("ParkSim-v0").max_episode_steps == MAX_EPISODE_STEPS
    env = gym.make("ParkSim-v0", bundle=bundle_dir, cameras=[], max_episode_steps=3)
    obs, info = env.reset(seed=1)
    assert set(obs) == {"state"} and not info["is_success"]
    ends = [env.step(np.zeros(2, np.float32))[2:4] for _ in range(3)]
    assert ends == [(False, False), (False, False), (False, True)], "TimeLimit truncates at max_episode_steps"


def test_normalised_actions_map_to_the_vehicle_limits(bundle_dir):
    p = VehicleParams()
    env = ParkingEnv(bundle=bundle_dir, cameras=[], vehicle=p)
    assert (env.action_space.low == -1).all() and (env.action_space.high == 1).all()
    env.reset(seed=0)
    env.step(np.array([1.0, 1.0], np.float32))
    assert env.state.v == p.max_accel * p.dt, "+1 is the full acceleration"
    assert abs(env.state.steer - p.max_steer_rate * p.dt) <= np.spacing(p.max_steer), "steering moves at its rate"
    for _ in range(20):
        env.step(np.array([0.0, 1.0], np.float32))
    assert env.state.steer == p.max_steer, "+1 steers to the full lock"
    v = env.state.v
    env.step(np.array([-1.0, 0.0], np.float32))
    assert abs(env.state.v - (v - p.max_decel * p.dt)) <= np.spacing(p.max_speed), "-1 is the full braking"
    assert to_controls([5.0, -5.0], p) == (p.max_accel, -p.max_steer), "actions are clipped to [-1, 1]"
    for accel, steer in [(1.3, -0.2), (-3.1, 0.45), (0.0, 0.0)]:
        back = to_controls(to_action(accel, steer, p), p)
        assert np.allclose(back, (accel, steer), rtol=0, atol=float(np.spacing(np.float32(p.max_decel)))), back


def test_observation_holds_the_slot_in_the_ego_frame_and_no_pose_unless_privileged(bundle_dir):
    blind, seeing = (ParkingEnv(bundle=bundle_dir, cameras=[], privileged=p) for p in (False, True))
    (obs, info), (pobs, pinfo) = blind.reset(seed=3), seeing.reset(seed=3)
    assert set(obs) == {"state"} and "pose" not in info and "pose" not in blind.observation_space.spaces
    assert set(pobs) == {"state", "pose"} and pinfo["pose"] == seeing.state.pose
    np.testing.assert_array_equal(pobs["state"], obs["state"])
    np.testing.assert_array_equal(pobs["pose"], np.array(seeing.state.pose, np.float32))
    s = blind.state
    centre, slot_yaw = slot_pose(blind.slot)
    rel = np.array([[math.cos(s.yaw), math.sin(s.yaw)], [-math.sin(s.yaw), math.cos(s.yaw)]]) @ (centre - (s.x, s.y))
    expected = np.array([s.v, s.steer, *rel, wrap_angle(slot_yaw - s.yaw)])
    tol = np.spacing(np.float32(np.abs(expected).max())) * 4
    np.testing.assert_allclose(obs["state"], expected, rtol=0, atol=tol)
    assert blind.observation_space.contains(obs) and seeing.observation_space.contains(pobs)


def test_same_seed_gives_the_same_start_and_observations(bundle_dir):
    a, b = (ParkingEnv(bundle=bundle_dir, cameras=["front"], privileged=True) for _ in range(2))
    (oa, ia), (ob, ib) = a.reset(seed=11), b.reset(seed=11)
    assert ia == ib and a.state == b.state
    actions = np.random.default_rng(0).uniform(-1, 1, (3, 2)).astype(np.float32)
    for act in actions:
        for key in oa:
            np.testing.assert_array_equal(oa[key], ob[key])
        (oa, *_), (ob, *_) = a.step(act), b.step(act)
    assert a.reset()[1] == b.reset()[1], "the unseeded reset after a seeded one follows the same stream"
    assert a.reset(seed=12)[1]["pose"] != ib["pose"], "another seed starts elsewhere"


def test_driving_into_a_wall_terminates_with_collision(bundle_dir):
    env = ParkingEnv(bundle=bundle_dir, cameras=[])
    env.reset(seed=0, options={"start": (30.0, 0.0, 0.0)})
    for _ in range(100):
        _, reward, terminated, _, info = env.step(np.array([1.0, 0.0], np.float32))
        if terminated:
            break
    assert terminated and info["collision"] and not info["is_success"] and reward < -5


def test_parked_pose_terminates_with_success(bundle_dir):
    env = ParkingEnv(bundle=bundle_dir, cameras=[])
    _, info = env.reset(seed=0)
    target = env.target_pose()
    _, info = env.reset(seed=0, options={"start": target, "slot": info["slot"]})
    _, reward, terminated, _, info = env.step(np.array([0.0, 0.0], np.float32))
    assert terminated and info["is_success"] and info["distance"] < 1e-6
    centre, yaw = slot_pose(env.slot)
    assert heading_error(yaw + math.pi, yaw) < 1e-9, "backing in counts as parked too"
    with pytest.raises(ValueError, match="not a free slot"):
        env.reset(options={"slot": -1})


def test_server_and_in_process_env_give_the_same_frames(bundle_dir):
    kwargs = {"cameras": ["front", "left"], "bev": True, "scale": 0.25}
    local = ParkingEnv(bundle=bundle_dir, **kwargs)
    app = create_app(bundle_dir.parent)
    with running_server(app) as url:
        remote = ParkingEnv(server=url, scene=bundle_dir.name, **kwargs)
        for env in (local, remote):
            env.reset(seed=5)
        for _ in range(2):
            a = np.array([0.75, 0.33], np.float32)
            (o1, *_), (o2, *_) = local.step(a), remote.step(a)
        for key in ("state", "front", "left", "bev"):
            np.testing.assert_array_equal(o1[key], o2[key])
        assert o1["front"].std() > 1


@pytest.mark.parametrize("cameras", [[], ["front"]], ids=["state-only", "camera"])
def test_a_non_finite_action_is_refused_and_leaves_the_state_unchanged(bundle_dir, cameras):
    env, twin = (ParkingEnv(bundle=bundle_dir, cameras=cameras) for _ in range(2))
    env.reset(seed=4)
    twin.reset(seed=4)
    env.step(np.array([0.8, 0.3], np.float32))
    twin.step(np.array([0.8, 0.3], np.float32))
    before = env.state
    for bad in ([math.nan, 0.0], [0.0, math.inf], [-math.inf, math.nan]):
        with pytest.raises(ValueError, match=r"^action \[.*(nan|inf).*non-finite.*refused, the vehicle state is "
                                             r"unchanged$"):
            env.step(np.array(bad, np.float32))
        assert env.state == before
    good = np.array([0.5, -0.4], np.float32)
    (obs, reward, terminated, _, info), (tobs, treward, tterminated, _, tinfo) = env.step(good), twin.step(good)
    assert env.state == twin.state and (reward, terminated, info) == (treward, tterminated, tinfo)
    assert set(obs) == {"state", *cameras} and np.isfinite(obs["state"]).all()
    for key in obs:
        np.testing.assert_array_equal(obs[key], tobs[key], err_msg=key)


def test_a_vector_step_with_a_non_finite_action_moves_no_sub_env(bundle_dir):
    with (running_server(create_app(bundle_dir.parent)) as url,
          closing(BatchRenderVectorEnv(3, server=url, scene=bundle_dir.name, cameras=[], max_episode_steps=3)) as envs):
        envs.reset(seed=2)
        envs.step(np.full((3, 2), 0.5, np.float32))
        before = [e.state for e in envs.envs]
        actions = np.array([[0.5, 0.1], [math.nan, 0.0], [0.25, math.inf]], np.float32)
        with pytest.raises(ValueError, match=r"^actions of sub-envs \[1, 2\] \(\[\[nan, 0.0\], \[0.25, inf\]\]\) "
                                             r"have a non-finite value.*no sub-env's state changed$"):
            envs.step(actions)
        assert [e.state for e in envs.envs] == before
        obs, _, _, truncated, _ = envs.step(np.zeros((3, 2), np.float32))
        assert np.isfinite(obs["state"]).all() and not truncated.any()
        assert envs.step(np.zeros((3, 2), np.float32))[3].all(), "the refused step did not count towards the limit"


@pytest.mark.parametrize(("start", "message"), [
    ((math.nan, 0.0, 0.0), r"options\['start'\] \[nan, 0.0, 0.0\] has a non-finite value"),
    ((10.0, 0.0, math.inf), r"options\['start'\] \[10.0, 0.0, inf\] has a non-finite value"),
    ((10.0, 0.0), r"options\['start'\] must be \(x, y, yaw\), 3 numbers, got \(10.0, 0.0\)"),
    ((10.0, 0.0, 0.0, 1.5), r"must be \(x, y, yaw\), 3 numbers, got \(10.0, 0.0, 0.0, 1.5\)"),
    ((500.0, 0.0, 0.0), r"\[500.0, 0.0, 0.0\] is outside the scene: x must lie in \[-5, 39\] and y in "
                        r"\[-13.7, 13.7\] \(its bounds plus 5 m\)"),
    ((10.0, -40.0, 0.0), r"\[10.0, -40.0, 0.0\] is outside the scene"),
], ids=["nan", "inf-yaw", "2-values", "4-values", "far-x", "far-y"])
def test_a_bad_start_is_refused_with_its_reason(bundle_dir, start, message):
    env = ParkingEnv(bundle=bundle_dir, cameras=[])
    env.reset(seed=0)
    before = env.state
    with pytest.raises(ValueError, match=message):
        env.reset(options={"start": start})
    assert env.state == before, "a refused reset changes nothing"


def test_a_start_yaw_is_wrapped_into_the_pose_box(bundle_dir):
    env = ParkingEnv(bundle=bundle_dir, cameras=[], privileged=True)
    obs, _ = env.reset(seed=0, options={"start": (10.0, 0.0, 2 * math.pi + 0.5)})
    assert abs(env.state.yaw - 0.5) < 1e-12 and env.observation_space.contains(obs)
