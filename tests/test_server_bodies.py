"""``POST /render`` bodies: one that cannot be parsed as JSON is 400, a parsed one with a bad value is 422.

Both come back as the server's JSON ``{"detail": ...}`` naming what is wrong (docs/http.md, Errors).
"""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from parksim.server import create_app
from sim_fixtures import make_bundle


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    app = create_app({"tiny": make_bundle(tmp_path_factory.mktemp("scenes") / "tiny", n=300, bev_px=64)})
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def _post(client: TestClient, body: bytes):
    r = client.post("/render", content=body, headers={"content-type": "application/json"})
    assert r.headers["content-type"] == "application/json", (r.status_code, r.headers, r.text[:200])
    return r


@pytest.mark.parametrize("body, words", [
    (b'{"poses": ' + b"[" * 10_000 + b"]" * 10_000 + b"}", "nested too deeply"),
    (b'{"poses": [[' + b"9" * 5_000 + b", 0, 0]]}", "an integer has more than 4300 digits"),
    (b'{"poses": [[12, 0, 0]], "scene": "\xff\xfe"}', "not valid UTF-8: byte 0xff at offset 34"),
    (b'{"poses": [[12, 0, 0]', "not valid JSON: Expecting ',' delimiter at character 21"),
    ('{"poses": [[12, 0, 0]]}'.encode("utf-16-le"), "not UTF-8: it holds NUL bytes"),
    ('{"poses": [[12, 0, 0]]}'.encode("utf-16"), "UTF-16/32 byte-order mark"),
    ('{"poses": [[12, 0, 0]]}'.encode("utf-32-be"), "not UTF-8"),
], ids=["deep", "huge-int", "not-utf8", "malformed", "utf16-le", "utf16-bom", "utf32"])
def test_unparsable_body_is_400_naming_why(client, body, words):
    r = _post(client, body)
    assert r.status_code == 400 and words in r.json()["detail"], r.text[:300]


@pytest.mark.parametrize("body, words", [
    (b'{"poses": [[12, 0, 0]], "scale": 99}', "scale=99 is out of range"),
    (b'{"poses": "here"}', "poses"),
    (b'{"poses": [[12, 0, 0]], "colour": "red"}', "colour"),
], ids=["out-of-range", "wrong-type", "unknown-key"])
def test_parsed_body_with_a_bad_value_is_422(client, body, words):
    r = _post(client, body)
    assert r.status_code == 422 and words in r.json()["detail"], r.text[:300]
