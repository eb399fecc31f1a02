"""The viewer on a server with API keys, in a real headless Chromium (Debian's chromium +
chromedriver): the read-only key given as ``#key=`` renders and leaves the address bar;
without a key the page asks for one and renders once it is typed; the start-up line
says how, without a key in it."""
from __future__ import annotations


import numpy as np
import pytest

from flatserve.client import Client
from flatserve.service import Settings, create_app
from flatserve.service.demo import viewer_key_hint, viewer_url
from tests.harness.browser import chromium, serving, wait_for
from tests.harness.process import free_port

WRITE_KEY, READ_KEY = "write-key-0123456789", "read-key-0123456789"
WAIT_S = 60.0


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    port = free_port()
    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("keys") / "data", port=port,
                              snapshot_every=0, api_key=WRITE_KEY, read_only_key=READ_KEY,
                              host="127.0.0.1"))
    with serving(app, port, WAIT_S) as url:
        rng = np.random.default_rng(7)
        n = 3000
        eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
        screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
        with Client(url, api_key=WRITE_KEY) as c:
            c.create_field("lf", channels=1)
            c.upload_rays("lf", eyes, screen - eyes, 0.5 + 0.5 * np.sin(3 * screen[:, :1]))
        yield url


@pytest.fixture
def browser(tmp_path):
    with chromium(tmp_path / "profile", ["--window-size=900,900"], WAIT_S) as drv:
        yield drv


def _wait(fn, what: str):
    return wait_for(fn, what, WAIT_S)


def _renders(drv) -> int:
    return int(drv.find_element("id", "frame").get_attribute("data-renders") or 0)


def test_the_read_only_key_in_the_fragment_renders_and_leaves_the_address_bar(server, browser):
    browser.get(f"{server}/viewer/lf#key={READ_KEY}")
    _wait(lambda: _renders(browser) >= 1, "a frame rendered with the key")
    assert browser.find_element("id", "status").text == ""
    assert "key" not in browser.current_url and READ_KEY not in browser.current_url


def test_without_a_key_the_page_asks_for_it(server, browser):
    browser.get(f"{server}/viewer/lf")
    form = browser.find_element("id", "key-form")
    _wait(lambda: form.is_displayed(), "the key form")
    assert "needs an API key" in browser.find_element("id", "status").text
    assert _renders(browser) == 0
    browser.find_element("id", "key").send_keys("wrong")
    browser.find_element("css selector", "#key-form button").click()
    _wait(lambda: "refused" in browser.find_element("id", "status").text, "the refusal")
    browser.find_element("id", "key").send_keys(READ_KEY)
    browser.find_element("css selector", "#key-form button").click()
    _wait(lambda: _renders(browser) >= 1, "a frame rendered with the typed key")
    assert not form.is_displayed() and browser.find_element("id", "status").text == ""


def test_a_pose_in_the_url_renders_that_camera_and_stays(server, browser):
    """``?camera=`` (a NeRF pose, with the key in the fragment): the first frame is the
    pose's, scaled to 250 pixels on its longer side, pixel for pixel the service's PNG of
    that body; the page says the camera is fixed, and a drag renders nothing new."""
    import io
    import json
    import time
    from urllib.parse import quote

    from PIL import Image
    from selenium.webdriver.common.action_chains import ActionChains

    from flatserve.lightfield.camera import PinholeCamera

    cam = PinholeCamera(eye=(0.2, 0.1, -3.0), rotation=np.eye(3), fx=40.0, fy=40.0, cx=16.0,
                        cy=12.0, width=32, height=24)
    pose = {"nerf": cam.to_nerf()}
    browser.get(f"{server}/viewer/lf?camera={quote(json.dumps(pose))}#key={READ_KEY}")
    _wait(lambda: _renders(browser) >= 1, "the pose's frame")
    img = browser.find_element("id", "frame")
    assert img.get_attribute("data-camera") == "nerf"
    assert browser.find_element("id", "status").text == ""
    assert "camera=" in browser.current_url and READ_KEY not in browser.current_url
    note = browser.find_element("id", "pose-note")
    assert note.is_displayed() and "fixed" in note.text and "nerf" in note.text
    assert not browser.find_element("id", "hint").is_displayed()
    w, h, px = browser.execute_script(_READ_FRAME_JS)
    assert (w, h) == (250, 188)  # 32 x 24 at 250 on the longer side
    with Client(server, api_key=READ_KEY) as c:
        png = c.render("lf", {**pose, "width": 250, "height": 188, "supersample": 4},
                       format="png")
    want = np.asarray(Image.open(io.BytesIO(png)).convert("L"))
    np.testing.assert_array_equal(np.asarray(px, np.uint8).reshape(h, w), want)
    # the camera stays: a drag, the wheel and a double click render nothing
    n = _renders(browser)
    stage = browser.find_element("id", "stage")
    ActionChains(browser).move_to_element(stage).click_and_hold().move_by_offset(80, 20) \
        .release().double_click(stage).perform()
    time.sleep(1.0)
    assert _renders(browser) == n and img.get_attribute("data-camera") == "nerf"
    assert "pose" in browser.find_element("id", "camera").text


def test_a_camera_the_page_cannot_read_is_said_and_not_rendered(server, browser):
    browser.get(f"{server}/viewer/lf?camera=%7Bnot-json#key={READ_KEY}")
    _wait(lambda: "camera in the URL" in browser.find_element("id", "status").text,
          "the page's complaint")
    assert _renders(browser) == 0
    # a pose the service refuses: its 422, naming the member
    bad = '{"colmap": {"qvec": [2, 0, 0, 0], "tvec": [0, 0, 3], "params": [40, 40, 16, 12], ' \
          '"width": 32, "height": 24}}'
    from urllib.parse import quote

    browser.get(f"{server}/viewer/lf?camera={quote(bad)}#key={READ_KEY}")
    _wait(lambda: "422" in browser.find_element("id", "status").text, "the refusal")
    assert "qvec" in browser.find_element("id", "status").text and _renders(browser) == 0


# the displayed frame's size and red channel, read through a canvas in the page
_READ_FRAME_JS = """
const img = document.getElementById('frame');
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const g = c.getContext('2d'); g.drawImage(img, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data;
const out = [];
for (let i = 0; i < d.length; i += 4) out.push(d[i]);
return [c.width, c.height, out];
"""


def test_the_start_up_line_says_how_without_a_key():
    url = viewer_url("127.0.0.1", 8000, "bunny")
    assert viewer_key_hint(Settings(), url) == ""
    keyed = Settings(api_key=WRITE_KEY, read_only_key=READ_KEY)
    hint = viewer_key_hint(keyed, url)
    assert f"{url}#key=READ_ONLY_KEY" in hint and "FLATSERVE_READ_ONLY_KEY" in hint
    assert WRITE_KEY not in hint and READ_KEY not in hint
    assert "FLATSERVE_READ_ONLY_KEY" in viewer_key_hint(Settings(api_key=WRITE_KEY), url)
