"""``parksim serve --ray``: the Ray Serve deployment answers as the single-process app does (same images, same 4xx
status and detail), follows --replicas, stops on Ctrl-C; without Ray the command says what to install."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from parksim.bench.procs import free_port
from parksim.cli import main
from parksim.frames import decode_npz
from parksim.server import Settings, create_app
from sim_fixtures import make_bundle

ray = pytest.importorskip("ray")
serve = pytest.importorskip("ray.serve")

PARKSIM = str(Path(sys.executable).with_name("parksim"))
KEY = "s3cret"
AUTH = {"X-API-Key": KEY}
POSE = "12.0,0.3,0.2"


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("scenes") / "tiny", n=2000, bev_px=100)


@pytest.fixture(scope="module")
def cluster():
    """One small local Ray instance for the module; its GCS address."""
    ray.init(num_cpus=2, object_store_memory=150 * 1024**2, include_dashboard=False, logging_level="ERROR",
             log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        serve.shutdown()
        ray.shutdown()


@pytest.fixture(scope="module")
def served(cluster, bundle_dir, tmp_path_factory):
    """``parksim serve --ray`` joined to the module's cluster with two replicas and an API key; (process, URL, its
    stderr log). Python's fault handler is on in it, so SIGABRT writes every thread's stack to that log."""
    port = free_port()
    log = tmp_path_factory.mktemp("log") / "serve.err"
    with log.open("w") as err:
        proc = subprocess.Popen([PARKSIM, "serve", "--ray", "--address", cluster, "--replicas", "2", "--api-key", KEY,
                                 "--scenes", str(bundle_dir.parent), "--port", str(port)],
                                stdout=subprocess.DEVNULL, stderr=err, env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 240
        while not _answers(base):
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.5)
        yield proc, base, log
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)


def _answers(base: str) -> bool:
    try:
        return httpx.get(f"{base}/healthz", timeout=5).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.fixture(scope="module")
def both(served, bundle_dir):
    """(Serve client, in-process client of ``create_app`` with the same settings)."""
    with httpx.Client(base_url=served[1], timeout=120) as remote, \
            TestClient(create_app(bundle_dir.parent, Settings(api_key=KEY))) as local:
        yield remote, local


def test_renders_are_the_single_process_servers(both):
    remote, local = both
    params = {"pose": POSE, "scale": 0.25, "bev": "on", "depth": "on"}
    (a,), meta_a = decode_npz(_ok(remote.get("/render", params=params, headers=AUTH)).content)
    (b,), meta_b = decode_npz(_ok(local.get("/render", params=params, headers=AUTH)).content)
    assert set(a.images) == set(b.images) == {"front", "rear", "left", "right"} and meta_a["sizes"] == meta_b["sizes"]
    for name in b.images:
        np.testing.assert_array_equal(a.images[name], b.images[name])
        np.testing.assert_array_equal(a.depth[name], b.depth[name])
    np.testing.assert_array_equal(a.bev, b.bev)
    png = {"pose": POSE, "scale": 0.5}
    png_remote, png_local = (_ok(c.get("/render/left.png", params=png, headers=AUTH)).content for c in (remote, local))
    assert png_remote == png_local
    body = {"poses": [[12, 0.3, 0.2], [20, -0.2, 1.0]], "cameras": ["rear"], "scale": 0.25}
    (ra, rb), _ = decode_npz(_ok(remote.post("/render", json=body, headers=AUTH)).content)
    (la, lb), _ = decode_npz(_ok(local.post("/render", json=body, headers=AUTH)).content)
    np.testing.assert_array_equal(ra.images["rear"], la.images["rear"])
    np.testing.assert_array_equal(rb.images["rear"], lb.images["rear"])


@pytest.mark.parametrize("method, path, params, headers", [
    ("GET", "/render", {"pose": "12,0.3"}, AUTH),                      # bad pose string: 422
    ("GET", "/render", {"pose": POSE, "scene": "nosuch"}, AUTH),       # unknown scene: 404
    ("GET", "/render", {"pose": POSE, "scale": "9"}, AUTH),            # scale out of range: 422
    ("GET", "/render", {"pose": POSE}, {}),                           # missing API key: 401
    ("GET", "/scenes", {}, {"X-API-Key": "wrong"}),                    # wrong API key: 401
    ("GET", "/scenes/nosuch", {}, AUTH),                               # unknown scene: 404
    ("GET", "/nosuch", {}, AUTH),                                      # unknown route: 404
    ("DELETE", "/render", {}, AUTH),                                   # method not allowed: 405
])
def test_bad_input_gets_the_same_status_and_detail(both, method, path, params, headers):
    remote, local = both
    a = remote.request(method, path, params=params, headers=headers)
    b = local.request(method, path, params=params, headers=headers)
    assert 400 <= b.status_code < 500
    assert (a.status_code, a.json()) == (b.status_code, b.json())


def test_scenes_health_and_viewer_answer(both):
    remote, local = both
    for path in ("/scenes", "/scenes/tiny"):
        assert _ok(remote.get(path, headers=AUTH)).json() == _ok(local.get(path, headers=AUTH)).json()
    health = _ok(remote.get("/healthz")).json()
    assert health["scenes"] == ["tiny"] and health["pool"]["capacity"] == 9
    assert _ok(remote.get("/")).text == _ok(local.get("/")).text
    assert "parksim_requests_total" in _ok(remote.get("/metrics", headers=AUTH)).text


def test_replicas_follow_the_flag(served):
    deployment = serve.status().applications["parksim"].deployments["SimReplica"]
    assert deployment.replica_states == {"RUNNING": 2}


def test_ctrl_c_takes_the_deployment_down(served):
    proc, base, log = served
    proc.send_signal(signal.SIGINT)
    try:
        assert proc.wait(120) == 0
    except subprocess.TimeoutExpired:   # its stacks showed the cause once (serve.wait_for_interrupt): keep them
        proc.send_signal(signal.SIGABRT)
        proc.wait(30)
        pytest.fail("parksim serve --ray still ran 120 s after Ctrl-C; its stderr and stacks:\n"
                    + log.read_text()[-6000:])
    assert "parksim" not in serve.status().applications
    assert not _answers(base)


def test_without_ray_the_command_says_what_to_install(bundle_dir):
    """With ``ray`` unimportable, --ray is one line and exit 2; the single-process app and its flag checks work."""
    code = ("import sys; sys.modules['ray'] = None\n"
            "from parksim.cli import main\n"
            "from parksim.server import create_app\n"
            f"create_app({str(bundle_dir)!r})\n"
            f"assert main(['serve', '--scenes', {str(bundle_dir)!r}, '--replicas', '2']) == 2\n"
            f"sys.exit(main(['serve', '--ray', '--scenes', {str(bundle_dir)!r}]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if not line.startswith("compiling render kernels")]
    assert lines == ["parksim serve: error: --replicas only applies with --ray",
                     "parksim serve: error: --ray needs Ray Serve, which is not installed: install parksim[ray] "
                     "(pip install 'parksim[ray]')"]


@pytest.mark.parametrize("argv, message", [
    (["--autoscale", "3,1"], "argument --autoscale: need 1 <= MIN <= MAX, got 3,1"),
    (["--autoscale", "2"], "argument --autoscale: expected MIN,MAX like 1,4, got '2'"),
    (["--replicas", "2", "--autoscale", "1,2"], "argument --autoscale: not allowed with argument --replicas"),
    (["--replica-cpus", "0"], "argument --replica-cpus: must be an integer >= 1, got 0"),
])
def test_bad_ray_flags_are_one_line(bundle_dir, capsys, argv, message):
    assert main(["serve", "--ray", "--scenes", str(bundle_dir.parent), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.rstrip().endswith(message), err


def test_an_unreachable_cluster_is_one_line(bundle_dir):
    port = free_port()   # nothing listens there
    done = subprocess.run([PARKSIM, "serve", "--ray", "--address", f"127.0.0.1:{port}", "--scenes",
                           str(bundle_dir.parent), "--port", str(free_port())], capture_output=True, text=True,
                          timeout=120)
    assert (done.returncode, done.stderr) == (2, f"parksim serve: error: cannot reach the Ray cluster at "
                                                 f"127.0.0.1:{port}: Connection refused\n")


def _ok(response: httpx.Response) -> httpx.Response:
    assert response.status_code == 200, response.text
    return response
