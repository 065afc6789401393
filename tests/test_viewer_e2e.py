"""Web viewer end to end: headless Chromium loads /, shows the five views, and keyboard driving updates them.

Needs Debian's ``chromium`` and ``chromium-driver`` (apt) and the ``selenium`` package; skips otherwise.
"""

from __future__ import annotations

import shutil

import pytest

from server import create_app
from sim_fixtures import make_bundle, running_server

webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
if not (shutil.which("chromium") and shutil.which("chromedriver")):
    pytest.skip("chromium and chromedriver are not installed (apt-get install chromium chromium-driver)",
                allow_module_level=True)

from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

_PIXELS = """
const img = document.getElementById(arguments[0]);
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const ctx = c.getContext('2d'); ctx.drawImage(img, 0, 0);
return Array.from(ctx.getImageData(0, 0, c.width, c.height).data.filter((_, i) => i % 97 == 0));
"""


@pytest.fixture(scope="module")
def browser():
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1200,800"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(shutil.which("chromedriver")))
    yield driver
    driver.quit()


def _frames(driver) -> int:
    return driver.execute_script("return window.viewerState ? window.viewerState.frames : 0")


def test_viewer_shows_views_and_updates_on_keys(browser, tmp_path):
    bundle = make_bundle(tmp_path / "tiny", n=2000, bev_px=100)
    with running_server(create_app(bundle.parent)) as url:
        browser.get(f"{url}/")
        wait = WebDriverWait(browser, 60, poll_frequency=0.2)
        wait.until(lambda d: _frames(d) >= 1)
        for view in ("front", "rear", "left", "right", "bev"):
            assert browser.execute_script(f"return document.getElementById('img-{view}').naturalWidth") > 0
        before_pose = browser.find_element(By.ID, "pose").text
        before = {v: browser.execute_script(_PIXELS, f"img-{v}") for v in ("front", "bev")}
        assert "latency" in browser.find_element(By.ID, "latency").text
        body = browser.find_element(By.TAG_NAME, "body")
        body.send_keys(Keys.ARROW_UP)
        body.send_keys("w")
        wait.until(lambda d: _frames(d) >= 2 and not d.execute_script("return window.viewerState.busy"))
        assert browser.find_element(By.ID, "pose").text != before_pose
        after = {v: browser.execute_script(_PIXELS, f"img-{v}") for v in ("front", "bev")}
        assert all(after[v] != before[v] for v in after), "the images changed with the pose"
        assert browser.find_element(By.ID, "error").text == ""
