"""Cluster mode (``serve --ray``): a field's shards in actors on a REAL multi-node Ray
cluster (raylets on loopback, tests/harness/raycluster.py), fronts that are REAL server
processes, a REAL PostgreSQL log.

The oracle is the one-process field: the field's definition and its stored batches
read back from PostgreSQL and folded, in log order, through the code a lone server
runs (``prepare`` + ``insert_prepared`` in slices). Every answer of the cluster must
equal it bit for bit at the same log position (values, inside; sample ids and
weights for one chart); every acknowledged batch must be stored once.
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
import time

import httpx
import numpy as np
import pytest

from flatserve.client import Client, ServiceError
from flatserve.flats import Flats
from flatserve.service.rooms.units import adopt_unit
from flatserve.service.log.backend import open_backend
from flatserve.service.log.blobs import split_batch
from flatserve.service.rooms.entry import FieldSpec
from flatserve.service.http.routes_lightfield import CameraSpec, render_frame
from flatserve.service.settings import Settings
from tests.harness.cluster import Fronts, sphere_rays
from tests.harness.process import ServerProcess
from tests.harness.raycluster import RayNodes, assigned_resources, unbuilt_checkout

from tests.harness.fields import ONE_CHART, paper_rays
from tests.harness.service import snapshot_soon



def fill(c: Client, rng, atlas: str, *, batches: int, rows: int, copies: int = 1) -> dict:
    """Create an atlas field ``atlas`` (``copies`` of each shard group) and a one-chart
    field "one" in 2 tiles (2 channels; its shard group holds both tiles, on its node's
    cores) and upload ``batches`` batches of ``rows`` rays to each, waiting for every
    other one; the atlas field's create answer."""
    info = c.create_field(atlas, channels=2, copies=copies)
    c.create_field("one", channels=2, basis=ONE_CHART, tiles=2)
    for i in range(batches):
        o, d = sphere_rays(rng, rows)
        c.upload_rays(atlas, o, d, rng.uniform(size=(rows, 2)), wait=bool(i % 2))
        o, d = paper_rays(rng, rows)
        c.upload_rays("one", o, d, rng.uniform(size=(rows, 2)), wait=bool(i % 2))
    return info


def oracle(url, name: str, upto: int | None = None):
    """The field built in this process from its stored definition and batches, in log
    order, as a lone server builds it; and the log position of its last batch. ``url``:
    PostgreSQL's, or the data directory of a server on SQLite (read as a follower)."""
    st = open_backend(Settings(database_url=url) if isinstance(url, str) else
                      Settings(data_dir=url), follower=True)
    try:
        row = next(r for r in st.state()[1] if r.name == name)
        spec = FieldSpec.from_dict(row.spec)
        from flatserve.basis import Basis

        fld = spec.new_field(Basis(row.basis["Q"], row.basis["r"], spec.k))
        pos = 0
        for b in st.batches(row.id, upto_position=upto):
            arrays, values, unit = split_batch(st.batch_arrays(row.id, b.seq))
            adopt_unit(fld, unit)  # (the unit the front chose from the first batch)
            fld.insert_prepared(fld.prepare(Flats.from_arrays(arrays, k=spec.k, d=spec.d), values),
                                slice_rows=Settings().insert_slice_rows)
            pos = b.position
        return fld, pos
    finally:
        st.close()


def recorded_unit(url: str, name: str) -> float | None:
    """The unit of length stored with the first batch of field ``name`` (None: none)."""
    st = open_backend(Settings(database_url=url), follower=True)
    try:
        row = next(r for r in st.state()[1] if r.name == name)
        first = st.batches(row.id)[0]
        return split_batch(st.batch_arrays(row.id, first.seq))[2]
    finally:
        st.close()


