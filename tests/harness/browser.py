"""A real server in a thread and Debian's headless Chromium, for the tests that
drive a page (the viewer, the docs): one place for how both are started."""
from __future__ import annotations

import shutil
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

CHROMEDRIVER = Path("/usr/bin/chromedriver")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: Headless, and nothing of the browser's own talks to the network.
HEADLESS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@contextmanager
def serving(app, port: int, timeout: float = 60.0) -> Iterator[str]:
    """``app`` served by uvicorn on ``127.0.0.1:port`` in a thread; its URL."""
    import uvicorn

    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=srv.run, daemon=True)
    th.start()
    t0 = time.monotonic()
    while not srv.started:
        if time.monotonic() - t0 > timeout or not th.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        th.join(timeout=30)


@contextmanager
def chromium(profile: Path, flags=(), page_load_timeout: float = 60.0):
    """A Selenium driver of Debian's Chromium (:data:`HEADLESS` plus ``flags``),
    its profile in ``profile``."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    assert CHROMEDRIVER.is_file() and CHROMIUM is not None, \
        "Debian chromium + chromium-driver: bash scripts/install-system-deps.sh --browser"
    opts = Options()
    opts.binary_location = CHROMIUM
    for flag in [*HEADLESS, *flags, f"--user-data-dir={profile}"]:
        opts.add_argument(flag)
    drv = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)
    drv.set_page_load_timeout(page_load_timeout)
    try:
        yield drv
    finally:
        drv.quit()


def wait_for(fn, what: str = "condition", timeout: float = 60.0, step: float = 0.1):
    """``fn()``'s first true value, asked every ``step`` seconds for ``timeout``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = fn()
        if v:
            return v
        time.sleep(step)
    raise AssertionError(f"timed out waiting for {what}")
