"""Web viewer end to end: headless Chromium loads / from a real server and is driven with keys and mouse drags.

Needs Debian's ``chromium`` and ``chromium-driver`` (apt) and the ``selenium`` package; skips otherwise.
The scene is a small synthetic garage whose bundle carries the recorded path of the preset's drive.
"""

from __future__ import annotations

import math
import re
import shutil
import threading
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest

from parksim import bundle as bundle_io
from parksim.frames import decode_npz
from parksim.server import Settings, create_app
from parksim.sim import LocalSim
from parksim.synth.layout import build_garage
from parksim.synth.presets import get_preset
from parksim.synth.trajectory import drive
from parksim.vehicle import VehicleParams
from sim_fixtures import make_bundle, running_server

webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
if not (shutil.which("chromium") and shutil.which("chromedriver")):
    pytest.skip("chromium and chromedriver are not installed (apt-get install chromium chromium-driver)",
                allow_module_level=True)

from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

PRESET = "tiny"
RECORDED_FRAMES = 60  # the drive recorded: 12 m along the aisle (the preset's own 12 frames would hide under the ego)
COVERAGE_M = 3.0  # the viewer's stated sharp-view distance from the recorded path (scene.js)
MINIMAP_PX = 480  # the minimap canvas width (minimap.js)
EGO_RGB, PATH_RGB = (255, 210, 63), (77, 163, 255)  # minimap colours of the ego and the recorded path

_PIXELS = """
const c = document.getElementById(arguments[0]);
return [c.width, c.height, Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data)];
"""
_RENDER_URLS = "return performance.getEntriesByType('resource').map(e => e.name).filter(n => n.includes('/render'))"


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """A served bundle whose meta holds the recorded path of a drive (as ``parksim reconstruct`` stores it)."""
    folder = make_bundle(tmp_path_factory.mktemp("scenes") / PRESET, PRESET, n=2000, bev_px=100)
    preset = get_preset(PRESET)
    poses, _ = drive(build_garage(preset.layout), preset.trajectory, RECORDED_FRAMES)
    bundle = bundle_io.load(folder)
    bundle.meta["recorded_path"] = bundle_io.recorded_path(poses)
    bundle_io.save(folder, bundle)
    # one render first: a cold numba cache compiles the kernels (minutes on a busy machine), not the viewer's wait
    LocalSim.from_dir(folder).render([6.0, 0.0, 0.0], bev=True, scale=0.5)
    with running_server(create_app(folder.parent)) as url:
        info = httpx.get(f"{url}/scenes/{PRESET}").json()
        yield {"url": url, "poses": poses, "info": info, "folder": folder}


@pytest.fixture(scope="module")
def browser():
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--window-size=1200,800"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(shutil.which("chromedriver")))
    yield driver
    driver.quit()


def _state(driver, key: str) -> Any:
    return driver.execute_script(f"return window.viewerState ? window.viewerState.{key} : null")


def _idle(driver, frames: int) -> None:
    """Wait until at least ``frames`` frames were shown and no render is in flight or pending."""
    WebDriverWait(driver, 120, poll_frequency=0.1).until(
        lambda d: d.execute_script("const s = window.viewerState; return s && s.frames >= arguments[0] && "
                                   "!s.busy && !s.dirty", frames))


def _open(driver, url: str) -> None:
    driver.get(f"{url}/")
    _idle(driver, 1)


def _pixels(driver, canvas_id: str) -> np.ndarray:
    w, h, data = driver.execute_script(_PIXELS, canvas_id)
    return np.array(data, dtype=np.uint8).reshape(h, w, 4)


def _render_counts(url: str) -> dict[str, int]:
    """Answered GET requests per render route, from the server's /metrics."""
    counts = {"/render": 0, "/render/{view}.{ext}": 0}
    for labels, n in re.findall(r"^parksim_requests_total\{(.*)\} (\S+)$", httpx.get(f"{url}/metrics").text, re.M):
        label = dict(re.findall(r'(\w+)="([^"]*)"', labels))
        if label["method"] == "GET" and label["route"] in counts:
            counts[label["route"]] += int(float(n))
    return counts


def _pose(driver) -> tuple[float, float, float]:
    p = _state(driver, "pose")
    return p["x"], p["y"], p["yaw"]


def _path_distance(path: np.ndarray, x: float, y: float) -> float:
    """Distance from (x, y) to the polyline ``path`` [N, >=2], float64."""
    a, b = path[:-1, :2], path[1:, :2]
    d = b - a
    t = np.clip(((np.array([x, y]) - a) * d).sum(1) / (d * d).sum(1), 0, 1)
    return float(np.hypot(*(np.array([x, y]) - a - t[:, None] * d).T).min())