def assert_same(url: str, front: ServerProcess, name: str, probe, *, weights=False,
                timeout: float = 120.0, interpolant: str = "linear") -> None:
    """The front's answer at the log's head equals the one-process field's, bit for bit:
    for ``probe`` (answered through the front's thread pool) and for small queries
    of its first rays (routed and awaited on the front's event loop); with
    ``interpolant``, the shards' answers by it."""
    ref, head = oracle(url, name)
    want = ref.query(Flats.from_rays(*probe), return_weights=weights, interpolant=interpolant)
    end = time.monotonic() + timeout
    with Client(front.url, retries=0, timeout=120) as c:
        while True:
            try:
                got = c.query_rays(name, *probe, weights=weights, min_position=head,
                                   interpolant=interpolant)
                break
            except ServiceError as exc:  # shards still restoring: 503, never a partial answer
                assert exc.status == 503, exc
                if time.monotonic() > end:
                    raise
                time.sleep(1.0)
        while c.describe(name)["nsamples"] != ref.nsamples and time.monotonic() < end:
            time.sleep(0.5)  # the shards report their sizes each second
        assert c.describe(name)["nsamples"] == ref.nsamples
        small = [(got, want)]
        for rows in (slice(0, 1), slice(1, 11), slice(11, 74)):
            o, d = probe[0][rows], probe[1][rows]
            small.append((c.query_rays(name, o, d, weights=weights, min_position=head,
                                       interpolant=interpolant),
                          ref.query(Flats.from_rays(o, d), return_weights=weights,
                                    interpolant=interpolant)))
    for got, want in small:
        np.testing.assert_array_equal(got.inside, want.inside)
        np.testing.assert_array_equal(got.values, want.values)  # bit-identical
        if weights:
            np.testing.assert_array_equal(got.ids, want.ids)
            np.testing.assert_array_equal(got.weights, want.weights)


@pytest.fixture
def nodes():
    with RayNodes(workers=2) as n:  # a head and two workers: 3 nodes
        yield n


@pytest.fixture
def fronts(tmp_path, pg_url, nodes):
    with contextlib.ExitStack() as stack:
        yield Fronts(tmp_path, pg_url, nodes.address, stack)


def test_a_three_node_cluster_answers_as_one_process(fronts, pg_url, rng):
    a = fronts.start()
    probe = sphere_rays(rng, 3000)
    with Client(a.url, retries=0, timeout=120) as c:
        assert fill(c, rng, "atlas", batches=4, rows=2500)["ncharts"] == 16
    assert_same(pg_url, a, "atlas", probe)
    assert_same(pg_url, a, "one", paper_rays(rng, 2000), weights=True)
    # the gradient interpolant: slopes computed by the shard workers, beside their charts
    assert_same(pg_url, a, "atlas", probe, interpolant="gradient")
    assert_same(pg_url, a, "one", paper_rays(rng, 2000), interpolant="gradient")
    # the one-chart field's 2 tiles each in an actor of its own, on different nodes
    with Client(a.url, retries=0) as c:
        end = time.monotonic() + 30
        while True:  # the tiles' places are polled each second: the last batch's in a moment
            (group,) = c.describe("one")["shard_groups"]
            held = sum(t["npoints"] for t in group["tiles"] or ())
            if held > group["samples"] or time.monotonic() > end:
                break
            time.sleep(0.5)
    assert len(group["tiles"]) == 2, group
    assert len({t["node"] for t in group["tiles"]}) == 2, group
    assert held > group["samples"], group  # own points + halo
    # a rendered view (the light-field route) is the one-process field's, bit for bit
    ref, _ = oracle(pg_url, "atlas")
    want, *_ = render_frame(ref, CameraSpec(width=24, height=20).camera(), fill=0.0, fmt="npy")
    got = httpx.post(f"{a.url}/v1/fields/atlas/render", timeout=120,
                     json={"width": 24, "height": 20, "format": "npy"})
    assert got.status_code == 200, got.text
    assert got.content == want
    want, *_ = render_frame(ref, CameraSpec(width=24, height=20).camera(), fill=0.0, fmt="npy",
                            interpolant="gradient")
    got = httpx.post(f"{a.url}/v1/fields/atlas/render", timeout=120,
                     json={"width": 24, "height": 20, "format": "npy", "interpolant": "gradient"})
    assert got.status_code == 200, got.text
    assert got.content == want
    # a second front (stateless: nothing to load) answers the same
    b = fronts.start()
    assert_same(pg_url, b, "atlas", probe)
    # read-your-writes through any front: an upload through a, read at once through b
    with Client(a.url, retries=0) as ca, Client(b.url, retries=0) as cb:
        o, d = sphere_rays(rng, 500)
        pos = ca.upload_rays("atlas", o, d, rng.uniform(size=(500, 2)))["position"]
        got = cb.query_rays("atlas", o, d, min_position=pos)
        assert got.inside.mean() > 0.9  # its own samples are there
    assert_same(pg_url, b, "atlas", probe)


