"""One bundle that fails to load does not stop ``parksim serve``: the good bundles are served, the bad one is refused
with its one-line reason (``/scenes``, ``/healthz``, a warning in the log); ``--strict`` (or ``create_app(...,
strict=True)``) and a folder where no bundle loads fail at start-up with exit status 2 and one line. Real bundles on
disk, a real ``parksim serve`` process and fastapi's TestClient over ``create_app``."""

from __future__ import annotations

import http.client
import json
import logging
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from parksim.bundle import BundleError
from parksim.cli import main
from parksim.server import create_app
from sim_fixtures import make_bundle

PARKSIM = str(Path(sys.executable).with_name("parksim"))
POSE = "12,0.5,0"
TRUNCATED = "gaussians.ply: not a readable PLY file"


def _break_ply(bundle: Path) -> Path:
    """``bundle`` with its gaussians.ply cut in half, as an interrupted copy leaves it."""
    ply = bundle / "gaussians.ply"
    data = ply.read_bytes()
    ply.write_bytes(data[:len(data) // 2])
    return bundle


def _wrong_version(bundle: Path) -> Path:
    """``bundle`` whose bundle.json has a version field this parksim does not read."""
    meta = bundle / "bundle.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "version": 99}))
    return bundle


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A scenes folder: good bundles ``garage_a`` and ``garage_b``, and ``broken`` with a truncated gaussians.ply."""
    root = tmp_path_factory.mktemp("scenes")
    make_bundle(root / "garage_a", n=1500)
    shutil.copytree(root / "garage_a", root / "garage_b")
    shutil.copytree(root / "garage_a", root / "broken")
    _break_ply(root / "broken")
    return root


def _check_refused(body: dict, scenes: Path) -> None:
    [refused] = body["refused"]
    assert refused["id"] == "broken"
    assert refused["reason"].startswith(f"{scenes / 'broken' / TRUNCATED} (")
    assert "\n" not in refused["reason"]


def test_create_app_serves_the_good_bundles_and_lists_the_bad_one(scenes, caplog):
    with caplog.at_level(logging.WARNING, logger="parksim.server.scenes"):
        client = TestClient(create_app(scenes))
    [warning] = caplog.records
    assert warning.levelno == logging.WARNING
    assert warning.getMessage().startswith(f"refused scene 'broken': {scenes / 'broken' / TRUNCATED}")

    listed = client.get("/scenes").json()
    assert [s["id"] for s in listed["scenes"]] == ["garage_a", "garage_b"]
    _check_refused(listed, scenes)
    health = client.get("/healthz").json()
    assert health["status"] == "ok" and health["scenes"] == ["garage_a", "garage_b"]
    _check_refused(health, scenes)
    for scene in ("garage_a", "garage_b"):
        reply = client.get(f"/render/front.png?pose={POSE}&scale=0.1&scene={scene}")
        assert reply.status_code == 200 and reply.content.startswith(b"\x89PNG")
    assert client.get(f"/render/front.png?pose={POSE}&scale=0.1&scene=broken").status_code == 404


def test_create_app_strict_raises_the_bad_bundles_error(scenes):
    with pytest.raises(BundleError, match="broken/gaussians.ply: not a readable PLY file"):
        create_app(scenes, strict=True)


def test_a_folder_of_good_bundles_refuses_none(scenes, tmp_path):
    shutil.copytree(scenes / "garage_a", tmp_path / "garage_a")
    client = TestClient(create_app(tmp_path))
    assert client.get("/scenes").json()["refused"] == [] and client.get("/healthz").json()["refused"] == []


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _get(port: int, path: str) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    try:
        conn.request("GET", path)
        reply = conn.getresponse()
        return reply.status, reply.read()
    finally:
        conn.close()


def test_parksim_serve_serves_the_good_bundles_and_logs_the_bad_one(scenes):
    port = _free_port()
    proc = subprocess.Popen([PARKSIM, "serve", "--scenes", str(scenes), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                status, body = _get(port, "/healthz")
                break
            except OSError:
                assert proc.poll() is None, proc.communicate()[1]
                assert time.monotonic() < deadline, "parksim serve did not answer within 120 s"
                time.sleep(0.2)
        assert status == 200
        health = json.loads(body)
        assert health["scenes"] == ["garage_a", "garage_b"]
        _check_refused(health, scenes)
        status, body = _get(port, "/scenes")
        assert status == 200
        _check_refused(json.loads(body), scenes)
        for scene in ("garage_a", "garage_b"):
            status, body = _get(port, f"/render/rear.png?pose={POSE}&scale=0.1&scene={scene}")
            assert status == 200 and body.startswith(b"\x89PNG")
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    assert any(line.startswith(f"refused scene 'broken': {scenes / 'broken' / TRUNCATED} (")
               for line in err.splitlines()), err
    assert out.splitlines()[0].startswith(f"serving garage_a, garage_b on http://127.0.0.1:{port} ")
    assert out.splitlines()[0].endswith("; refused broken (see /scenes)")


def test_parksim_serve_strict_exits_2_on_the_bad_bundle(scenes, capsys):
    assert main(["serve", "--scenes", str(scenes), "--port", str(_free_port()), "--strict"]) == 2
    [line] = capsys.readouterr().err.splitlines()
    assert line.startswith(f"parksim serve: error: {scenes / 'broken' / TRUNCATED} (")


def test_parksim_serve_exits_2_when_no_bundle_loads(scenes, tmp_path, capsys):
    _break_ply(make_bundle(tmp_path / "cut", n=300))
    _wrong_version(make_bundle(tmp_path / "future", n=300))
    assert main(["serve", "--scenes", str(tmp_path), "--port", str(_free_port())]) == 2
    [line] = capsys.readouterr().err.splitlines()
    assert line.startswith(f"parksim serve: error: no scene to serve: every bundle was refused (cut: "
                           f"{tmp_path / 'cut' / TRUNCATED} (")
    assert line.endswith(f"; future: {tmp_path / 'future' / 'bundle.json'}: bundle version 99 is not the supported "
                         "version 1)")