def _px_per_m(info: dict[str, Any]) -> float:
    """Minimap pixels per metre: the canvas spans the scene bounds grown by the server's pose margin."""
    return MINIMAP_PX / (info["bounds"]["x"][1] - info["bounds"]["x"][0] + 2 * info["pose_margin_m"])


def _minimap_px(info: dict[str, Any], x: float, y: float) -> tuple[float, float]:
    """World (m) -> minimap canvas pixel (u right, v down)."""
    m, s = info["pose_margin_m"], _px_per_m(info)
    return (x - info["bounds"]["x"][0] + m) * s, (info["bounds"]["y"][1] + m - y) * s


def test_opens_on_the_recorded_path_and_draws_it(browser, scene) -> None:
    _open(browser, scene["url"])
    x, y, yaw = _pose(browser)
    recorded = [(p[0, 3], p[1, 3], math.atan2(p[1, 0], p[0, 0])) for p in scene["poses"]]
    yaw_tol = 2 * np.spacing(math.pi)  # the path's yaw went through numpy's arctan2, the reference through math's
    assert any((x, y) == r[:2] and abs(yaw - r[2]) <= yaw_tol for r in recorded), "starts at a recorded pose"
    assert not browser.find_element(By.ID, "coverage").is_displayed()

    mini = _pixels(browser, "minimap")
    assert mini.shape[1] == MINIMAP_PX
    assert (mini[..., :3] == PATH_RGB).all(-1).sum() > 50, "the recorded path is drawn"
    ego = np.argwhere((mini[..., :3] == EGO_RGB).all(-1))
    length, width = VehicleParams().length, VehicleParams().width
    s = _px_per_m(scene["info"])
    assert 0.5 * length * width * s * s < len(ego) < length * width * s * s, "the ego footprint is drawn at its size"
    centre = VehicleParams().extent[0] + length / 2
    u, v = _minimap_px(scene["info"], x + centre * math.cos(yaw), y + centre * math.sin(yaw))
    assert np.hypot(*(ego.mean(0) - (v, u))) < width / 2 * s, "the ego is drawn where the pose is"
    slots = scene["info"]["map"]["slots"]
    u, v = map(round, _minimap_px(scene["info"], *slots[0]["corners"][0]))
    assert (np.abs(mini[v - 1:v + 2, u - 1:u + 2, :3].astype(int) - (155, 227, 155)).sum(-1) < 60).any(), \
        "slot outlines are drawn at their corners"


def test_one_render_request_per_step_with_every_view(browser, scene) -> None:
    url = scene["url"]
    _open(browser, url)
    before, frames, pose = _render_counts(url), _state(browser, "frames"), _pose(browser)
    shown = {c: _pixels(browser, c) for c in ("cam-front", "bev")}
    body = browser.find_element(By.TAG_NAME, "body")
    for step in range(1, 4):
        body.send_keys("w")
        _idle(browser, frames + step)
        expected = {"/render": before["/render"] + step, "/render/{view}.{ext}": before["/render/{view}.{ext}"]}
        WebDriverWait(browser, 10).until(lambda _, n=expected["/render"]: _render_counts(url)["/render"] >= n)
        assert _render_counts(url) == expected, "exactly one GET /render per step, no per-view image requests"
    x, y, yaw = _pose(browser)
    assert math.hypot(x - pose[0], y - pose[1]) == pytest.approx(1.5) and yaw == pose[2]

    render_url = browser.execute_script(_RENDER_URLS)[-1]
    assert "bev=true" in render_url and "format=npz" in render_url
    frame = decode_npz(httpx.get(render_url).content)[0][0]
    for camera, image in frame.images.items():
        np.testing.assert_array_equal(_pixels(browser, f"cam-{camera}")[..., :3], image, err_msg=camera)
    np.testing.assert_array_equal(_pixels(browser, "bev")[..., :3], frame.bev)
    assert all(not np.array_equal(_pixels(browser, c), shown[c]) for c in shown), "the views changed"
    assert browser.find_element(By.ID, "error").text == ""


def test_warns_when_far_from_the_recorded_path(browser, scene) -> None:
    _open(browser, scene["url"])
    warning = browser.find_element(By.ID, "coverage")
    body = browser.find_element(By.TAG_NAME, "body")
    path = np.array(scene["info"]["recorded_path"])
    for _ in range(8):
        body.send_keys("q")
        x, y, _ = _pose(browser)
        assert warning.is_displayed() == (_path_distance(path, x, y) > COVERAGE_M)
    assert warning.is_displayed() and "Off the recorded path" in warning.text
    assert _state(browser, "coverage")["distance"] == pytest.approx(_path_distance(path, x, y), abs=1e-9)
    for _ in range(8):
        body.send_keys("e")
    assert not warning.is_displayed()


