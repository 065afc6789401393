"""The episode API over HTTP (parksim.server.episodes, episode_routes) and actors in ``POST /render``.

A scenario driven through the API equals the same scenario in ``ParkingEnv`` step by step (state, pose, reward,
done, info, the PNG views decoded, the scorecard); errors answer one line with the right status; idle episodes
expire; concurrent steps of one episode run one after the other; the Node.js example client drives an episode to
its scorecard; a car actor posted to ``/render`` is drawn as ``LocalSim.render(actors=)`` draws it.

The scene is scene1's garage as a 300-Gaussian bundle (as tests/test_episode.py)."""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from parksim.env import ParkingEnv
from parksim.frames import decode_npz
from parksim.planners import HybridAStarParker
from parksim.render.actors import Actor
from parksim.scenarios import ActorSpec, Scenario, Scorecard, dump_scenario
from parksim.scenarios.episode import load_actor_asset
from parksim.server import Settings, create_app
from parksim.server.deps import get_episodes
from parksim.server.episodes import EpisodeStore
from parksim.server.scenes import SceneRegistry
from parksim.sim import LocalSim
from sim_fixtures import easy_scenario, make_bundle, running_server

ROOT = Path(__file__).resolve().parents[1]
SEED = 2
"""A scene1 start from which Hybrid A* reverses into its slot (tests/test_episode.py)."""
VIEWS = {"cameras": ["front"], "bev": True, "scale": 0.25}


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return LocalSim(make_bundle(tmp_path_factory.mktemp("episode_api") / "scene1", preset="scene1", n=300,
                                bev_px=64), "scene1")


@pytest.fixture(scope="module")
def easy(sim):
    """The env's random start of ``SEED``, the slot Hybrid A* picks from it, and a pedestrian standing in view."""
    plain = easy_scenario(sim, SEED)
    x, y, _ = plain.ego.pose
    standing = ActorSpec(name="standing", asset="pedestrian", pose=(x - 6.0, y + 1.5, 0.0))
    return plain.model_copy(update={"actors": (standing,)})


@pytest.fixture(scope="module")
def app(sim):
    return create_app(SceneRegistry([sim]))