def test_snapshot_written_in_parts_by_the_shards_and_a_cluster_restarted_from_the_log(
        tmp_path, pg_url, rng):
    probe = sphere_rays(rng, 2000)
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=1))
        fr = Fronts(tmp_path, pg_url, nodes.address, stack)
        a = fr.start()
        with Client(a.url, retries=0, timeout=120) as c:
            c.create_field("f", channels=2)
            for _ in range(3):
                o, d = sphere_rays(rng, 3000)
                c.upload_rays("f", o, d, rng.uniform(size=(3000, 2)), wait=True)
            snap = snapshot_soon(c, 60.0, name="f", interval=1.0)
            assert snap["batch"] == 3 and snap["written"] > 0
            # a batch touching one chart: the next snapshot writes only its part
            o = np.zeros((200, 3)) + rng.normal(scale=0.01, size=(200, 3))
            d = np.tile([0.0, 0.0, 1.0], (200, 1)) + rng.normal(scale=0.01, size=(200, 3))
            c.upload_rays("f", o, d, rng.uniform(size=(200, 2)), wait=True)
            snap2 = snapshot_soon(c, 60.0, name="f", interval=1.0)
            assert 0 < snap2["written"] < snap["written"] / 3, (snap, snap2)
            o, d = sphere_rays(rng, 1000)  # after the snapshot: replayed from the log
            c.upload_rays("f", o, d, rng.uniform(size=(1000, 2)))
            unit = c.describe("f")["atlas"]["unit"]
        # the front chose the unit from the first batch and stored it with it (the
        # shard workers took it from there)
        assert unit is not None and recorded_unit(pg_url, "f") == unit
        assert_same(pg_url, a, "f", probe)
    # the whole cluster (every node, every front) is gone; a new one starts from the log
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=2))
        fr = Fronts(tmp_path / "again", pg_url, nodes.address, stack)
        (tmp_path / "again").mkdir()
        b = fr.start()
        assert_same(pg_url, b, "f", probe)
        with Client(b.url, retries=0) as c:  # each shard loaded its own parts, then the log
            got = c.describe("f")
            groups = got["shard_groups"]
            assert got["atlas"]["unit"] == unit  # (a front restarted: the recorded unit)
        assert len(groups) == 4 and all(
            g["restored_from"] == "snapshot after batch 4" for g in groups), groups


def test_a_node_killed_during_uploads_and_queries_loses_nothing(fronts, nodes, pg_url, rng):
    a = fronts.start()
    probe = sphere_rays(rng, 1500)
    with Client(a.url, retries=0, timeout=120) as c:
        c.create_field("f", channels=2, copies=2)
        o, d = sphere_rays(rng, 4000)
        c.upload_rays("f", o, d, rng.uniform(size=(4000, 2)), wait=True)
    assert_same(pg_url, a, "f", probe)
    acked: dict[str, int] = {}
    stop = threading.Event()
    failures: list = []
    answered = [0, 0]  # queries answered, 503s

    def writer():
        r = np.random.default_rng(7)
        with Client(a.url, retries=0, timeout=120) as c:
            i = 0
            while not stop.is_set():
                o, d = sphere_rays(r, 500)
                key = f"w{i}"
                try:
                    acked[key] = c.upload_rays("f", o, d, r.uniform(size=(500, 2)),
                                               idempotency_key=key)["batch"]
                except Exception as exc:  # uploads never depend on the shards
                    failures.append(("upload", repr(exc)))
                i += 1
                time.sleep(0.05)

    def reader(rows, counts):  # large queries (thread pool) or small ones (event loop)
        with Client(a.url, retries=0, timeout=120) as c:
            while not stop.is_set():
                try:
                    got = c.query_rays("f", probe[0][rows], probe[1][rows])
                    assert got.inside.mean() > 0.5, "a partial answer presented as whole"
                    counts[0] += 1
                except ServiceError as exc:
                    if exc.status != 503:
                        failures.append(("query", repr(exc)))
                    counts[1] += 1
                time.sleep(0.05)

    small = [0, 0]
    ts = [threading.Thread(target=writer),
          threading.Thread(target=reader, args=(slice(None), answered)),
          threading.Thread(target=reader, args=(slice(0, 20), small))]
    for t in ts:
        t.start()
    time.sleep(3)
    before, before_small = answered[0], small[0]
    nodes.kill(nodes.workers[0])  # a node with shards on it dies
    time.sleep(15)
    during, during_small = answered[0] - before, small[0] - before_small
    stop.set()
    for t in ts:
        t.join(120)
    assert not failures, failures
    assert during > 0, "no query answered after the node died (a copy keeps reads flowing)"
    assert during_small > 0, "no small query answered after the node died"
    nodes.add_worker()  # room for the lost copies again
    with Client(a.url, retries=0) as c:
        stored = {b["idempotency_key"]: b["batch"] for b in c.batches("f")}
        end = time.monotonic() + 240
        while time.monotonic() < end:  # the lost copies are placed again and restored
            groups = c.describe("f")["shard_groups"]
            if all(g["live"] == 2 for g in groups):
                break
            time.sleep(1)
        assert all(g["live"] == 2 for g in groups), groups
    assert all(stored.get(k) == v for k, v in acked.items()), "an acknowledged batch was lost"
    assert_same(pg_url, a, "f", probe, timeout=240)


