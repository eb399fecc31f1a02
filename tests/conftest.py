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
# tests whose harness is not a fixture and the slow ones, by the tables LANES and SLOW below.

#: fixture -> lane: a test that uses the fixture is in the lane.
FIXTURE_LANES = {
    "pg_cluster": "postgres", "pg_url": "postgres", "own_pg_cluster": "postgres",
}

#: Whole modules (``path``) or single tests (``path::function``, every parameter of the
#: function), paths under tests/, and their lanes. A module or test named here that does
#: not exist is a collection error (a renamed one would otherwise slip into the fast lane).
LANES = {
    # browser: Debian's headless Chromium (tests/harness/browser.py)
    "test_lightfield_viewer.py": ("browser", "slow"),
    "test_lightfield_viewer_keys.py": ("browser",),
    "service/http/test_docs.py::test_docs_render_every_operation_without_a_network": ("browser",),
    # docker: the container image built and run (with PostgreSQL and Ray inside)
    "test_docker.py": ("docker", "slow"),
    # ray: a Ray cluster of several nodes on this machine (tests/harness/raycluster.py)
    "service/cluster/test_cluster.py": ("ray", "server", "slow"),
    "service/cluster/test_cluster_tiles.py": ("ray", "slow"),
    "service/cluster/test_cluster_faults.py": ("ray", "server", "slow"),
    # postgres: tests that start PostgreSQL clusters of their own (not through a fixture)
    "service/test_pgcluster.py": ("postgres",),
    "service/test_service_postgres.py": ("postgres", "server", "slow"),
    # server: real server processes (tests/harness/process.py), kill -9, replicas
    "service/test_service_crash.py": ("server", "slow"),
    "service/test_service_damage.py": ("server",),
    "service/http/test_connections.py": ("server",),
    "service/http/test_metrics.py": ("server",),
    "service/test_soak_script.py": ("server",),
    "service/test_soak_script.py::test_short_soak_on_postgresql_with_two_replicas": ("postgres",),
    "test_lightfield_orbit_service.py": ("server", "slow"),
    # a real server (uvicorn on a loopback port) the captures are imported into
    "test_lightfield_import.py": ("server", "slow"),
    "test_readme.py::test_readme_blocks_run_as_written_twice": ("server",),
    "test_docs_site.py::test_page_blocks_run_as_written_twice": ("server",),
    "service/test_service_answers.py::test_healthz_answers_within_a_second_during_worst_cases":
        ("server",),
    "service/log/test_datadir.py::test_second_server_on_a_data_dir_in_use_refuses_to_start":
        ("server",),
    # not a server process, but the machine itself: it mounts a tmpfs (root) to fill a disk
    "service/log/test_datadir.py::test_full_disk_refuses_writes_with_507_and_reads_go_on":
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
    # the docs site: a strict MkDocs build, and every page's blocks against a real server
    "test_docs_site.py::test_the_site_builds_strictly_with_every_page": ("slow",),
    "test_docs_site.py::test_the_http_reference_is_the_apps_schema": ("slow",),
    "test_docs_site.py::test_the_api_reference_is_written_from_the_docstrings": ("slow",),
    "test_docs_site.py::test_page_blocks_run_as_written_twice": ("server",),
}

