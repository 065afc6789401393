"""Simulator service: renders, every bad-input class answered 4xx, fuzzing finds no 500, 503 on a full queue,
concurrent requests get their own images, API key, metrics."""

from __future__ import annotations

import asyncio
import json
import threading
from concurrent.futures import ThreadPoolExecutor

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families

from parksim.client import RemoteSim
from parksim.frames import decode_npz
from parksim.server import Settings, create_app
from parksim.server.auth import check_bind
from parksim.sim import LocalSim
from sim_fixtures import make_bundle, running_server

POSE = "12.0,0.3,0.2"
SMALL = {"scale": 0.25}


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("scenes") / "tiny", n=2000, bev_px=100)


@pytest.fixture(scope="module")
def app(bundle_dir):
    return create_app(bundle_dir.parent, Settings(max_batch=4))


@pytest.fixture(scope="module")
def client(app):
    with TestClient(app) as c:
        yield c


def test_scenes_and_health(client):
    assert client.get("/healthz").json()["scenes"] == ["tiny"]
    assert client.get("/scenes").json()["scenes"][0] == {"id": "tiny", "gaussians": 2000,
                                                        "cameras": ["front", "rear", "left", "right"]}
    info = client.get("/scenes/tiny").json()
    assert set(info["rig"]["cameras"]) == {"front", "rear", "left", "right"} and info["bev"]["width"] == 100
    assert info["bounds"]["x"] == [0.0, 34.0] and info["map"]["slots"] and info["pose_margin_m"] == 5.0


def test_render_returns_only_what_is_asked(client):
    r = client.get("/render", params={"pose": POSE, "cameras": "front,left", **SMALL})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-npz"
    (frame,), meta = decode_npz(r.content)
    assert set(frame.images) == {"front", "left"} and frame.bev is None and not frame.depth
    assert frame.images["front"].shape == (30, 40, 3) and frame.images["front"].dtype == np.uint8
    assert frame.images["front"].std() > 1, "a real scene renders texture, not a flat image"
    assert meta["sizes"]["front"] == [40, 30] and meta["poses"][0]["yaw"] == 0.2
    (bev_only,), _ = decode_npz(client.get("/render", params={"pose": POSE, "cameras": "", "bev": "on",
                                                               "depth": "on", **SMALL}).content)
    assert not bev_only.images and bev_only.bev.shape == (100, 100, 3)


def test_single_view_images_match_npz(client):
    params = {"pose": POSE, **SMALL}
    (frame,), _ = decode_npz(client.get("/render", params={**params, "cameras": "rear", "bev": "on"}).content)
    png = client.get("/render/rear.png", params=params)
    assert png.headers["content-type"] == "image/png"
    decoded = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_array_equal(decoded, frame.images["rear"])
    bev = client.get("/render/bev.png", params=params)
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(bev.content, np.uint8), cv2.IMREAD_COLOR)[..., ::-1],
                                  frame.bev)
    assert client.get("/render/front.jpeg", params=params).headers["content-type"] == "image/jpeg"
    fmt = client.get("/render", params={**params, "cameras": "front", "format": "png"})
    assert fmt.headers["content-type"] == "image/png"


def test_batch_post(client):
    r = client.post("/render", json={"poses": [[12, 0, 0], {"x": 14, "y": 0.5, "yaw": 0.1}], "cameras": ["front"],
                                     **SMALL})
    frames, meta = decode_npz(r.content)
    assert r.status_code == 200 and meta["batch"] == 2 and len(frames) == 2
    assert not np.array_equal(frames[0].images["front"], frames[1].images["front"])


@pytest.mark.parametrize("params, status, words", [
    ({"pose": "1,2"}, 422, "3 comma-separated numbers"),
    ({"pose": "1,two,3"}, 422, "not a number"),
    ({"pose": "nan,0,0"}, 422, "finite"),
    ({"pose": "1,inf,0"}, 422, "finite"),
    ({"pose": "1_2,0,0"}, 422, "not a number in decimal notation"),
    ({"pose": "\u0661\u0662,0,0"}, 422, "not a number in decimal notation"),
    ({"pose": "500,0,0"}, 422, "x must be in"),
    ({"pose": "10,-40,0"}, 422, "y must be in"),
    ({"pose": "10,0,9,0,0,0"}, 422, "z must be in"),
    ({"pose": "10,0,0,1.5,0,0"}, 422, "roll"),
    ({}, 422, "pose: Field required"),
    ({"pose": POSE, "scene": "garage9"}, 404, "loaded scenes: ['tiny']"),
    ({"pose": POSE, "cameras": "front,top"}, 422, "has ['front', 'rear', 'left', 'right']"),
    ({"pose": POSE, "cameras": "front,front"}, 422, "['front'] asked for twice"),
    ({"pose": POSE, "scale": "3"}, 422, "[0.05, 2]"),
    ({"pose": POSE, "scale": "0"}, 422, "[0.05, 2]"),
    ({"pose": POSE, "scale": "nan"}, 422, "[0.05, 2]"),
    ({"pose": POSE, "bev": "maybe"}, 422, "boolean"),
    ({"pose": POSE, "format": "gif"}, 422, "'npz', 'png' or 'jpeg'"),
    ({"pose": POSE, "format": "png"}, 422, "exactly one view"),
    ({"pose": POSE, "cameras": ""}, 422, "nothing to render"),
    ({"pose": POSE, "colour": "red"}, 422, "colour: Extra inputs"),
])
def test_bad_get_is_4xx_with_reason(client, params, status, words):
    r = client.get("/render", params=params)
    assert r.status_code == status and words in r.json()["detail"], r.text


