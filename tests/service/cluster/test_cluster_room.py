"""Cluster mode when the nodes have no room for a shard group: describe and the 503 say
so, and what would fix it; the group is placed, and answers, once room is made.

A real Ray cluster on loopback (tests/harness/raycluster.py) whose one node holds three
shards of 1 GiB: a field of two groups fits, a second field's second group does not."""
from __future__ import annotations

import contextlib
import time

import numpy as np
import pytest

from flatserve.client import Client, ServiceError
from tests.harness.cluster import sphere_rays
from tests.harness.process import ServerProcess
from tests.harness.raycluster import GiB, RayNodes

pytestmark = [pytest.mark.ray, pytest.mark.server, pytest.mark.slow]


def _groups(c: Client, name: str, until, wait_s: float = 120.0) -> list[dict]:
    end = time.monotonic() + wait_s
    while True:
        groups = c.describe(name)["shard_groups"]
        if until(groups) or time.monotonic() > end:
            return groups
        time.sleep(1.0)


def test_a_group_no_node_has_room_for_is_described_with_the_fix(tmp_path):
    rng = np.random.default_rng(53)
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=0, memory=3 * GiB))
        front = stack.enter_context(ServerProcess(
            tmp_path / "data", tmp_path / "front.log", ray=nodes.address, snapshot_every=0,
            ray_shards=2, ray_shard_memory=GiB, read_wait_timeout=5, apply_wait_timeout=5))
        front.wait_ready(180)
        with Client(front.url, retries=0, timeout=120) as c:
            c.create_field("first", channels=1)
            placed = _groups(c, "first", lambda gs: all(g["live"] == 1 for g in gs))
            assert [(g["live"], g["unplaced"]) for g in placed] == [(1, None), (1, None)], placed
            c.create_field("second", channels=1)
            groups = _groups(c, "second", lambda gs: sum(g["live"] for g in gs) == 1
                             and any(g["unplaced"] for g in gs))
            # one group fits beside the first field's two; the other has no room
            assert sorted(g["live"] for g in groups) == [0, 1], groups
            why = next(g["unplaced"] for g in groups if g["live"] == 0)
            assert "no live node has room" in why and "ray_shard_memory" in why, why
            assert "FLATSERVE_RAY_SHARD_MEMORY" in why and "--memory" in why, why
            assert all(g["unplaced"] is None for g in groups if g["live"] == 1), groups
            # a query that needs the group: 503 saying it cannot be placed and why
            o, d = sphere_rays(rng, 2000)
            c.upload_rays("second", o, d, rng.uniform(size=(2000, 1)), wait=False)
            with pytest.raises(ServiceError) as exc:
                c.query_rays("second", o, d)
            assert exc.value.status == 503 and "cannot be placed" in str(exc.value), exc.value
            assert "no live node has room" in str(exc.value)
            # room made: the group is placed and the field answers every ray it holds
            c.delete_field("first")
            groups = _groups(c, "second", lambda gs: all(g["live"] == 1 for g in gs), 180)
            assert all(g["live"] == 1 and g["unplaced"] is None for g in groups), groups
            got = None
            end = time.monotonic() + 120
            while got is None:
                try:
                    got = c.query_rays("second", o[:200], d[:200])
                except ServiceError as e:
                    if e.status != 503 or time.monotonic() > end:
                        raise
                    time.sleep(1.0)
            assert got.inside.all()
