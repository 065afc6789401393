"""Vector ParkSim-v0 past one process: four sub-envs in Ray actors and the batch-render env against a server agree
with single envs seeded alike (spaces, shapes, seeding, next-step autoreset, TimeLimit truncation)."""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector.utils import batch_space

from parksim.env import ParkingEnv
from parksim.server import create_app
from parksim.vector_env import BatchRenderVectorEnv, RayVectorEnv, make_vector_env
from sim_fixtures import make_bundle, running_server

ray = pytest.importorskip("ray")

N, LIMIT, SEED = 4, 3, 7
KWARGS = {"cameras": ["front"], "bev": False, "scale": 0.25}


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("vec") / "tiny", n=1500, bev_px=64)


@pytest.fixture(scope="module")
def ray_envs(bundle_dir):
    ray.init(num_cpus=2, object_store_memory=150 * 1024**2, include_dashboard=False, logging_level="WARNING")
    try:
        envs = gym.make_vec("ParkSim-v0", num_envs=N, bundle=str(bundle_dir), max_episode_steps=LIMIT, **KWARGS)
        yield envs
        envs.close()
    finally:
        ray.shutdown()


def _actions(steps: int) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, (steps, N, 2)).astype(np.float32)


def _reference(bundle_dir, steps: int) -> list[list[dict[str, np.ndarray]]]:
    """Per step, per env: the observation of single envs seeded SEED + i, reset in the step after their end."""
    envs = [ParkingEnv(bundle=bundle_dir, **KWARGS) for _ in range(N)]
    trace = [[e.reset(seed=SEED + i)[0] for i, e in enumerate(envs)]]
    for t, acts in enumerate(_actions(steps), start=1):
        trace.append([e.reset()[0] if t % (LIMIT + 1) == 0 else e.step(a)[0]
                      for e, a in zip(envs, acts)])
    return trace


def _assert_same(batch: dict[str, np.ndarray], singles: list[dict[str, np.ndarray]]) -> None:
    assert set(batch) == set(singles[0])
    for key in batch:
        np.testing.assert_array_equal(batch[key], np.stack([o[key] for o in singles]), err_msg=key)


def test_a_single_env_passes_gymnasiums_checker(bundle_dir):
    check_env(gym.make("ParkSim-v0", bundle=bundle_dir, **KWARGS).unwrapped)


def test_make_vec_puts_the_envs_in_ray_actors_with_batched_spaces(ray_envs, bundle_dir):
    assert isinstance(ray_envs, RayVectorEnv) and len(ray_envs.actors) == N
    single = ParkingEnv(bundle=bundle_dir, **KWARGS)
    assert ray_envs.single_observation_space == single.observation_space
    assert ray_envs.single_action_space == single.action_space
    assert ray_envs.observation_space == batch_space(single.observation_space, N)
    assert ray_envs.action_space == batch_space(single.action_space, N)
    pids = set(ray.get([a.__ray_call__.remote(lambda host: os.getpid()) for a in ray_envs.actors]))
    assert len(pids) == N and os.getpid() not in pids, "one process per sub-env"


def test_ray_vector_env_steps_resets_and_truncates_like_single_envs(ray_envs, bundle_dir):
    steps = 2 * (LIMIT + 1)
    reference = _reference(bundle_dir, steps)
    obs, infos = ray_envs.reset(seed=SEED)
    assert ray_envs.observation_space.contains(obs) and infos["_slot"].all()
    _assert_same(obs, reference[0])
    for t, acts in enumerate(_actions(steps), start=1):
        obs, rewards, terminated, truncated, infos = ray_envs.step(acts)
        assert rewards.shape == terminated.shape == truncated.shape == (N,)
        assert ray_envs.observation_space.contains(obs)
        _assert_same(obs, reference[t])
        assert truncated.all() == (t % (LIMIT + 1) == LIMIT) and not terminated.any(), t
        assert (rewards == 0).all() == (t % (LIMIT + 1) == 0), "the step after an end resets: reward 0"
    again, _ = ray_envs.reset(seed=SEED)
    _assert_same(again, reference[0])
    other, _ = ray_envs.reset(seed=SEED + 100)
    assert not np.array_equal(other["state"], again["state"]), "another seed starts elsewhere"


