"""``parksim serve`` against DNS rebinding and key exposure: the Host check, the key only as a header, the key from
a file, and keys that could never match refused at start-up. Raw HTTP requests against real ``parksim serve``
processes on loopback."""

from __future__ import annotations

import http.client
import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from parksim.cli import main
from parksim.server.auth import allowed_hosts, host_name
from sim_fixtures import make_bundle

PARKSIM = str(Path(sys.executable).with_name("parksim"))
KEY = "s3cret-key"
POSE = "12,0.5,0"


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _get(port: int, path: str, host: str, headers: dict[str, str] | None = None) -> tuple[int, dict]:
    """GET ``path`` from 127.0.0.1:``port`` with this exact ``Host`` header, as a rebinding page's browser sends it."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    try:
        conn.putrequest("GET", path, skip_host=True)
        conn.putheader("Host", host)
        for name, value in (headers or {}).items():
            conn.putheader(name, value)
        conn.endheaders()
        reply = conn.getresponse()
        body = reply.read()
        is_json = reply.getheader("content-type", "").startswith("application/json")
        return reply.status, json.loads(body) if is_json else {}
    finally:
        conn.close()


def _wait_up(proc: subprocess.Popen, port: int) -> None:
    deadline = time.monotonic() + 120
    while True:
        try:
            _get(port, "/healthz", f"127.0.0.1:{port}")
            return
        except OSError:
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "parksim serve did not answer within 120 s"
            time.sleep(0.2)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_bundle(tmp_path_factory.mktemp("bundle") / "garage", n=2000)


def _serving(bundle: Path, *argv: str) -> Iterator[int]:
    """The port of a ``parksim serve`` on 127.0.0.1 over ``bundle`` with ``argv``; stopped after."""
    port = _free_port()
    proc = subprocess.Popen([PARKSIM, "serve", "--scenes", str(bundle), "--port", str(port), *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_up(proc, port)
        yield port
    finally:
        proc.terminate()
        proc.communicate(timeout=30)


@pytest.fixture(scope="module")
def open_server(bundle: Path) -> Iterator[int]:
    """Port of ``parksim serve`` on loopback without a key."""
    yield from _serving(bundle)


@pytest.fixture(scope="module")
def keyed_server(bundle: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    """Port of ``parksim serve --api-key-file`` on loopback, the file holding KEY and a newline."""
    key_file = tmp_path_factory.mktemp("key") / "key"
    key_file.write_text(KEY + "\n")
    yield from _serving(bundle, "--api-key-file", str(key_file))


@pytest.mark.parametrize("host", ["evil.example", "evil.example:{port}", "localhost.evil.example:{port}", ""])
@pytest.mark.parametrize("path", ["/scenes", "/healthz", "/"])
def test_a_foreign_host_is_refused_by_a_loopback_server_without_key(open_server, host, path):
    port = open_server
    status, body = _get(port, path, host.format(port=port))
    assert status == 421
    assert f"does not answer to Host {host.format(port=port)!r}: use one of localhost, 127.0.0.1, ::1" in body["detail"]


@pytest.mark.parametrize("host", ["localhost:{port}", "LOCALHOST:{port}", "127.0.0.1:{port}", "[::1]:{port}",
                                  "localhost"])
def test_the_loopback_names_are_answered(open_server, host):
    port = open_server
    status, body = _get(port, "/scenes", host.format(port=port))
    assert status == 200 and [s["id"] for s in body["scenes"]] == ["garage"]


def test_the_key_from_the_file_is_taken_as_a_header_only(keyed_server):
    port = keyed_server
    here, auth = f"localhost:{port}", {"X-API-Key": KEY}
    assert _get(port, "/scenes", here, auth)[0] == 200   # the file's trailing newline is not part of the key
    assert _get(port, "/scenes", here, {"X-API-Key": "wrong"})[0] == 401
    assert _get(port, "/scenes", here)[0] == 401
    for path in (f"/scenes?api_key={KEY}", f"/render?pose={POSE}&scale=0.1&api_key={KEY}",
                 f"/render/front.png?pose={POSE}&scale=0.1&api_key={KEY}"):
        status, body = _get(port, path, here)
        assert status == 400, path
        assert body["detail"] == ("the API key is not accepted in the query string (proxies and browsers log "
                                  "URLs): send it as the X-API-Key header")
    assert _get(port, f"/scenes?api_key={KEY}", here, auth)[0] == 400
    assert _get(port, f"/render/front.png?pose={POSE}&scale=0.1", here, auth)[0] == 200
    assert _get(port, "/scenes", "evil.example", auth)[0] == 421   # the right key does not open a foreign Host


def test_allowed_hosts_follow_the_bound_host():
    assert allowed_hosts("127.0.0.1") == ("localhost", "127.0.0.1", "::1")
    assert allowed_hosts("192.168.1.5") == ("localhost", "127.0.0.1", "::1", "192.168.1.5")
    assert allowed_hosts("[::1]") == ("localhost", "127.0.0.1", "::1")
    assert allowed_hosts("0.0.0.0") is None and allowed_hosts("::") is None
    assert [host_name(h) for h in ("Sim.Lan:80", "[fe80::1]:8000", "fe80::1", "x")] == ["sim.lan", "fe80::1",
                                                                                        "fe80::1", "x"]


def _serve_fails(argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """The one stderr line of ``parksim serve`` failing at start-up with exit status 2 (no scenes there: a run that
    got past the key would fail on loading them instead, never serve)."""
    assert main(["serve", "--scenes", str(tmp_path / "none"), "--port", str(_free_port()), *argv]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("parksim serve: error: "), lines
    return lines[0]


def test_a_missing_or_empty_key_file_is_one_line(tmp_path, capsys):
    missing = tmp_path / "nokey"
    assert f"--api-key-file {missing}: No such file or directory" in _serve_fails(
        ["--api-key-file", str(missing)], tmp_path, capsys)
    for text in ("", "\n", "  \n"):
        (tmp_path / "key").write_text(text)
        assert f"--api-key-file {tmp_path / 'key'}: the file holds no key (it is empty or whitespace only)" in \
            _serve_fails(["--api-key-file", str(tmp_path / "key")], tmp_path, capsys)


@pytest.mark.parametrize("key, message", [
    ("   ", "api_key: the API key is empty or whitespace only"),
    ("", "api_key: the API key is empty or whitespace only"),
    (" k3y", "api_key: the API key starts or ends with whitespace, which HTTP trims from headers"),
])
def test_a_key_that_could_never_match_is_refused_at_start(tmp_path, capsys, monkeypatch, key, message):
    assert message in _serve_fails(["--api-key", key], tmp_path, capsys)
    if key:
        monkeypatch.setenv("PARKSIM_API_KEY", key)
        assert message in _serve_fails([], tmp_path, capsys)