def tiles_reported(c, name, n, timeout=120.0, **unless):
    """The field's one shard group once its status reports ``n`` tiles, none of them
    with a value of ``unless`` (``pid=..``, ``node=..``): describe shows a group's last
    report, which follows a start or a restart by a poll."""
    end = time.monotonic() + timeout
    while True:
        (group,) = c.describe(name)["shard_groups"]
        tiles = group.get("tiles") or []
        if len(tiles) == n and not any(t[k] == v for t in tiles for k, v in unless.items()):
            return group
        assert time.monotonic() < end, group
        time.sleep(0.5)


def test_a_tile_lost_with_its_process_or_its_node_its_group_restores_itself(fronts, nodes, pg_url, rng):
    """A tile cannot be rebuilt alone (its halo came from the exchange): its group's
    actor ends and Ray restarts it, with new tiles, from the log."""
    a = fronts.start()
    probe = paper_rays(rng, 1500)
    with Client(a.url, retries=0, timeout=120) as c:
        c.create_field("one", channels=2, basis=ONE_CHART, tiles=2)
        for i in range(3):
            o, d = paper_rays(rng, 2000)
            c.upload_rays("one", o, d, rng.uniform(size=(2000, 2)), wait=True)
        assert_same(pg_url, a, "one", probe, weights=True)
        group = tiles_reported(c, "one", 2)
        # a tile's process dies: its group ends itself and is restarted, with new tiles
        os.kill(group["tiles"][1]["pid"], signal.SIGKILL)
        o, d = paper_rays(rng, 1000)  # an upload meanwhile: stored, applied once back
        c.upload_rays("one", o, d, rng.uniform(size=(1000, 2)), wait=False)
        assert_same(pg_url, a, "one", probe, weights=True, timeout=240)
        again = tiles_reported(c, "one", 2, pid=group["tiles"][1]["pid"])
        # a node holding a tile dies
        on = {t["node"] for t in again["tiles"]}
        victim = next(w for w in nodes.workers if w.node_id in on)
        nodes.kill(victim)
        nodes.add_worker()  # room for the restarted group and its tiles
        o, d = paper_rays(rng, 1000)  # (wait=false: the group restarts meanwhile)
        c.upload_rays("one", o, d, rng.uniform(size=(1000, 2)), wait=False)
        assert_same(pg_url, a, "one", probe, weights=True, timeout=240)
        group = tiles_reported(c, "one", 2, node=victim.node_id)
    assert group["restored_from"] == "the log", group


def test_a_front_killed_the_other_answers(fronts, pg_url, rng):
    a, b = fronts.start(), fronts.start()
    probe = sphere_rays(rng, 1500)
    with Client(a.url, retries=0, timeout=120) as c:
        c.create_field("f", channels=2)
        for _ in range(3):
            o, d = sphere_rays(rng, 1500)
            c.upload_rays("f", o, d, rng.uniform(size=(1500, 2)))
    a.kill9()
    assert_same(pg_url, b, "f", probe)
    with Client(b.url, retries=0) as c:  # writes go on through the survivor
        o, d = sphere_rays(rng, 800)
        c.upload_rays("f", o, d, rng.uniform(size=(800, 2)))
    assert_same(pg_url, b, "f", probe)