def test_batch_render_env_against_a_server_matches_the_ray_env(ray_envs, bundle_dir):
    acts = _actions(LIMIT + 2)
    with running_server(create_app(bundle_dir.parent)) as url:
        served = gym.make_vec("ParkSim-v0", num_envs=N, server=url, scene=bundle_dir.name, backend="batch",
                              max_episode_steps=LIMIT, **KWARGS)
        assert isinstance(served, BatchRenderVectorEnv)
        results = []
        for envs in (served, ray_envs):
            trace = [envs.reset(seed=SEED)[0]] + [envs.step(a)[0] for a in acts]
            results.append(trace)
        served.close()
    for a, b in zip(*results):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_batch_render_env_in_process_matches_the_ray_env(ray_envs, bundle_dir):
    """backend="batch" with bundle=: every car's cameras rendered in one LocalSim.render_batch per step, the same
    observations as the Ray actors' single envs."""
    acts = _actions(LIMIT + 2)
    local = gym.make_vec("ParkSim-v0", num_envs=N, bundle=str(bundle_dir), backend="batch", device="cpu",
                         max_episode_steps=LIMIT, **KWARGS)
    assert isinstance(local, BatchRenderVectorEnv) and local.sim.device.type == "cpu"
    results = [[envs.reset(seed=SEED)[0]] + [envs.step(a)[0] for a in acts] for envs in (local, ray_envs)]
    local.close()
    for a, b in zip(*results):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_vector_envs_share_one_render_actor(ray_envs, bundle_dir):
    """render_actor=NAME: the poses of a step go to one Ray actor holding the bundle (a GPU one when it reserves
    GPUs), in one render_batch call; a second vector env naming it uses the same actor; observations as the Ray
    env's single envs."""
    from parksim.ray_sim import RaySim

    acts = _actions(LIMIT + 2)
    first = make_vector_env(N, backend="batch", bundle=str(bundle_dir), render_actor="garage-renderer",
                            render_cpus=0, device="cpu", max_episode_steps=LIMIT, **KWARGS)
    second = make_vector_env(2, backend="batch", bundle=str(bundle_dir), render_actor="garage-renderer",
                             render_cpus=0, max_episode_steps=LIMIT, **KWARGS)
    assert isinstance(first.sim, RaySim) and first.sim.device == "cpu"
    assert first.sim.actor._actor_id == second.sim.actor._actor_id
    results = [[envs.reset(seed=SEED)[0]] + [envs.step(a)[0] for a in acts] for envs in (first, ray_envs)]
    for a, b in zip(*results):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    second.reset(seed=SEED)
    for envs in (first, second):
        envs.close()
    ray.kill(first.sim.actor)
    with pytest.raises(ValueError, match="render actor did not start"):
        RaySim(bundle_dir, device="cuda:7", cpus=0)


def test_sync_mode_still_vectorises_in_process(bundle_dir):
    envs = gym.make_vec("ParkSim-v0", num_envs=2, vectorization_mode="sync", bundle=bundle_dir, cameras=[])
    obs, _ = envs.reset(seed=SEED)
    assert isinstance(envs, gym.vector.SyncVectorEnv) and obs["state"].shape == (2, 5)
    envs.close()


def test_bad_vector_arguments_are_refused(bundle_dir):
    with pytest.raises(ValueError, match="backend must be one of"):
        make_vector_env(2, backend="threads", bundle=bundle_dir)
    with pytest.raises(ValueError, match="give server="):
        make_vector_env(2, backend="batch", cameras=[])
    with pytest.raises(ValueError, match="not both"):
        BatchRenderVectorEnv(2, server="http://127.0.0.1:9", bundle=bundle_dir)
    with pytest.raises(ValueError, match="cannot ship sim="):
        make_vector_env(2, sim=ParkingEnv(bundle=bundle_dir, cameras=[]).sim)


def test_scenario_sub_envs_draw_their_actors_and_end_at_the_scenarios_time_limit(bundle_dir, tmp_path):
    """backend="batch" with scenario=: each car's views are its own scenario's (actors drawn in, equal to a single
    env's), and the scenario's time limit truncates a sub-env, which resets on the step after."""
    import json

    from parksim.scenarios import write_set
    from parksim.scenarios.make import make_set

    world_map = json.loads((bundle_dir / "map.json").read_text())
    made = make_set(world_map, "tiny", 2, 0, difficulties=("hard",))
    made = type(made)(made.name, tuple(s.model_copy(update={"time_limit": 0.3}) for s in made.scenarios))
    write_set(tmp_path / "set", made)
    kwargs = {"cameras": ["front"], "bev": True, "scale": 0.25, "scenario": str(tmp_path / "set")}
    vec = BatchRenderVectorEnv(2, bundle=str(bundle_dir), device="cpu", **kwargs)
    singles = [ParkingEnv(bundle=bundle_dir, **kwargs) for _ in range(2)]
    obs, info = vec.reset(seed=SEED)
    reference = [e.reset(seed=SEED + i) for i, e in enumerate(singles)]
    _assert_same(obs, [o for o, _ in reference])
    assert list(info["scenario"]) == [i["scenario"] for _, i in reference]
    for step in range(1, 5):
        obs, _, terminated, truncated, info = vec.step(np.zeros((2, 2), np.float32))
        if step <= 3:
            _assert_same(obs, [e.step(np.zeros(2))[0] for e in singles])
        assert not terminated.any() and truncated.tolist() == [step == 3] * 2, step
    assert info["time"].tolist() == [0.0, 0.0], "the step after the time limit reset both"
    vec.close()
