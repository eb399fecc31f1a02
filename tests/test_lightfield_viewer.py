"""The viewer page in a real headless Chromium (Debian's chromium + chromedriver).

A uvicorn server on a free loopback port holds a small bunny field; Selenium
drives the system browser: the page loads, shows a non-blank bunny, and a
drag changes the image. Skipped when the browser, its driver or selenium is
missing (``scripts/install-system-deps.sh --browser`` installs them).
"""
from __future__ import annotations

import shutil
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from flatserve.lightfield.mesh import CGAL_DATA_TARBALL

CHROMEDRIVER = Path("/usr/bin/chromedriver")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
webdriver = pytest.importorskip("selenium.webdriver")

pytestmark = [
    pytest.mark.skipif(not CHROMEDRIVER.is_file() or CHROMIUM is None,
                       reason="Debian chromium + chromium-driver not installed"),
    pytest.mark.skipif(not CGAL_DATA_TARBALL.is_file(), reason="Debian libcgal-demo not installed"),
]

DEMO_N = 60
#: A frame is "not blank" when its grey values spread at least this much.
MIN_STD = 0.05
#: A drag "changes the image" when the mean absolute difference exceeds this.
MIN_CHANGE = 0.01
WAIT_S = 120.0

CHROME_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--window-size=900,900"]

# the displayed frame's pixels (grey), read through a canvas in the page
READ_FRAME_JS = """
const img = document.getElementById('frame');
if (!img.complete || !img.naturalWidth) return null;
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const g = c.getContext('2d'); g.drawImage(img, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data;
const out = [];
for (let i = 0; i < d.length; i += 4) out.push(d[i]);
return [c.width, c.height, out];
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    import uvicorn

    from flatserve.service.demo import ensure_demo_field
    from flatserve.service import Settings, create_app

    port = free_port()
    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("viewer") / "data", snapshot_every=0, port=port))
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=srv.run, daemon=True)
    th.start()
    t0 = time.monotonic()
    while not srv.started:
        if time.monotonic() - t0 > WAIT_S or not th.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.05)
    ensure_demo_field(app.state.registry, n=DEMO_N, batch=1200, progress=False)
    yield f"http://127.0.0.1:{port}"
    srv.should_exit = True
    th.join(timeout=30)


@pytest.fixture
def browser(tmp_path):
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    opts = Options()
    opts.binary_location = CHROMIUM
    for flag in CHROME_FLAGS + [f"--user-data-dir={tmp_path / 'chromium-profile'}"]:
        opts.add_argument(flag)
    drv = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)
    drv.set_page_load_timeout(WAIT_S)
    yield drv
    drv.quit()


def wait_for(fn, timeout=WAIT_S, what="condition"):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = fn()
        if v:
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def frame_pixels(drv) -> np.ndarray:
    w, h, px = wait_for(lambda: drv.execute_script(READ_FRAME_JS), what="a decoded frame")
    return np.asarray(px, dtype=np.float64).reshape(h, w) / 255.0


def renders(drv) -> int:
    return int(drv.find_element("id", "frame").get_attribute("data-renders") or 0)


def test_viewer_shows_the_bunny_and_a_drag_changes_it(server, browser, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains

    browser.get(f"{server}/viewer/bunny")
    assert "bunny" in browser.title
    wait_for(lambda: renders(browser) >= 1, what="the first frame")
    first = frame_pixels(browser)
    assert first.shape == (250, 250)
    assert first.std() > MIN_STD, "the first frame is blank"
    assert browser.find_element("id", "status").text == ""
    assert "ms" in browser.find_element("id", "render-time").text
    browser.save_screenshot(str(tmp_path / "viewer-before.png"))

    n0 = renders(browser)
    stage = browser.find_element("id", "stage")
    ActionChains(browser).move_to_element(stage).click_and_hold().move_by_offset(60, 0) \
        .move_by_offset(60, 30).release().perform()
    # the last frame after release is rendered at 4 rays per pixel
    wait_for(lambda: renders(browser) > n0 and
             browser.find_element("id", "frame").get_attribute("data-supersample") == "4" and
             browser.find_element("id", "busy").get_attribute("hidden") is not None,
             what="frames after the drag")
    time.sleep(0.5)
    wait_for(lambda: browser.find_element("id", "busy").get_attribute("hidden") is not None,
             what="rendering to finish")
    after = frame_pixels(browser)
    browser.save_screenshot(str(tmp_path / "viewer-after.png"))
    assert after.std() > MIN_STD
    assert np.abs(after - first).mean() > MIN_CHANGE, "the drag did not change the image"
    assert "yaw" in browser.find_element("id", "camera").text
