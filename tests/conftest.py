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


# -- PostgreSQL: throwaway clusters (Debian's postgresql binaries, never the system's cluster)
@pytest.fixture(scope="session")
def pg_cluster():
    """One throwaway cluster for the session (``fsync=off``: only processes die in
    these tests, never the machine). Tests that stop or restart PostgreSQL use
    :func:`own_pg_cluster` instead."""
    from tests.harness.pgcluster import PgCluster

    with PgCluster(fsync=False) as pg:
        yield pg


@pytest.fixture
def pg_url(pg_cluster, request):
    """The URL of a fresh database on the session's cluster, for one test."""
    import re
    import uuid

    stem = re.sub(r"[^a-z0-9_]", "_", request.node.name.lower())[:40]
    return pg_cluster.create_database(f"t_{stem}_{uuid.uuid4().hex[:8]}")


@pytest.fixture
def own_pg_cluster():
    """A cluster of this test's own (it may stop, crash and restart it)."""
    from tests.harness.pgcluster import PgCluster

    with PgCluster(fsync=False) as pg:
        yield pg
