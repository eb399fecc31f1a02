"""The viewer page in a real headless Chromium (Debian's chromium + chromedriver).

A uvicorn server on a free loopback port holds a small 360 degree bunny field
(the demo's oriented covering atlas, fewer samples); Selenium drives the system
browser: the page loads, shows a non-blank bunny, a drag changes the image,
and dragging all the way round (24 steps of 15 degrees of azimuth, then
elevations up to +-75 degrees) shows the bunny in every frame: the pixels where
the mesh's ground truth (the same camera's rays cast against the mesh) sees the
bunny are not background. Skipped when the browser, its driver or selenium is
missing (``scripts/install-system-deps.sh --browser`` installs them).
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from flatserve.lightfield.mesh import CGAL_DATA_TARBALL
from tests.harness.browser import CHROMEDRIVER, CHROMIUM, chromium, serving
from tests.harness.browser import wait_for as _wait_for
from tests.harness.process import free_port

webdriver = pytest.importorskip("selenium.webdriver")

pytestmark = [
    pytest.mark.skipif(not CHROMEDRIVER.is_file() or CHROMIUM is None,
                       reason="Debian chromium + chromium-driver not installed"),
    pytest.mark.skipif(not CGAL_DATA_TARBALL.is_file(), reason="Debian libcgal-demo not installed"),
]

#: Rays of the test's demo field (the demo's sampling and atlas, fewer samples).
DEMO_SAMPLES = 20_000
#: A frame is "not blank" when its grey values spread at least this much.
MIN_STD = 0.05
#: A pixel shows the object when its grey value exceeds this (background 0; the
#: darkest lit surface, ambient only, is 0.135).
OBJECT_GREY = 0.05
#: In every frame of the orbit at least this share of the pixels whose rays all
#: hit the mesh (ground truth) must show the object (measured: >= 0.80 at 20,000
#: samples; a view outside every chart shows none)...
MIN_FILLED = 0.6
#: ... and at most this share of the pixels whose rays all miss it (measured <= 0.39).
MAX_SPILL = 0.6
#: Orbit steps: degrees per drag, and the drag length in CSS pixels (viewer.js
#: turns 0.15 degrees per pixel).
STEP_DEG = 15
STEP_PX = 100
DEG_PER_PX = 0.15
#: The viewer's camera: eye distance and focal length (viewer.js DEFAULT), frame side.
VIEW_DISTANCE, VIEW_FOCAL, VIEW_SIZE = 3.0, 4.0, 250
#: A drag "changes the image" when the mean absolute difference exceeds this.
MIN_CHANGE = 0.01
WAIT_S = 120.0

CHROME_FLAGS = ["--disable-quic", "--window-size=900,900"]

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


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from flatserve.service.demo import ensure_demo_field
    from flatserve.service import Settings, create_app

    port = free_port()
    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("viewer") / "data", snapshot_every=0, port=port))
    with serving(app, port, WAIT_S) as url:
        ensure_demo_field(app.state.rooms, samples=DEMO_SAMPLES, batch=5000, progress=False)
        yield url


@pytest.fixture
def browser(tmp_path):
    with chromium(tmp_path / "chromium-profile", CHROME_FLAGS, WAIT_S) as drv:
        yield drv


def wait_for(fn, timeout=WAIT_S, what="condition"):
    return _wait_for(fn, what, timeout)


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


def object_mask(scene, yaw: float, pitch: float) -> np.ndarray:
    """(H, W) bool: pixels whose 4 rays all hit the mesh (the viewer's camera at yaw, pitch)."""
    from flatserve.lightfield import Camera

    cam = Camera.orbit(yaw, pitch, VIEW_DISTANCE, focal=VIEW_FOCAL, width=VIEW_SIZE,
                       height=VIEW_SIZE, supersample=4)
    o, d = cam.rays()
    s = cam.side
    return scene.cast(o, d).hit.reshape(cam.height, s, cam.width, s).all(axis=(1, 3))


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def drag_and_settle(drv, dx: int, dy: int, yaw: float, pitch: float) -> np.ndarray:
    """Drag the stage by (dx, dy) CSS pixels; wait for the frame of the camera at
    (yaw, pitch) rendered at 4 rays per pixel; return its pixels."""
    from selenium.webdriver.common.action_chains import ActionChains

    stage = drv.find_element("id", "stage")
    ActionChains(drv).move_to_element(stage).click_and_hold().move_by_offset(dx, dy) \
        .release().perform()
    img = drv.find_element("id", "frame")

    def settled():
        if img.get_attribute("data-supersample") != "4" or \
                drv.find_element("id", "busy").get_attribute("hidden") is None:
            return False
        y, p = img.get_attribute("data-yaw"), img.get_attribute("data-pitch")
        return y is not None and angle_diff(float(y), yaw) < 0.5 and abs(float(p) - pitch) < 0.5

    wait_for(settled, what=f"the frame at yaw {yaw}, pitch {pitch}")
    return frame_pixels(drv)


def test_viewer_orbits_all_the_way_round_without_holes(server, browser, tmp_path):
    from flatserve.lightfield.sampling import bunny_scene

    scene = bunny_scene(1)
    browser.get(f"{server}/viewer/bunny")
    wait_for(lambda: renders(browser) >= 1, what="the first frame")
    # azimuth: 24 drags of 15 degrees (the viewer turns yaw = -dx * 0.15), back to the start;
    # then elevation up to 75 degrees and down to -75 (pitch = +dy * 0.15)
    steps = [(STEP_PX, 0)] * (360 // STEP_DEG) + [(0, STEP_PX)] * 5 + [(0, -STEP_PX)] * 10
    yaw = pitch = 0.0
    seen, failures = [], []
    for i, (dx, dy) in enumerate(steps):
        yaw = (yaw - dx * DEG_PER_PX + 180.0) % 360.0 - 180.0
        pitch += dy * DEG_PER_PX
        px = drag_and_settle(browser, dx, dy, yaw, pitch)
        assert px.shape == (VIEW_SIZE, VIEW_SIZE)
        mask = object_mask(scene, yaw, pitch)
        assert 0.05 < mask.mean() < 0.95  # the bunny is in view, not filling it
        obj = px > OBJECT_GREY
        filled, spill = obj[mask].mean(), obj[~mask].mean()
        seen.append((round(yaw), round(pitch)))
        if not (filled >= MIN_FILLED and spill <= MAX_SPILL):
            browser.save_screenshot(str(tmp_path / f"orbit-{i:02d}.png"))
            failures.append(f"yaw {yaw:.0f}, pitch {pitch:.0f}: {filled:.0%} of the bunny's "
                            f"pixels shown, {spill:.0%} of the background not background")
    assert not failures, "frames with holes:\n" + "\n".join(failures)
    # the orbit went all the way round in azimuth and well past 45 degrees of elevation
    assert len({y for y, p in seen if p == 0}) == 360 // STEP_DEG
    assert max(p for _, p in seen) == 75 and min(p for _, p in seen) == -75
    assert browser.find_element("id", "status").text == ""