@pytest.mark.parametrize("path, status, words", [
    ("/render/top.png?pose=12,0,0", 422, "unknown camera"),
    ("/render/front.gif?pose=12,0,0", 422, "'png', 'jpg' or 'jpeg'"),
    ("/scenes/nope", 404, "unknown scene"),
    ("/no/such/route", 404, "no route"),
])
def test_bad_paths_are_4xx(client, path, status, words):
    r = client.get(path)
    assert r.status_code == status and words in r.json()["detail"]


@pytest.mark.parametrize("body, status, words", [
    ({"poses": [[12, 0, 0]] * 5}, 422, "at most 4"),
    ({"poses": []}, 422, "at least 1"),
    ({"poses": [[12, 0]]}, 422, "3 values"),
    ({"poses": [[12, 0, 0]], "scale": 10}, 422, "[0.05, 2]"),
    ({"poses": [[12, 0, 0]], "cameras": ["up"]}, 422, "unknown camera"),
    ({"poses": [[12, 0, 0]], "cameras": ["rear", "front", "rear"]}, 422, "['rear'] asked for twice"),
    ({"poses": [["1_2", 0, 0]]}, 422, "'1_2' is not a number in decimal notation"),
    ({"poses": [{"x": "\u0661\u0662", "y": 0, "yaw": 0}]}, 422, "is not a number in decimal notation"),
    ({"poses": [[12, True, 0]]}, 422, "boolean"),
    (b'{"poses": [[NaN, 0, 0]]}', 422, "finite"),
    (b"{not json", 400, "not valid JSON"),
    (b"x" * (2 << 20), 413, "Content-Length"),
])
def test_bad_post_is_4xx(client, body, status, words):
    r = (client.post("/render", json=body) if isinstance(body, dict) else
         client.post("/render", content=body, headers={"content-type": "application/json"}))
    assert r.status_code == status and words in r.json()["detail"], r.text


_text = st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=30)
_number = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-100, 100).map(str), _text)


@hsettings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pose=st.one_of(st.lists(_number, min_size=0, max_size=7).map(",".join), _text),
       scale=st.one_of(st.sampled_from(["0.1", "0.25"]), _number),
       cameras=st.one_of(st.none(), st.sampled_from(["front", "", "left,rear", "bev"]), _text),
       bev=st.sampled_from(["off", "on", "x", ""]), fmt=st.sampled_from(["npz", "png", "jpeg", "tiff"]),
       scene=st.one_of(st.none(), st.just("tiny"), _text))
def test_fuzz_get_never_500(client, pose, scale, cameras, bev, fmt, scene):
    params = {"pose": pose, "scale": scale, "bev": bev, "format": fmt}
    params.update({k: v for k, v in (("cameras", cameras), ("scene", scene)) if v is not None})
    assert client.get("/render", params=params).status_code < 500


_json = st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | _text,
                     lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_text, inner, max_size=4),
                     max_leaves=12)


@hsettings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(body=st.one_of(_json, st.fixed_dictionaries(
    {"poses": st.lists(st.lists(st.floats(-50, 50) | st.integers(-50, 50), min_size=2, max_size=7), max_size=5)},
    optional={"cameras": st.lists(st.sampled_from(["front", "rear", "x"]), max_size=3), "scale": st.floats(),
              "bev": st.booleans(), "scene": _text})))
def test_fuzz_post_never_500(client, body):
    payload = body if not isinstance(body, dict) or "scale" in body else {**body, "scale": 0.1}
    # Sent as raw text: NaN/Infinity tokens are not JSON, and the server must turn them down with a 4xx.
    r = client.post("/render", content=json.dumps(payload, allow_nan=True),
                    headers={"content-type": "application/json"})
    assert r.status_code < 500


