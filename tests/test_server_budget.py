"""Reply memory is bounded by bytes: a request whose reply would be too large is refused before rendering (413),
and the bytes of replies not yet sent (a client that never reads) hold a global budget until the send ends (503)."""

from __future__ import annotations

import json
import socket
import time

import httpx
import pytest
from fastapi.testclient import TestClient

from parksim.server import Settings, create_app
from parksim.sim import LocalSim
from sim_fixtures import make_bundle, running_server

SMALL = {"pose": "12,0,0", "cameras": "front", "scale": "0.25"}


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("scenes") / "tiny", n=2000, bev_px=100)


@pytest.mark.parametrize("body", [
    {"poses": [[12, 0, 0]], "cameras": ["front"], "scale": 0.25},
    {"poses": [[12, 0, 0], [14, 0.5, 0.1], [9, 0, 0]], "bev": True, "depth": True, "scale": 0.5},
    {"poses": [[12, 0, 0]], "cameras": [], "bev": True, "scale": 1.0},
])
def test_reply_size_is_bounded_before_rendering(bundle_dir, body):
    """The size counted before rendering is an upper bound of the reply, and a tight one (headers and meta only)."""
    sim = LocalSim.from_dir(bundle_dir)
    names = sim.check(body.get("cameras"), body["scale"])
    bound = sim.reply_bytes(len(body["poses"]), names, body.get("bev", False), body["scale"], body.get("depth", False))
    with TestClient(create_app({"tiny": bundle_dir})) as c:
        r = c.post("/render", json=body)
    assert r.status_code == 200 and len(r.content) <= bound <= len(r.content) + 64 * 1024


def _post_and_never_read(url: str, body: dict) -> socket.socket:
    """A raw client that sends ``POST /render`` and then reads nothing (a tiny receive window, as a stalled peer)."""
    host, port = url.removeprefix("http://").split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    data = json.dumps(body).encode()
    sock.sendall(b"POST /render HTTP/1.1\r\nHost: %s\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n%s"
                 % (host.encode(), len(data), data))
    return sock


def _wait_for(url: str, done, timeout: float = 300.0) -> dict:
    """Poll /healthz until ``done(health)``; the last health."""
    deadline = time.monotonic() + timeout
    while True:
        health = httpx.get(f"{url}/healthz").json()
        if done(health):
            return health
        assert time.monotonic() < deadline, f"server state never reached: {health}"
        time.sleep(0.05)


def test_413_and_503_while_an_unread_reply_holds_the_budget(bundle_dir):
    """On a real uvicorn server on loopback: a too large request is refused with both sizes named; a reply that its
    client does not read keeps its bytes reserved after rendering ended, so the next request gets 503 with
    Retry-After; when that client goes, the bytes come back and requests are served again."""
    sim = LocalSim.from_dir(bundle_dir)
    big = {"poses": [[12, 0, 0], [14, 0.5, 0.1]] * 4, "bev": True, "depth": True, "scale": 2.0}
    limit = sim.reply_bytes(8, sim.cameras, True, 2.0, True)      # 17 MB: more than the socket buffers take
    app = create_app({"tiny": bundle_dir}, Settings(max_batch=16, max_reply_bytes=limit, reply_budget_bytes=limit,
                                                    retry_after_s=3))
    with running_server(app) as url:
        r = httpx.post(f"{url}/render", json={**big, "poses": big["poses"] + [[10, 0, 0]]})
        too_large = sim.reply_bytes(9, sim.cameras, True, 2.0, True)
        assert r.status_code == 413, r.text
        assert f"would be {too_large} bytes" in r.json()["detail"] and f"limit of {limit} bytes" in r.json()["detail"]
        assert httpx.get(f"{url}/healthz").json()["replies"]["in_flight_bytes"] == 0, "nothing reserved for a 413"

        stalled = _post_and_never_read(url, big)
        try:
            health = _wait_for(url, lambda h: h["pool"]["in_flight"] == 0 and h["replies"]["in_flight_bytes"] > 0)
            assert health["replies"]["in_flight_bytes"] == limit, "rendering is over, the unsent reply still counts"
            time.sleep(0.5)
            r = httpx.get(f"{url}/render", params=SMALL)
            assert r.status_code == 503 and r.headers["retry-after"] == "3", r.text
            assert f"{limit} of {limit} bytes are held" in r.json()["detail"]
        finally:
            stalled.close()
        _wait_for(url, lambda h: h["replies"]["in_flight_bytes"] == 0, timeout=30)
        assert httpx.get(f"{url}/render", params=SMALL).status_code == 200
        assert httpx.get(f"{url}/healthz").json()["replies"]["rejected"] == 1


def test_settings_refuse_a_budget_smaller_than_one_reply():
    with pytest.raises(ValueError, match=r"^server settings: settings: reply_budget_bytes \(268435456\) must be at "
                                         r"least max_reply_bytes \(1073741824\)[^\n]*$"):
        Settings.from_env(max_reply_bytes=1 << 30)
    assert Settings.from_env(max_reply_bytes=1 << 30, reply_budget_bytes=1 << 30).max_reply_bytes == 1 << 30
