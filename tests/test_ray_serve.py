"""``parksim serve --ray``: the Ray Serve deployment answers as the single-process app does (same images, same 4xx
status and detail), follows --replicas, answers the requests of a killed replica 503 JSON, stops on Ctrl-C; without
Ray the command says what to install."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from parksim.bench.procs import free_port
from parksim.cli import main
from parksim.frames import decode_npz
from parksim.ray_proxy import ReplicaLost
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
    """``parksim serve --ray`` joined to the module's cluster with two replicas and an API key, once it says it
    serves (both replicas loaded); (process, URL, its stderr log). Python's fault handler is on in it, so SIGABRT
    writes every thread's stack to that log."""
    port = free_port()
    log = tmp_path_factory.mktemp("log") / "serve.err"
    out = log.with_name("serve.out")
    with log.open("w") as err, out.open("w") as said:
        proc = subprocess.Popen([PARKSIM, "serve", "--ray", "--address", cluster, "--replicas", "2", "--api-key", KEY,
                                 "--scenes", str(bundle_dir.parent), "--port", str(port)],
                                stdout=said, stderr=err, env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 240
        while "serving on" not in out.read_text():
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
    assert _replica_states() == {"RUNNING": 2}


def test_a_killed_replica_answers_its_requests_503_json(served):
    """A replica killed by PID under load: the requests it held get the documented 503 JSON with Retry-After, none
    500 text/plain, none a broken connection; Serve starts a new replica, which then serves."""
    base = served[1]
    victim = _replica_pids()[0]
    replies: list[httpx.Response] = []
    failures: list[httpx.HTTPError] = []
    stop = threading.Event()

    def client() -> None:
        with httpx.Client(base_url=base, timeout=120) as c:   # a first render may compile kernels (~30 s)
            while not stop.is_set():
                try:
                    replies.append(c.get("/render", params={"pose": POSE, "scale": 0.5, "bev": "on"}, headers=AUTH))
                except httpx.HTTPError as e:
                    failures.append(e)

    threads = [threading.Thread(target=client) for _ in range(8)]   # several per replica; fewer than one's capacity (9)
    for t in threads:
        t.start()
    try:
        _until(lambda: len(replies) >= 6, 240, "the deployment answered no renders")
        killed_at = len(replies)
        os.kill(victim, signal.SIGKILL)
        _until(lambda: len(replies) >= killed_at + 12, 120, "the other replica stopped answering")
    finally:
        stop.set()
        for t in threads:
            t.join(120)
    codes = Counter(r.status_code for r in replies)
    assert not failures and set(codes) <= {200, 503} and codes[503] >= 1, (codes, failures[:3])
    for r in (r for r in replies if r.status_code == 503):
        assert (r.headers["content-type"], r.headers["retry-after"]) == ("application/json", "1")
        assert "replica serving this request stopped" in r.json()["detail"]
    _until(lambda: len(pids := _replica_pids()) == 2 and victim not in pids and _replica_states() == {"RUNNING": 2},
           240, "Serve did not restart the replica")
    for _ in range(4):   # and the deployment serves again
        _ok(httpx.get(f"{base}/render", params={"pose": POSE, "scale": 0.25}, headers=AUTH, timeout=120))


def test_replica_lost_rewrites_only_replies_that_did_not_complete():
    """The proxy middleware answers 503 JSON for a request the proxy returned from in silence or with its reply cut
    after the headers (the replica died between Serve's messages); an app's own error reply (here a 500 JSON) passes
    through as it was; a reply larger than the hold streams through as it comes."""
    start = {"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"6")]}

    async def silent(scope, receive, send):   # what Serve's proxy does after a RayActorError
        return None

    async def cut(scope, receive, send):   # the replica died after its headers
        await send(start)
        await send({"type": "http.response.body", "body": b"abc", "more_body": True})

    async def own_error(scope, receive, send):
        await send({"type": "http.response.start", "status": 500, "headers": [(b"content-type", b"application/json")]})
        await send({"type": "http.response.body", "body": b'{"detail": "x"}'})

    async def streamed(scope, receive, send):
        await send(start)
        await send({"type": "http.response.body", "body": b"abc", "more_body": True})
        await send({"type": "http.response.body", "body": b"def"})

    for app in (silent, cut):
        lost = TestClient(ReplicaLost(app, retry_after_s=3)).get("/render")
        assert (lost.status_code, lost.headers["retry-after"], lost.headers["content-type"]) == (503, "3",
                                                                                                "application/json")
        assert lost.json() == {"detail": "the Ray Serve replica serving this request stopped before it answered "
                                         "(Serve restarts it): retry after 3 s"}
    kept = TestClient(ReplicaLost(own_error)).get("/render")
    assert (kept.status_code, kept.json(), "retry-after" in kept.headers) == (500, {"detail": "x"}, False)
    for hold in (1, 2, 100):
        whole = TestClient(ReplicaLost(streamed, hold_bytes=hold)).get("/render")
        assert (whole.status_code, whole.content) == (200, b"abcdef")


def _replica_pids() -> list[int]:
    """PIDs of the live SimReplica actors (Ray's public state API needs the dashboard, which this cluster lacks)."""
    from ray._private import state
    return sorted(a["Pid"] for a in state.actors().values()
                  if a["ActorClassName"] == "ServeReplica:parksim:SimReplica" and a["State"] == "ALIVE")


def _replica_states() -> dict[str, int]:
    return serve.status().applications["parksim"].deployments["SimReplica"].replica_states


def _until(done: Callable[[], bool], timeout_s: float, failure: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            pytest.fail(f"{failure} within {timeout_s:.0f} s")
        time.sleep(0.2)


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