def test_full_queue_answers_503_with_retry_after(bundle_dir):
    app = create_app({"tiny": bundle_dir}, Settings(workers=1, queue_size=0, retry_after_s=2))
    release, started = threading.Event(), threading.Event()

    def block() -> None:
        started.set()
        release.wait(30)

    holder = threading.Thread(target=lambda: asyncio.run(app.state.pool.run(block)))
    holder.start()
    try:
        assert started.wait(10)
        with TestClient(app) as c:
            r = c.get("/render", params={"pose": POSE, "cameras": "front", **SMALL})
            assert r.status_code == 503 and r.headers["retry-after"] == "2" and "queue full" in r.json()["detail"]
            release.set()
            holder.join(10)
            assert c.get("/render", params={"pose": POSE, "cameras": "front", **SMALL}).status_code == 200
            assert "parksim_render_rejected_total 1" in c.get("/metrics").text
    finally:
        release.set()


def test_concurrent_requests_get_their_own_images(app, bundle_dir):
    poses = [(8.0 + 2 * i, 0.2 * (i % 3), 0.15 * i) for i in range(6)]
    local = LocalSim.from_dir(bundle_dir)
    expected = [local.render(p, ["front"], scale=0.25).images["front"] for p in poses]
    with running_server(app) as url:
        remote = RemoteSim(url, scene="tiny")
        with ThreadPoolExecutor(6) as ex:
            got = list(ex.map(lambda p: remote.render(p, ["front"], scale=0.25).images["front"], poses))
    for g, e in zip(got, expected):
        np.testing.assert_array_equal(g, e)
    assert len({g.tobytes() for g in got}) == len(poses)


def test_api_key_and_bind_policy(bundle_dir):
    app = create_app({"tiny": bundle_dir}, Settings(api_key="s3cret"))
    with TestClient(app) as c:
        assert c.get("/healthz").status_code == 200
        r = c.get("/scenes")
        assert r.status_code == 401 and "X-API-Key" in r.json()["detail"]
        assert c.get("/scenes", headers={"X-API-Key": "wrong"}).status_code == 401
        assert c.get("/scenes", headers={"X-API-Key": "s3cret"}).status_code == 200
        png = c.get("/render/front.png", params={"pose": POSE, **SMALL}, headers={"X-API-Key": "s3cret"})
        assert png.status_code == 200
    check_bind("127.0.0.1", None)
    check_bind("0.0.0.0", "key")
    with pytest.raises(ValueError, match="API key"):
        check_bind("0.0.0.0", None)


def _samples(text: str) -> dict[str, list]:
    """Prometheus exposition -> samples by name, parsed by prometheus_client's own parser."""
    out: dict[str, list] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            out.setdefault(sample.name, []).append(sample)
    return out


def test_metrics_and_docs(client):
    client.get("/render", params={"pose": POSE, "cameras": "front", **SMALL})
    client.get("/render", params={"pose": "1,2"})
    samples = _samples(client.get("/metrics").text)
    requests = {(s.labels["route"], s.labels["method"], s.labels["status"]): s.value
                for s in samples["parksim_requests_total"]}
    assert requests[("/render", "GET", "200")] >= 1 and requests[("/render", "GET", "422")] >= 1
    assert any(s.labels == {"status": "422"} and s.value >= 1 for s in samples["parksim_errors_total"])
    assert any(s.labels == {"stage": "views", "le": "+Inf"} and s.value >= 1
               for s in samples["parksim_render_stage_seconds_bucket"])
    assert samples["parksim_request_seconds_count"] and samples["parksim_images_total"][0].value >= 1
    assert samples["parksim_render_capacity"][0].value == 9 and samples["parksim_reply_budget_bytes"][0].value > 0
    spec = client.get("/openapi.json").json()
    params = {p["name"]: p for p in spec["paths"]["/render"]["get"]["parameters"]}
    assert set(params) >= {"pose", "scene", "cameras", "bev", "scale", "depth", "format"}
    assert all(p.get("description") for p in params.values())


def test_remote_client_reports_server_errors(app):
    with running_server(app) as url:
        remote = RemoteSim(url)
        with pytest.raises(ValueError, match="422.*x must be in"):
            remote.render((900.0, 0.0, 0.0), ["front"], scale=0.25)
        assert httpx.get(f"{url}/healthz").status_code == 200


def test_a_scene_is_served_with_the_projection_it_was_trained_with(bundle_dir, tmp_path):
    """An EWA-trained bundle (bundle.json "projection": "ewa") renders through EWA, not the UT default: the same
    pixels as ``render(..., method="ewa")``, and not UT's (an EWA scene served through UT scored 12 dB lower)."""
    from parksim.bundle import load, save
    from parksim.imageio import to_uint8
    from parksim.render import render

    ewa = load(bundle_dir)
    ewa.meta["projection"] = "ewa"
    save(tmp_path / "ewa", ewa)
    sim, pose = LocalSim(load(tmp_path / "ewa"), "ewa"), [12.0, 0.3, 0.2]
    served = sim.render(pose, ["front"], scale=0.25).images["front"]
    for method, same in (("ewa", True), ("ut", False)):
        want = to_uint8(render(ewa.scene, ewa.rig, pose, cameras=["front"], scale=0.25, method=method).images["front"])
        assert np.array_equal(served, want) == same, method
