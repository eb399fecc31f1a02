"""Suite-wide settings.

With ``FLATSERVE_STRICT=1`` (set by ``.ci/run`` and ``make test``) a skipped
test is reported as a failure: on a machine that ran the project's own set-up
(Debian packages, browser, test extras) nothing has a reason to be skipped, and
a skip there would hide a test that did not run.
"""
from __future__ import annotations

import os

import pytest

STRICT = os.environ.get("FLATSERVE_STRICT") == "1"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if STRICT and report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"skipped under FLATSERVE_STRICT=1 (set-up incomplete?): {reason}"
