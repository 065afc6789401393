"""ParkingEnv: gymnasium's env checker, dynamics and episode ends, and the same frames in-process and via the server."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from parksim.env import ParkingEnv, heading_error, slot_pose
from server import create_app
from sim_fixtures import make_bundle, running_server


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("env") / "tiny", n=2000, bev_px=64)


def test_check_env_passes(bundle_dir):
    env = ParkingEnv(bundle=bundle_dir, cameras=["front"], bev=True, scale=0.25, max_steps=10,
                     render_mode="rgb_array")
    check_env(env, skip_render_check=False)
    obs, _ = env.reset(seed=0)
    assert obs["front"].shape == (30, 40, 3) and obs["bev"].shape == (64, 64, 3) and obs["state"].shape == (8,)
    top = env.render()
    assert top.ndim == 3 and top.dtype == np.uint8 and (top == (255, 140, 0)).all(-1).any(), "ego footprint drawn"


def test_registered_and_made_with_gym_make(bundle_dir):
    env = gym.make("ParkSim-v0", bundle=bundle_dir, cameras=[], max_steps=3)
    obs, info = env.reset(seed=1)
    assert set(obs) == {"state"} and not info["is_success"]
    for _ in range(3):
        *_, truncated, _ = env.step(np.zeros(2, np.float32))
    assert truncated


def test_driving_into_a_wall_terminates_with_collision(bundle_dir):
    env = ParkingEnv(bundle=bundle_dir, cameras=[])
    env.reset(seed=0, options={"start": (30.0, 0.0, 0.0)})
    for _ in range(100):
        _, reward, terminated, _, info = env.step(np.array([2.0, 0.0], np.float32))
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
            a = np.array([1.5, 0.2], np.float32)
            (o1, *_), (o2, *_) = local.step(a), remote.step(a)
        for key in ("state", "front", "left", "bev"):
            np.testing.assert_array_equal(o1[key], o2[key])
        assert o1["front"].std() > 1