def _image(text: str) -> np.ndarray:
    """A base64 PNG as uint8 RGB."""
    return cv2.imdecode(np.frombuffer(base64.b64decode(text), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]


def _json(value: object) -> object:
    """What the env's ``value`` is in JSON (numpy scalars as numbers, tuples as lists, the scorecard as a dict)."""
    def plain(v: object) -> object:
        return v.to_dict() if isinstance(v, Scorecard) else v.item() if isinstance(v, np.generic) else v.tolist()

    return json.loads(json.dumps(value, default=plain))


def _same_observation(served: dict, obs: dict) -> None:
    """The served observation is the env's: numbers exactly, PNG views pixel for pixel."""
    assert set(served) == {"state", "pose", "images", "bev"} and set(served["images"]) == {"front"}
    np.testing.assert_array_equal(np.array(served["state"], np.float32), obs["state"])
    np.testing.assert_array_equal(np.array(served["pose"], np.float32), obs["pose"])
    np.testing.assert_array_equal(_image(served["images"]["front"]), obs["front"])
    np.testing.assert_array_equal(_image(served["bev"]), obs["bev"])


def test_an_episode_over_http_is_the_env_step_by_step(sim, easy, app, tmp_path):
    """Hybrid A* parks the scenario in the env; the same actions posted to the API give the same episode."""
    dump_scenario(easy, tmp_path / "easy.yaml")
    env = ParkingEnv(sim=sim, privileged=True, scenario=tmp_path / "easy.yaml", **VIEWS)
    obs, info = env.reset(seed=0)
    parker = HybridAStarParker()
    path = parker.plan(tuple(float(v) for v in obs["pose"]), env.slot, env.obstacles)
    assert path is not None, parker.result
    parker.follow(path)
    steps, done = [(obs, info)], False
    while not done:
        action = parker.act(steps[-1][0])
        obs, r, terminated, truncated, info = env.step(action)
        steps.append((obs, info, action, r, terminated or truncated, truncated))
        done = terminated or truncated
    assert info["scorecard"].success and np.asarray(steps[0][0]["bev"] != sim.render(
        env.state.pose, [], bev=True, scale=0.25).bev).any(), "parked, and the pedestrian shows"

    with running_server(app) as url, httpx.Client(base_url=url, timeout=60) as client:
        r = client.post("/episodes", json={"scenario": (tmp_path / "easy.yaml").read_text(), "privileged": True,
                                           **VIEWS})
        assert r.status_code == 201, r.text
        created = r.json()
        _same_observation(created["observation"], steps[0][0])
        assert created["info"] == _json(steps[0][1]) and created["info"]["scenario"] == "easy"
        episode = f"/episodes/{created['id']}"
        for obs, info, action, reward, done, truncated in steps[1:]:
            r = client.post(f"{episode}/step", json={"action": [float(a) for a in action]})
            assert r.status_code == 200, r.text
            reply = r.json()
            _same_observation(reply["observation"], obs)
            assert (reply["reward"], reply["done"], reply["truncated"]) == (reward, done, truncated)
            assert reply["info"] == _json(info)
        result = client.get(f"{episode}/result").json()
        assert result == {"id": created["id"], "scenario": "easy", "done": True,
                          "scorecard": info["scorecard"].to_dict()}
        r = client.post(f"{episode}/step", json={"action": [0.0, 0.0]})
        assert r.status_code == 409 and "is over" in r.json()["detail"]
        assert client.delete(episode).status_code == 204
        assert client.get(f"{episode}/result").status_code == 404


def _scenario(easy: Scenario, **update: object) -> dict:
    """``easy`` as the JSON object of its file, with ``update`` applied."""
    return easy.model_copy(update=update).model_dump(mode="json")


def test_errors_answer_one_line_with_their_status(sim, easy):
    key = {"X-API-Key": "k"}
    app = create_app(SceneRegistry([sim]), Settings(api_key="k", max_episodes=1, max_reply_bytes=1 << 16))
    state_only = {"scenario": _scenario(easy, time_limit=0.1), "cameras": []}
    with TestClient(app) as c:
        assert c.post("/episodes", json=state_only).status_code == 401
        bad = {"scene": ({"scenario": _scenario(easy, scene="other")}, 404, "unknown scene 'other'"),
               "file asset": ({"scenario": {**_scenario(easy), "actors": [{"name": "a", "asset": "/tmp/a.ply",
                                                                           "pose": [0, 0, 0]}]}},
                              422, "actors.0.asset: '/tmp/a.ply' is not a built-in asset"),
               "format": ({"scenario": {**_scenario(easy), "ego": {}}}, 422, "scenario: ego: give exactly one"),
               "alias": ({"scenario": "name: &n easy\nscene: *n\n"}, 422, "aliases (*name) are not accepted"),
               "yaml": ({"scenario": "name: [easy\n"}, 422, "scenario: not valid YAML"),
               "camera": ({**state_only, "cameras": ["roof"]}, 422, "roof"),
               "reply": ({**state_only, "cameras": None, "scale": 1.0}, 413, "over this server's limit")}
        for name, (body, status, words) in bad.items():
            r = c.post("/episodes", json=body, headers=key)
            assert r.status_code == status and words in r.json()["detail"], (name, r.text)
            assert "\n" not in r.json()["detail"], name
        r = c.post("/episodes", json=state_only, headers=key)
        assert r.status_code == 201 and r.json()["observation"]["images"] == {}, r.text
        episode = f"/episodes/{r.json()['id']}"
        r = c.post("/episodes", json=state_only, headers=key)
        assert r.status_code == 503 and int(r.headers["Retry-After"]) >= 1, r.text
        assert r.json()["detail"].startswith("episode store full: this server holds at most 1 (max_episodes)")
        for action in ("[NaN, 0]", "[0, Infinity]", "[0, 0, 0]", "[true, 0]", '["1", 0]', "[0]"):
            r = c.post(f"{episode}/step", content=f'{{"action": {action}}}', headers={
                **key, "Content-Type": "application/json"})
            assert r.status_code == 422 and r.json()["detail"].startswith("action"), (action, r.text)
        for method, path in (("post", f"{episode}/step"), ("get", f"{episode}/result"), ("delete", episode)):
            assert c.request(method, path, json={"action": [0, 0]}).status_code == 401, path
        r = c.post(f"{episode}/step", json={"action": [1, 0]}, headers=key)
        assert r.json()["done"] and r.json()["truncated"], "one step is the time limit"
        r = c.post(f"{episode}/step", json={"action": [1, 0]}, headers=key)
        assert r.status_code == 409 and "is over" in r.json()["detail"]
        assert c.delete(episode, headers=key).status_code == 204
        for method, path in (("post", f"{episode}/step"), ("get", f"{episode}/result"), ("delete", episode)):
            r = c.request(method, path, json={"action": [0, 0]}, headers=key)
            assert r.status_code == 404 and "no episode" in r.json()["detail"], path
        assert c.post("/episodes", json=state_only, headers=key).status_code == 201, "deleting freed the place"


class Clock:
    """A settable time source."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_an_idle_episode_expires_and_frees_its_place(sim, easy, app):
    clock = Clock()
    store = EpisodeStore(capacity=1, ttl_s=10.0, clock=clock)
    app.dependency_overrides[get_episodes] = lambda: store
    body = {"scenario": _scenario(easy), "cameras": []}
    try:
        with TestClient(app) as c:
            episode = f"/episodes/{c.post('/episodes', json=body).json()['id']}"
            r = c.post("/episodes", json=body)
            assert r.status_code == 503 and r.headers["Retry-After"] == "10", "until the idle one expires"
            clock.now = 9.0
            assert c.post(f"{episode}/step", json={"action": [0, 0]}).status_code == 200, "touched at 9 s"
            clock.now = 18.0
            assert c.get(f"{episode}/result").status_code == 200, "idle 9 s only"
            clock.now = 28.5
            r = c.get(f"{episode}/result")
            assert r.status_code == 404 and "expired after 10 s" in r.json()["detail"]
            r = c.post("/episodes", json=body)
            assert len(store) == 1 and r.status_code == 201, "the expired one was dropped"
    finally:
        app.dependency_overrides.clear()
    with store.using(r.json()["id"]):
        clock.now += 100
        assert store.sweep() == [], "never expired while a request uses it"
    clock.now += 11
    assert len(store.sweep()) == 1


def test_concurrent_steps_of_one_episode_run_one_after_the_other(sim, easy):
    """Each reply's observation is of its own step (rendering releases the GIL: unserialised steps would mix)."""
    app = create_app(SceneRegistry([sim]), Settings(workers=4))
    with TestClient(app) as c:
        r = c.post("/episodes", json={"scenario": _scenario(easy), "privileged": True, **VIEWS})
        episode = f"/episodes/{r.json()['id']}"
        with ThreadPoolExecutor(8) as threads:
            replies = [r.json() for r in threads.map(
                lambda _: c.post(f"{episode}/step", json={"action": [1.0, 0.5]}), range(8))]
        times = sorted(reply["info"]["time"] for reply in replies)
        assert np.allclose(times, 0.1 * np.arange(1, 9), rtol=0, atol=1e-12), times
        for reply in replies:
            np.testing.assert_array_equal(np.float32(reply["observation"]["pose"]), np.float32(reply["info"]["pose"]))
        assert c.get(f"{episode}/result").json()["scorecard"]["steps"] == 8


@pytest.mark.skipif(shutil.which("node") is None, reason="node (Node.js >= 18) is not installed")
def test_the_node_client_drives_an_episode_to_its_scorecard(sim, easy, tmp_path):
    dump_scenario(easy.model_copy(update={"time_limit": 1.0}), tmp_path / "short.yaml")
    app = create_app(SceneRegistry([sim]), Settings(api_key="k"))
    with running_server(app) as url:
        run = subprocess.run(["node", str(ROOT / "docs/examples/episode_client.mjs"), str(tmp_path / "short.yaml"),
                              "--url", url, "--policy", "0.5,0;-0.2,0.3"], capture_output=True, text=True,
                             timeout=60, env={"PATH": os.environ["PATH"], "PARKSIM_API_KEY": "k"})
        assert run.returncode == 0, run.stderr
        lines = [json.loads(line) for line in run.stdout.splitlines()]
        assert [line["step"] for line in lines[:-1]] == list(range(1, 11)) and lines[-2]["truncated"]
        card = lines[-1]["scorecard"]
        assert lines[-1]["done"] and card["steps"] == 10 and math.isclose(card["time"], 1.0)
        assert card["direction_changes"] == 1, "forward, then the held second action reverses"
        assert len(app.state.episodes) == 0, "the client deleted its episode"
        bad = subprocess.run(["node", str(ROOT / "docs/examples/episode_client.mjs"), str(tmp_path / "short.yaml"),
                              "--url", url], capture_output=True, text=True, timeout=60,
                             env={"PATH": os.environ["PATH"]})
        assert bad.returncode == 1 and "401 missing or wrong API key" in bad.stderr


def test_post_render_draws_actors_as_local_sim_does(sim, easy, app):
    x, y, yaw = easy.ego.pose
    ahead = [x + 7.0 * math.cos(yaw), y + 7.0 * math.sin(yaw), yaw + 1.0]
    body = {"poses": [[x, y, yaw]], "cameras": ["front"], "bev": True, "scale": 0.25}
    with TestClient(app) as c:
        bare = decode_npz(c.post("/render", json=body).content)[0][0]
        r = c.post("/render", json={**body, "actors": [{"asset": "car", "pose": ahead}]})
        assert r.status_code == 200, r.text
        drawn = decode_npz(r.content)[0][0]
        r = c.post("/render", json={**body, "actors": [{"asset": "cars/x.ply", "pose": ahead}]})
        assert r.status_code == 422 and "not a built-in asset" in r.json()["detail"]
    want = sim.render([x, y, yaw], ["front"], bev=True, scale=0.25, actors=[Actor(load_actor_asset("car"), ahead)])
    np.testing.assert_array_equal(drawn.images["front"], want.images["front"])
    np.testing.assert_array_equal(drawn.bev, want.bev)
    assert (drawn.images["front"] != bare.images["front"]).any(axis=-1).sum() > 50, "the car shows in front"


def test_a_scene_named_by_a_sets_relative_path_is_the_loaded_scene_of_that_name(sim, easy):
    """``parksim scenarios make`` names the scene by its path relative to the set: its last part picks the loaded
    scene; a path to a scene that is not loaded is 404, as an unknown id."""
    with TestClient(create_app(SceneRegistry([sim]), Settings())) as c:
        made = c.post("/episodes", json={"scenario": _scenario(easy, scene=f"../../scenes/{sim.id}"), "cameras": []})
        assert made.status_code == 201, made.text
        other = c.post("/episodes", json={"scenario": _scenario(easy, scene="../../scenes/elsewhere"), "cameras": []})
        assert other.status_code == 404 and "elsewhere" in other.json()["detail"]
