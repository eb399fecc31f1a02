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


# -- Lanes: what a test needs beyond this interpreter, as pytest markers ---------------------
# The markers are registered (and described) in pyproject.toml; `make test-fast` runs the
# tests that carry none of them, `make test` runs all. They are given here, in one place:
# by the fixtures a test uses, by a ``backend`` parameter naming PostgreSQL, and for the
# tests whose harness is not a fixture, by the table LANES below.

#: fixture -> lane: a test that uses the fixture is in the lane.
FIXTURE_LANES = {
    "pg_cluster": "postgres", "pg_url": "postgres", "own_pg_cluster": "postgres",
}

#: Whole modules (``path``) or single tests (``path::function``), paths under tests/, and
#: their lanes. A path here that does not exist is a collection error (a renamed module
#: would otherwise slip into the fast lane unseen).
LANES = {
    # browser: Debian's headless Chromium (tests/harness/browser.py)
    "test_lightfield_viewer.py": ("browser", "slow"),
    "test_lightfield_viewer_keys.py": ("browser",),
    "service/test_docs.py::test_docs_render_every_operation_without_a_network": ("browser",),
    # docker: the container image built and run (with PostgreSQL and Ray inside)
    "test_docker.py": ("docker", "slow"),
    # ray: a Ray cluster of several nodes on this machine (tests/harness/raycluster.py)
    "service/test_cluster.py": ("ray", "server", "slow"),
    "service/test_cluster_tiles.py": ("ray", "slow"),
    "service/test_cluster_faults.py": ("ray", "server", "slow"),
    # postgres: tests that start PostgreSQL clusters of their own (not through a fixture)
    "service/test_pgcluster.py": ("postgres",),
    "service/test_service_postgres.py": ("postgres", "server", "slow"),
    # server: real server processes (tests/harness/process.py), kill -9, replicas
    "service/test_service_crash.py": ("server", "slow"),
    "service/test_service_damage.py": ("server",),
    "service/test_connections.py": ("server",),
    "service/test_metrics.py": ("server",),
    "service/test_soak_script.py": ("server",),
    "service/test_soak_script.py::test_short_soak_on_postgresql_with_two_replicas": ("postgres",),
    "test_lightfield_orbit_service.py": ("server", "slow"),
    "test_readme.py::test_readme_blocks_run_as_written_twice": ("server",),
    "test_docs_site.py::test_page_blocks_run_as_written_twice": ("server",),
    "service/test_service_answers.py::test_healthz_answers_within_a_second_during_worst_cases":
        ("server",),
    "service/test_datadir.py::test_second_server_on_a_data_dir_in_use_refuses_to_start":
        ("server",),
    "service/test_service_hostile_bodies.py::"
    "test_real_server_keeps_the_connection_after_hostile_bodies": ("server",),
    "service/test_service_hostile_bodies.py::"
    "test_real_server_answers_deeply_nested_json_with_a_422_and_keeps_the_connection": ("server",),
    "service/test_service_limits.py::test_big_json_bodies_do_not_stall_the_event_loop": ("server",),
    "service/test_logs.py::test_a_real_server_logs_json_only": ("server",),
    "service/test_service_replicas.py::test_write_through_one_replica_read_through_the_other":
        ("server",),
    "service/test_service_replicas.py::test_replicas_at_the_same_position_answer_bit_identically":
        ("server",),
    "service/test_service_replicas.py::test_kill9_of_a_replica_during_uploads_loses_nothing":
        ("server", "slow"),
    "service/test_service_replicas.py::test_kill9_of_the_replica_writing_a_snapshot": ("server",),
    "service/test_service_replicas.py::test_processes_2_share_one_port_and_one_data_dir":
        ("server",),
    "service/test_service_replicas.py::"
    "test_children_import_the_supervisors_installation_from_any_directory": ("server",),
    "service/test_service_replicas.py::test_a_restarted_replica_takes_connections_only_once_ready":
        ("server",),
}

TESTS = os.path.dirname(os.path.abspath(__file__))


def _lane_table() -> dict[str, set[str]]:
    """LANES by ``path`` and ``path::function``, every path checked to exist."""
    table: dict[str, set[str]] = {}
    for key, lanes in LANES.items():
        path = key.split("::")[0]
        if not os.path.isfile(os.path.join(TESTS, path)):
            raise pytest.UsageError(f"tests/conftest.py LANES names {key!r}: no such module")
        table.setdefault(key, set()).update(lanes)
    return table


def pytest_collection_modifyitems(config, items):
    table = _lane_table()
    modules = {}
    for item in items:
        path = os.path.relpath(str(item.path), TESTS).replace(os.sep, "/")
        name = getattr(item, "originalname", item.name)
        modules.setdefault(path, getattr(item, "module", None))
        lanes = table.get(path, set()) | table.get(f"{path}::{name}", set())
        fixtures = getattr(item, "fixturenames", ())
        lanes.update(FIXTURE_LANES[f] for f in fixtures if f in FIXTURE_LANES)
        callspec = getattr(item, "callspec", None)
        if callspec is not None and callspec.params.get("backend") == "postgresql":
            lanes.add("postgres")
        for lane in sorted(lanes):
            item.add_marker(lane)
    for key in table:  # a test renamed would otherwise slip into the fast lane unseen
        path, _, name = key.partition("::")
        if name and modules.get(path) is not None and not hasattr(modules[path], name):
            raise pytest.UsageError(f"tests/conftest.py LANES names {key!r}: no such test")
