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


def test_the_start_up_line_says_how_without_a_key():
    url = viewer_url("127.0.0.1", 8000, "bunny")
    assert viewer_key_hint(Settings(), url) == ""
    keyed = Settings(api_key=WRITE_KEY, read_only_key=READ_KEY)
    hint = viewer_key_hint(keyed, url)
    assert f"{url}#key=READ_ONLY_KEY" in hint and "FLATSERVE_READ_ONLY_KEY" in hint
    assert WRITE_KEY not in hint and READ_KEY not in hint
    assert "FLATSERVE_READ_ONLY_KEY" in viewer_key_hint(Settings(api_key=WRITE_KEY), url)
