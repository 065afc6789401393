"""The service's self-description and wiring: /docs works offline, the OpenAPI schema documents the npz layout,
the API key scheme, the X-Render-* headers and exactly the errors each route can give; handlers take their state
from overridable dependencies; each app has its own Prometheus registry."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from parksim.server import Settings, create_app
from parksim.server.deps import get_registry, get_settings
from parksim.server.scenes import SceneRegistry
from parksim.sim import LocalSim
from sim_fixtures import make_bundle

POSE = "12.0,0.3,0.2"


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("scenes") / "tiny", n=500, bev_px=100)


@pytest.fixture(scope="module")
def app(bundle_dir):
    return create_app({"tiny": bundle_dir})


def test_docs_need_no_internet(app):
    """Swagger UI's page names only this server's URLs, and each of them answers."""
    with TestClient(app) as c:
        html = c.get("/docs").text
        assert "SwaggerUIBundle" in html and not re.search(r"https?://", html), html
        refs = re.findall(r'(?:src|href)="([^"]+)"', html) + re.findall(r"url: '([^']+)'", html)
        assert {r.rsplit(".", 1)[-1] for r in refs} >= {"js", "css", "png", "json"}, refs
        for ref in refs:
            r = c.get(ref)
            assert r.status_code == 200 and r.content, ref
        assert c.get("/redoc").status_code == 404, "ReDoc only loads from a CDN, so it is not served"


def _operations(spec: dict) -> dict[tuple[str, str], dict]:
    return {(path, method): op for path, ops in spec["paths"].items() for method, op in ops.items()}


def test_openapi_lists_only_the_errors_each_route_can_give(app):
    errors = {key: {c for c in op["responses"] if not c.startswith("2")}   # 200, 201, 204: not errors
              for key, op in _operations(app.openapi()).items()}
    assert errors == {
        ("/healthz", "get"): set(),
        ("/metrics", "get"): {"401"},
        ("/scenes", "get"): {"401"},
        ("/scenes/{scene_id}", "get"): {"401", "404", "422"},
        ("/render", "get"): {"401", "404", "413", "422", "503"},
        ("/render", "post"): {"400", "401", "404", "411", "413", "422", "503"},
        ("/render/{view}.{ext}", "get"): {"401", "404", "413", "422", "503"},
        ("/episodes", "post"): {"400", "401", "404", "411", "413", "422", "503"},
        ("/episodes/{episode_id}/step", "post"): {"400", "401", "404", "409", "411", "413", "422", "503"},
        ("/episodes/{episode_id}/result", "get"): {"401", "404", "422", "503"},
        ("/episodes/{episode_id}", "delete"): {"401", "404", "422"},
    }


def test_openapi_documents_the_key_the_npz_and_the_headers(app):
    spec = app.openapi()
    scheme = spec["components"]["securitySchemes"]["APIKeyHeader"]
    assert (scheme["type"], scheme["in"], scheme["name"]) == ("apiKey", "header", "X-API-Key")
    ops = _operations(spec)
    assert "security" not in ops[("/healthz", "get")]
    for key, op in ops.items():
        if key[0] != "/healthz":
            assert {"APIKeyHeader": []} in op["security"], key
    media = {("/render", "get"): {"application/x-npz", "image/png", "image/jpeg"},
             ("/render", "post"): {"application/x-npz"}, ("/render/{view}.{ext}", "get"): {"image/png", "image/jpeg"}}
    for key, types in media.items():
        ok = ops[key]["responses"]["200"]
        assert set(ok["content"]) == types and set(ok["headers"]) == {"X-Render-Timings", "X-Render-Time-Ms"}, key
        assert "Retry-After" in ops[key]["responses"]["503"]["headers"], key
    npz = ops[("/render", "post")]["responses"]["200"]
    for words in ("images/<camera>  uint8 [H, W, 3]", "depth/<camera>   float32 [H, W]", "bev              uint8",
                  "meta", "[B, H, W, 3]"):
        assert words in npz["description"], words


def test_handlers_take_their_state_from_overridable_dependencies(app, bundle_dir):
    """Swapping the registry and the settings changes what every handler (and the API key check) sees."""
    app.dependency_overrides[get_registry] = lambda: SceneRegistry([LocalSim(bundle_dir, "other")])
    app.dependency_overrides[get_settings] = lambda: Settings(max_batch=1, api_key="k")
    try:
        with TestClient(app) as c:
            assert c.get("/healthz").json()["scenes"] == ["other"]
            assert c.get("/scenes").status_code == 401
            key = {"X-API-Key": "k"}
            assert [s["id"] for s in c.get("/scenes", headers=key).json()["scenes"]] == ["other"]
            r = c.post("/render", json={"poses": [[12, 0, 0]] * 2, "scale": 0.25}, headers=key)
            assert r.status_code == 422 and "at most 1 are allowed" in r.json()["detail"]
            r = c.get("/render", params={"pose": POSE, "cameras": "front", "scale": 0.25, "scene": "tiny"}, headers=key)
            assert r.status_code == 404 and "loaded scenes: ['other']" in r.json()["detail"]
    finally:
        app.dependency_overrides.clear()


def test_each_app_has_its_own_metrics_registry(bundle_dir):
    """Two apps in one process count their own requests (a shared global registry would clash or mix them)."""
    one, two = create_app({"tiny": bundle_dir}), create_app({"tiny": bundle_dir})
    assert one.state.metrics.registry is not two.state.metrics.registry
    with TestClient(one) as c1, TestClient(two) as c2:
        for _ in range(3):
            c1.get("/scenes")
        c2.get("/scenes")

        def scenes_count(c: TestClient) -> float:
            families = {f.name: f for f in text_string_to_metric_families(c.get("/metrics").text)}
            return sum(s.value for s in families["parksim_requests"].samples
                       if s.name == "parksim_requests_total" and s.labels["route"] == "/scenes")

        assert (scenes_count(c1), scenes_count(c2)) == (3, 1)