#: slow: tests of more than about 2 s each on a loaded 2-core machine (``--durations`` of
#: the fast lane), as ``path`` or ``path::function`` (every parameter of the function).
SLOW = [
    # the library
    "test_atlas.py::test_a_thinner_seam_is_stored_alike_whatever_the_batches",
    "test_atlas.py::test_covering_atlas_charts_every_flat",
    "test_atlas.py::test_planes_in_r4_field",
    "test_atlas.py::test_a_relative_field_file_answers_the_same",
    "test_atlas.py::test_a_net_leaves_a_stored_sample_near_every_sample_it_drops",
    "test_atlas.py::test_oriented_rays_keep_their_direction",
    "test_atlas.py::test_every_sample_accepted_and_reproduced",
    "test_atlas.py::test_weights_recombine_the_values",
    "test_atlas.py::test_a_fitted_unit_is_tried_without_the_net",
    "test_atlas.py::test_held_counts_what_route_routes",
    "test_atlas.py::test_a_flats_routing_does_not_depend_on_its_batch",
    "test_atlas.py::test_a_unit_from_the_data_is_chosen_by_the_first_batch_and_kept",
    "test_atlas_parts.py",
    "test_atlas_query.py::test_query_equals_the_reference_bit_for_bit",
    "test_atlas_query.py::test_query_equals_the_reference_in_given_order_and_threads",
    "test_atlas_query.py::test_routing_equals_the_reference",
    "test_atlas_query.py::test_status_says_why_a_row_has_no_value",
    "test_contract.py::test_mypy_verifies_both_kinds_implement_the_protocol",
    "test_parallel.py::"
    "test_answers_snapshots_and_restores_are_the_same_bits_on_any_number_of_threads",
    "test_parallel.py::"
    "test_concurrent_queries_and_inserts_on_threads_match_the_sequential_field",
    "test_tiles.py::test_the_fig11_field_at_1m_rays_in_2_4_8_tiles",
    "test_tiles.py::test_a_fields_chart_in_tiles_answers_as_the_unsplit_field",
    "test_tiles.py::test_auto_tiles_follow_the_points_and_the_threads",
    "test_tiles.py::test_batches_across_tile_borders_and_duplicates",
    "test_tiles.py::test_inserts_in_a_row_share_one_exchange",
    "test_atlas.py::test_deep_inside_a_chart_equals_the_single_chart_field",
    "test_atlas.py::test_a_relative_atlas_stores_fewer_copies_and_keeps_what_it_is",
    "test_atlas.py::test_sliced_insert_equals_the_whole_insert",
    "test_atlas.py::test_a_fitted_unit_follows_what_the_values_change_with",
    "test_atlas.py::test_data_driven_atlas_rejects_with_a_reason",
    "test_experiment.py::"
    "test_every_case_recovers_every_coefficient_with_degenerate_bases_redrawn",
    "test_gradient.py::test_a_points_field_answers_as_a_second_implementation",
    "test_gradient.py::test_a_tiled_chart_answers_as_the_whole_one",
    "test_tiles.py::test_answers_are_the_unsplit_triangulations_bits",
    "test_triangulation.py::test_interpolation_matches_scipy",
    "test_triangulation.py::test_snapshot_roundtrip_file",
    "test_triangulation.py::test_located_queries_lie_in_their_simplex",
    "test_warp.py::test_a_flat_warped_field_file_and_atlas_round_trip",
    # light fields: figures, orbits, captures imported over HTTP
    "test_lightfield_capture_figure.py::"
    "test_the_forward_rig_beats_the_two_plane_light_field_on_every_held_out_view",
    "test_lightfield_depth.py::test_the_sphere_rig_beats_the_two_sphere_light_field_on_every_held_out_view",
    "test_lightfield_depth.py::test_a_rig_camera_renders_its_own_photograph",
    "test_lightfield_orbit.py::test_ours_beats_the_nearest_rays_baseline_on_every_view",
    "test_lightfield_orbit.py::test_straddling_views_are_no_worse_than_inside_one_chart",
    "test_lightfield_render.py::test_baselines_on_the_same_samples",
    "test_lightfield_render.py::test_paper_figure_small",
    "test_lightfield_orbit.py::test_orbit_command_writes_sheet_and_table",
    "test_lightfield_orbit.py::test_with_sparse_eyes",
    "test_lightfield_orbit.py::test_views_by_the_gradient_interpolant",
    "test_lightfield_orbit.py::test_cli_orbit_with_the_papers_charts",
    "test_lightfield_orbit.py::test_inside_one_chart_the_atlas_answers_as_that_chart",
    "test_lightfield_service.py::test_start_demo_field_in_the_background",
    "test_lightfield_service.py::test_render_png_matches_ground_truth",
    # the service in-process
    "service/test_client_batches.py::test_progress_callback_and_bar",
    "service/test_layers.py::test_mypy_checks_the_wire",
    "service/http/test_docs.py::"
    "test_every_body_has_an_example_and_the_examples_are_valid_requests",
    "service/test_service_api.py::"
    "test_status_tells_empty_charts_from_unreachable_flats",
    "service/test_service_atlas.py::"
    "test_a_relative_atlas_asked_for_at_create_answers_as_the_librarys",
    "service/test_service_atlas.py::test_a_unit_fitted_to_the_first_batch_over_http",
    "service/test_service_atlas.py::"
    "test_reach_of_a_covering_atlas_is_validated_stored_and_restored",
    "service/test_service_atlas.py::test_atlas_fields_for_other_dimensions",
    "service/test_service_atlas.py::test_samples_atlas_charts_where_the_flats_are",
    "service/test_service_atlas.py::"
    "test_a_thinner_seam_is_taken_at_create_described_and_validated",
    "service/test_service_atlas.py::test_unit_of_length_is_validated_stored_and_restored",
    "service/test_service_atlas.py::"
    "test_a_field_stored_before_isometric_charts_restores_as_it_was_built",
    "service/test_service_cost.py::"
    "test_a_batch_half_inserted_does_not_inflate_the_estimate",
    "service/test_service_cost.py::"
    "test_refusal_counting_pending_samples_is_429_and_413_only_when_it_cannot_pass",
    "service/test_service_hardening.py::"
    "test_flats_without_arrays_are_outside_the_schema_and_refused",
    "service/test_service_limits.py::"
    "test_reads_keep_flowing_while_a_big_wait_false_batch_is_indexed",
    "service/test_service_replicas.py::"
    "test_a_read_waits_a_bounded_time_for_a_position_then_503",
    "service/test_service_storage.py::"
    "test_replicas_opening_a_new_data_dir_at_once_all_open",
    "service/test_service_tiles.py::"
    "test_a_tiled_one_chart_field_answers_as_the_unsplit_one",
    "service/test_service_wait.py::"
    "test_wait_false_acknowledges_then_indexes_in_commit_order",
    "service/test_service_wait.py::"
    "test_a_committed_upload_waits_a_bounded_time_then_503_stored",
    "service/http/test_codec_hostile.py::test_fuzz_npy",
    "service/http/test_codec_hostile.py::test_fuzz_npz",
    "service/http/test_codec_hostile.py::test_fuzz_strategies_reach_every_outcome",
    "service/test_service_api.py::test_upload_forms_match_in_process_field",
    "service/test_service_atlas.py::"
    "test_a_unit_from_the_data_is_chosen_once_and_recorded_with_the_batches",
    "service/test_service_atlas.py::"
    "test_covering_atlas_field_accepts_every_orientation_and_restores",
    "service/test_service_atlas.py::"
    "test_a_first_batch_of_one_flat_gives_the_default_unit_and_later_batches_keep_it",
    "service/test_service_atlas.py::test_cost_guard_counts_every_chart_holding_a_sample",
    "service/test_service_atlas.py::test_render_an_oriented_atlas_field",
    "service/test_service_cost.py::"
    "test_a_kind_that_could_not_hold_min_field_samples_is_refused_at_create",
    "service/test_service_schema.py::test_openapi_conformance",
    "service/test_service_schema.py::test_openapi_conformance_with_keys",
    "service/test_service_schema.py::test_what_the_schema_allows_but_the_service_refuses_is_stated",
    "service/test_service_snapshot_parts.py",
    "service/test_service_storage.py::test_delete_removes_batches_and_snapshot",
    "service/test_service_storage.py::test_queries_never_see_half_a_batch",
    "service/test_service_tiles.py::test_a_replayed_tiled_field_holds_the_same_bytes",
    "service/test_service_wait.py::test_shutdown_leaves_pending_batches_to_the_replay",
]

TESTS = os.path.dirname(os.path.abspath(__file__))


def _lane_table() -> dict[str, set[str]]:
    """LANES and SLOW by ``path`` and ``path::function``, every path checked to exist."""
    table: dict[str, set[str]] = {}
    for key, lanes in [*LANES.items(), *((key, ("slow",)) for key in SLOW)]:
        path = key.split("::")[0]
        if not os.path.isfile(os.path.join(TESTS, path)):
            raise pytest.UsageError(
                f"tests/conftest.py (LANES or SLOW) names {key!r}: no such module")
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
            raise pytest.UsageError(
                f"tests/conftest.py (LANES or SLOW) names {key!r}: no such test")