def test_an_unreachable_cluster_is_named_at_start(tmp_path, pg_url):
    with ServerProcess(tmp_path / "d", tmp_path / "log", database_url=pg_url,
                       ray="127.0.0.1:9") as srv:
        assert srv.proc.wait(180) == 2
    text = (tmp_path / "log").read_text()
    assert "the Ray cluster at '127.0.0.1:9' cannot be reached" in text, text[-2000:]


def test_a_one_machine_cluster_on_sqlite(tmp_path, rng):
    """No PostgreSQL: the front holds the SQLite data directory, the shards on this
    machine's Ray nodes read its log and store their snapshot parts there."""
    data = tmp_path / "front1"
    probe = sphere_rays(rng, 2000)
    opts = {"snapshot_every": 0, "ray_shards": 2, "ray_shard_memory": 1 << 30}
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=1))
        a = stack.enter_context(ServerProcess(data, tmp_path / "front1.log", ray=nodes.address,
                                              **opts))
        a.wait_ready(180)
        with Client(a.url, retries=0, timeout=120) as c:
            fill(c, rng, "f", batches=3, rows=2000, copies=2)  # a copy on each node
        assert_same(data, a, "f", probe)
        assert_same(data, a, "one", paper_rays(rng, 1000), weights=True)
        with Client(a.url, retries=0, timeout=120) as c:
            for name in ("f", "one"):
                snap = snapshot_soon(c, 60.0, name=name, interval=1.0)
                assert snap["batch"] == 3 and snap["written"] > 0
            o, d = sphere_rays(rng, 500)  # after the snapshot: replayed from the log
            c.upload_rays("f", o, d, rng.uniform(size=(500, 2)))
        # the parts are the shards' files in the data directory; the field in tiles
        # has one per tile, named by its field file (a part too)
        parts = [p.read_bytes() for p in (data / "snapshots" / "parts").iterdir()]
        assert len(parts) > 2
        heads = [p for p in parts if p.startswith(b"FSFIELD\0") and b'"parts": [' in p[:8192]]
        assert len(heads) == 1, "the field in tiles: one field file naming its tiles' parts"
        # each shard actor (both copies of f's groups, placed by a placement group's
        # bundles) holds a share of this machine's node:<address> resource, so that a
        # node joining later from elsewhere (no access to this data directory) is
        # given none (its tiles too: test_cluster_tiles.py)
        from flatserve.service.cluster.ray_env import PIN_SHARE

        shares = pinned_shares(nodes.address)
        assert len(shares) == 5 and set(shares.values()) == {PIN_SHARE}, shares
        with Client(a.url, retries=0) as c:
            assert [g["live"] for g in c.describe("f")["shard_groups"]] == [2, 2]
    # every process gone; a new front and new nodes on the same directory
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=1))
        b = stack.enter_context(ServerProcess(data, tmp_path / "front2.log", ray=nodes.address,
                                              **opts))
        b.wait_ready(180)
        assert_same(data, b, "f", probe)
        assert_same(data, b, "one", paper_rays(rng, 1000), weights=True)
        with Client(b.url, retries=0) as c:
            groups = c.describe("f")["shard_groups"] + c.describe("one")["shard_groups"]
        assert len(groups) == 3 and all(g["restored_from"] == "snapshot after batch 3"
                                        for g in groups), groups


def test_a_front_started_inside_an_unbuilt_checkout_its_shards_import_the_installed_package(
        tmp_path, rng, monkeypatch):
    """The README's way: installed, then ``flatserve serve --ray`` from inside the clone
    (no built extension there). Ray puts a driver's working directory first on its
    workers' ``sys.path``: the shard actors must import the installed package all
    the same, not the checkout (``cannot import name '_core'``, every query 503)."""
    import sys

    env, checkout = unbuilt_checkout(tmp_path)
    for k, v in env.items():  # (the nodes' workers and the front inherit it)
        monkeypatch.setenv(k, v)
    script = [os.path.join(os.path.dirname(sys.executable), "flatserve"), "serve"]
    o, d = paper_rays(rng, 600)
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=0))
        a = stack.enter_context(ServerProcess(
            tmp_path / "data", tmp_path / "front.log", command=script, cwd=checkout,
            ray=nodes.address, snapshot_every=0, ray_shards=1, ray_shard_memory=1 << 30,
            read_wait_timeout=30))
        a.wait_ready(180)
        with Client(a.url, retries=0, timeout=120) as c:
            c.create_field("one", channels=2, basis=ONE_CHART)
            c.upload_rays("one", o, d, rng.uniform(size=(600, 2)), wait=True)
            try:
                got = c.query_rays("one", o[:40], d[:40])
            except ServiceError as exc:
                raise AssertionError(f"{exc}\n{(tmp_path / 'front.log').read_text()[-3000:]}")
        assert got.inside.mean() > 0.9


