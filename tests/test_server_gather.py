"""Concurrent single-pose GET /render requests rendered together (parksim.server.gather), on a real uvicorn server:
each client gets its own reply, equal to the render of its pose alone, and the group shared one render."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest

from parksim.frames import decode_npz
from parksim.server import create_app
from parksim.server.settings import Settings
from parksim.sim import LocalSim
from sim_fixtures import make_bundle, running_server

POSES = [(0.5 * k, 0.2 * (k % 3) - 0.2, 0.3 * k) for k in range(6)]


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("gather") / "tiny", n=1500, bev_px=64)


def _get_all(url: str, fmt: str = "npz") -> list[httpx.Response]:
    """Every pose at once, from one thread each (a barrier-free burst; the window holds the first ones)."""
    def one(pose: tuple[float, float, float]) -> httpx.Response:
        params = {"pose": ",".join(map(str, pose)), "scale": "0.25", "bev": "on", "format": fmt}
        if fmt != "npz":
            params.update(cameras="", bev="on")
        return httpx.get(f"{url}/render", params=params, timeout=60)

    with ThreadPoolExecutor(len(POSES)) as pool:
        return list(pool.map(one, POSES))


def test_gathered_requests_get_their_own_renders(bundle_dir):
    sim = LocalSim(bundle_dir)
    settings = Settings(gather="on", gather_window_ms=300)
    with running_server(create_app(bundle_dir.parent, settings)) as url:
        replies = _get_all(url)
    gathered = []
    for pose, r in zip(POSES, replies):
        assert r.status_code == 200, r.text
        (frame,), meta = decode_npz(r.content)
        assert meta["poses"][0]["x"] == pose[0]
        want = sim.render(pose, None, True, 0.25)
        for name in sim.cameras:
            np.testing.assert_array_equal(frame.images[name], want.images[name])
        np.testing.assert_array_equal(frame.bev, want.bev)
        gathered.append(meta["gathered"])
    assert max(gathered) > 1 and all(g >= 1 for g in gathered)


def test_auto_does_not_gather_on_a_cpu_and_off_never_does(bundle_dir):
    for mode in ("auto", "off"):
        with running_server(create_app(bundle_dir.parent, Settings(gather=mode, gather_window_ms=300))) as url:
            replies = _get_all(url)
        assert all(r.status_code == 200 and decode_npz(r.content)[1]["gathered"] == 1 for r in replies), mode


def test_gathered_single_view_images_and_bad_flags(bundle_dir):
    with running_server(create_app(bundle_dir.parent, Settings(gather="on", gather_window_ms=300))) as url:
        replies = _get_all(url, fmt="png")
    assert all(r.status_code == 200 and r.headers["content-type"] == "image/png" for r in replies)
    assert len({r.content for r in replies}) == len(POSES)
    with pytest.raises(ValueError, match="gather"):
        Settings.from_env(gather="sometimes")