def test_mouse_drags_move_turn_and_place(browser, scene) -> None:
    _open(browser, scene["url"])
    info = scene["info"]
    bev = browser.find_element(By.ID, "bev")
    browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", bev)  # drags start at its true centre
    x0, y0, yaw0 = _pose(browser)
    ActionChains(browser).move_to_element(bev).click_and_hold().move_by_offset(0, 40).release().perform()
    x, y, yaw = _pose(browser)
    m_per_css_px = info["bev"]["width"] * info["bev"]["m_per_px"] / bev.size["width"]
    forward = (x - x0) * math.cos(yaw0) + (y - y0) * math.sin(yaw0)
    left = -(x - x0) * math.sin(yaw0) + (y - y0) * math.cos(yaw0)
    assert forward == pytest.approx(40 * m_per_css_px, abs=m_per_css_px) and abs(left) < m_per_css_px
    assert yaw == yaw0, "a plain drag on the BEV moves without turning"

    half = bev.size["width"] // 4
    (ActionChains(browser).key_down(Keys.SHIFT).move_to_element_with_offset(bev, half, 0).click_and_hold()
     .move_by_offset(-half, -half).release().key_up(Keys.SHIFT).perform())
    assert _pose(browser)[:2] == (x, y)
    assert _pose(browser)[2] == pytest.approx(math.atan2(math.sin(yaw - math.pi / 2), math.cos(yaw - math.pi / 2)),
                                              abs=0.05), "a shift-drag a quarter turn anticlockwise turns right"

    minimap = browser.find_element(By.ID, "minimap")
    browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", minimap)
    target = (info["bounds"]["x"][0] + 2.0, info["bounds"]["y"][1] - 2.0)
    u, v = _minimap_px(info, *target)
    css = minimap.size["width"] / MINIMAP_PX
    ActionChains(browser).move_to_element_with_offset(minimap, round(u * css - minimap.size["width"] / 2),
                                                      round(v * css - minimap.size["height"] / 2)).click().perform()
    assert math.dist(_pose(browser)[:2], target) < 1.5 / css / _px_per_m(info), "the click placed the ego"
    _idle(browser, 2)
    assert browser.find_element(By.ID, "coverage").is_displayed(), "a far corner of the garage is off the path"
    assert browser.find_element(By.ID, "error").text == ""


def test_depth_toggle_shows_colour_mapped_depth(browser, scene) -> None:
    _open(browser, scene["url"])
    frames = _state(browser, "frames")
    browser.find_element(By.ID, "depth").click()
    _idle(browser, frames + 1)
    assert _state(browser, "depthShown")
    render_url = browser.execute_script(_RENDER_URLS)[-1]
    assert "depth=true" in render_url
    depth = decode_npz(httpx.get(render_url).content)[0][0].depth
    for camera, d in depth.items():
        assert browser.find_element(By.ID, f"depth-{camera}").is_displayed()
        assert not browser.find_element(By.ID, f"cam-{camera}").is_displayed()
        rgb = _pixels(browser, f"depth-{camera}")[..., :3].astype(int)
        hit = d > 0
        assert hit.any() and (rgb[~hit] == 0).all() and (rgb[hit].sum(-1) > 0).all(), "black exactly where no surface"
        near, far = hit & (d < np.median(d[hit])), hit & (d > np.median(d[hit]))
        assert rgb[near, 0].mean() > rgb[far, 0].mean() and rgb[near, 2].mean() < rgb[far, 2].mean(), \
            "near is red, far is blue"
    browser.find_element(By.ID, "depth").click()
    _idle(browser, frames + 2)
    assert not _state(browser, "depthShown") and browser.find_element(By.ID, "cam-front").is_displayed()



def test_busy_server_is_retried_after_its_retry_after(browser, scene) -> None:
    """With no render queue, the page's render while a batch renders is refused (503, Retry-After); it is retried."""
    with running_server(create_app(scene["folder"].parent, Settings(queue_size=0))) as url:
        poses = [[6.0 + 0.1 * i, 0.0, 0.0] for i in range(16)]
        batch = threading.Thread(target=httpx.post, args=(f"{url}/render",),
                                 kwargs={"json": {"poses": poses, "bev": True, "scale": 2.0}, "timeout": 600})
        batch.start()
        WebDriverWait(browser, 30, poll_frequency=0.02).until(
            lambda _: httpx.get(f"{url}/healthz").json()["pool"]["in_flight"] == 1)
        browser.get(f"{url}/")
        WebDriverWait(browser, 60, poll_frequency=0.05).until(
            lambda d: "retrying" in d.find_element(By.ID, "error").text)
        busy = batch.is_alive()
        batch.join()
        _idle(browser, 1)
        assert busy, "the page was refused while the batch rendered"
        assert browser.find_element(By.ID, "error").text == ""
        refused = re.findall(r'^parksim_requests_total\{.*route="/render".*status="503".*\} (\S+)$',
                             httpx.get(f"{url}/metrics").text, re.M)
        assert refused and float(refused[0]) >= 1