def _groups_when_live(front, name: str, live: int, timeout: float) -> list[dict]:
    """The field's ``shard_groups`` once every group has ``live`` copies live, or as they
    are after ``timeout`` seconds."""
    end = time.monotonic() + timeout
    with Client(front.url, retries=0) as c:
        while True:
            groups = c.describe(name)["shard_groups"]
            if all(g["live"] == live for g in groups) or time.monotonic() > end:
                return groups
            time.sleep(1)


def test_copies_above_the_live_nodes_placed_as_far_as_they_go_and_answers_tell_the_truth(
        tmp_path, rng):
    """A field asking for 3 copies on a cluster of 2 nodes: each group is placed on both
    (a copy a node; describe: ``copies`` 3, ``live`` 2) and answers, where a placement
    group of 3 bundles would never be placed (503 forever). Before any copy is heard
    from none is counted live. A ``wait=true`` upload is answered once every shard has
    the batch, with the field's samples then; describe counts what the shards hold. A
    third node joins: each group gets its third copy there."""
    data = tmp_path / "front1"
    probe = sphere_rays(rng, 1000)
    with contextlib.ExitStack() as stack:
        nodes = stack.enter_context(RayNodes(workers=1))
        a = stack.enter_context(ServerProcess(data, tmp_path / "front1.log", ray=nodes.address,
                                              snapshot_every=0, ray_shards=2,
                                              ray_shard_memory=1 << 30, read_wait_timeout=60))
        a.wait_ready(180)
        with Client(a.url, retries=0, timeout=180) as c:
            c.create_field("f", channels=2, copies=3)
            groups = c.describe("f")["shard_groups"]
            assert all(g["copies"] == 3 for g in groups), groups
            assert all(g["live"] == 0 or g["position"] is not None for g in groups), \
                "copies counted live before any was heard from"
            answers = []
            for _ in range(3):
                o, d = sphere_rays(rng, 1500)
                v = rng.uniform(size=(1500, 2))
                answers.append(c.upload_rays("f", o, d, v, wait=True))
            again = c.upload_rays("f", o, d, v, wait=True)  # every row a duplicate
            answers.append(again)
            got = c.describe("f")
        for ans in answers:
            want, _ = oracle(data, "f", upto=ans["position"])
            assert ans["indexed"] and ans["nsamples"] == want.nsamples, (ans, want.nsamples)
        assert [a["duplicates"] for a in answers] == [0, 0, 0, 1500], answers
        assert again["accepted"] == 1500 and again["nsamples"] == answers[2]["nsamples"]
        assert got["nsamples"] == want.nsamples, (got["nsamples"], want.nsamples)
        assert all(g["position"] >= answers[-1]["position"] for g in got["shard_groups"]), got
        assert_same(data, a, "f", probe)
        groups = _groups_when_live(a, "f", 2, 120)
        assert [(g["copies"], g["live"]) for g in groups] == [(3, 2), (3, 2)], groups
        # a node joins: each group gets its third copy there, which restores itself
        nodes.add_worker()
        groups = _groups_when_live(a, "f", 3, 240)
        assert [(g["copies"], g["live"]) for g in groups] == [(3, 3), (3, 3)], groups
        assert "gets its copy 3 on a node that joined" in (tmp_path / "front1.log").read_text()
        assert_same(data, a, "f", probe)


def test_a_group_is_placed_as_far_as_the_nodes_hold_its_copies():
    """``copies`` as far as the live nodes hold them, never fewer than 1: a definition
    stored with 0 (or fewer) copies never reaches the group's ordering as 0."""
    from flatserve.service.cluster.front.placement import placed_copies

    assert [placed_copies(c, 3) for c in (1, 2, 3, 8, 1000)] == [1, 2, 3, 3, 3]
    assert [placed_copies(c, 3) for c in (0, -3)] == [1, 1]
    assert placed_copies(2, 0) == 1 and placed_copies(3, None) == 3


def pinned_shares(address: str) -> dict[str, float | None]:
    """Per shard actor of the deployment (by name), the share of its machine's
    ``node:<address>`` resource Ray assigned to it (asked inside the actor, from a
    driver connected for the purpose)."""
    import ray

    ray.init(address=address, namespace="flatserve", log_to_driver=False)
    try:
        key = f"node:{ray.util.get_node_ip_address()}"
        out = {}
        for name in (n for n in ray.util.list_named_actors() if n.startswith("field-")):
            out[name] = assigned_resources(ray.get_actor(name)).get(key)
        return out
    finally:
        ray.shutdown()


def test_the_cluster_lost_while_running_503_then_a_front_restarted_on_the_new_cluster(
        tmp_path, pg_url, rng, monkeypatch):
    # Ray ends a driver whose cluster stays away (60 s by default; 10 s here), so that
    # its supervisor starts it again once the cluster is back
    monkeypatch.setenv("RAY_gcs_rpc_server_reconnect_timeout_s", "10")
    probe = sphere_rays(rng, 1000)
    with contextlib.ExitStack() as stack:
        nodes = RayNodes(workers=1)
        fr = Fronts(tmp_path, pg_url, nodes.address, stack)
        a = fr.start()
        with Client(a.url, retries=0, timeout=120) as c:
            c.create_field("f", channels=2)
            o, d = sphere_rays(rng, 2000)
            c.upload_rays("f", o, d, rng.uniform(size=(2000, 2)), wait=True)
        assert_same(pg_url, a, "f", probe)
        nodes.shutdown()
        with Client(a.url, retries=0, timeout=60) as c:
            for rows in (slice(None), slice(0, 3)):  # the thread pool's path, the event loop's
                with pytest.raises(ServiceError) as err:
                    c.query_rays("f", probe[0][rows], probe[1][rows])
                assert err.value.status == 503 and "no live copy" in str(err.value)
                assert "field 'f'" in str(err.value)  # named as the client knows it
                assert c.last_response.headers.get("retry-after")
            o, d = sphere_rays(rng, 300)  # the log still takes uploads (wait=false: no
            acked = c.upload_rays("f", o, d, rng.uniform(size=(300, 2)),  # shard has it)
                                  wait=False)
        assert a.proc.wait(120) != 0  # for its supervisor to restart
        assert "cannot be reached: " in fr.logs()  # the front said why, meanwhile
    with contextlib.ExitStack() as stack:  # the cluster back (a new one), the front restarted
        nodes = stack.enter_context(RayNodes(workers=1))
        (tmp_path / "again").mkdir()
        b = Fronts(tmp_path / "again", pg_url, nodes.address, stack).start()
        assert_same(pg_url, b, "f", probe)
        with Client(b.url, retries=0) as c:
            assert any(x["batch"] == acked["batch"] for x in c.batches("f"))


def test_cluster_mode_on_sqlite_refuses_nodes_on_other_machines(tmp_path):
    """The shards of a cluster on SQLite read this machine's data directory: a node
    elsewhere is named at start (checked against Ray's own list of nodes)."""
    from types import SimpleNamespace

    from flatserve.service.cluster.ray_env import one_machine
    from flatserve.service.status import ShardUnavailableError

    def fake(nodes):
        return SimpleNamespace(util=SimpleNamespace(get_node_ip_address=lambda: "127.0.0.1"),
                               nodes=lambda: [{"Alive": alive, "NodeManagerAddress": ip}
                                              for ip, alive in nodes])

    settings = Settings(data_dir=tmp_path, ray="127.0.0.1:6379")
    one_machine(fake([("127.0.0.1", True), ("127.0.0.1", True), ("10.0.0.7", False)]), settings)
    with pytest.raises(ShardUnavailableError, match=r"nodes at 10\.0\.0\.7 are elsewhere.*"
                                                    "PostgreSQL"):
        one_machine(fake([("127.0.0.1", True), ("10.0.0.7", True)]), settings)
