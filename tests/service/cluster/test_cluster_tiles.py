"""Tiles of a chart in Ray actors of their own (flatserve/service/cluster/worker/tiles.py), on a
REAL multi-node Ray cluster on loopback (tests/harness/raycluster.py).

The oracle is the unsplit triangulation in this process: the tiled triangulation whose
tiles live in actors must answer its bits (values, sample ids, weights), across
batches that cross tile borders, after a snapshot is loaded into new actors, and
after a re-cut of the tiles. The end-to-end path (a front, a shard group holding a
one-chart field of 2 tiles, PostgreSQL) is tests/service/cluster/test_cluster.py's.
"""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from flatserve.contract import part_key
from flatserve.errors import SnapshotError
from flatserve.service.log.backend import open_backend
from flatserve.service.cluster.worker.tiles import RayTileHost, TileParts
from flatserve.service.settings import Settings
from flatserve.service.status import ShardUnavailableError
from flatserve.tiles import TiledTriangulation, hosting
from flatserve.triangulation import Triangulation
from tests.harness.raycluster import RayNodes, assigned_resources


@pytest.fixture(scope="module")
def cluster():
    import ray

    with RayNodes(workers=2) as nodes:  # a head and two workers: 3 nodes
        ray.init(address=nodes.address, namespace="tiles-test", log_to_driver=False)
        try:
            yield nodes
        finally:
            ray.shutdown()


@pytest.fixture
def host(cluster):
    return RayTileHost(Settings(ray_shard_memory=256 << 20, shard_threads=1))


def _placed(host, n: int) -> list:
    """The host's tiles' places, asked again until all ``n`` answered in one round
    (a round leaves out tiles slower than its wait)."""
    for _ in range(20):
        got = host.placement()
        if len(got) >= n:
            return got
    return got


def _running(pid: int) -> bool:
    """The process is alive (the cluster's nodes are on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _same(tt: TiledTriangulation, tri: Triangulation, q) -> None:
    v0, in0, loc0 = tri.query(q, locate=True)
    v1, in1, loc1 = tt.query(q, locate=True)
    np.testing.assert_array_equal(in0, in1)
    np.testing.assert_array_equal(v0, v1)  # bits, NaN outside
    # the cell and its weights, vertex by vertex (the tile's vertex order may differ)
    for r in np.flatnonzero(in0):
        a, b = np.argsort(loc0.ids[r]), np.argsort(loc1.ids[r])
        np.testing.assert_array_equal(loc0.ids[r][a], loc1.ids[r][b])
        np.testing.assert_array_equal(loc0.weights[r][a], loc1.weights[r][b])


def test_tiles_in_actors_on_different_nodes_answer_the_unsplit_bits(host, rng):
    D = 4
    tri = Triangulation(D)
    with hosting(host):
        tt = TiledTriangulation(D, tiles=3)
    pts = rng.normal(size=(6000, D))
    vals = rng.uniform(size=(6000, 2))
    for lo in range(0, 6000, 1500):  # batches over every tile
        a = tri.insert(pts[lo:lo + 1500], vals[lo:lo + 1500])
        b = tt.insert(pts[lo:lo + 1500], vals[lo:lo + 1500])
        np.testing.assert_array_equal(a.ids, b.ids)
    # a batch far off one side: crosses the borders and grows the boxes
    far = rng.normal(size=(800, D)) + np.array([3.0, 0, 0, 0])
    tri.insert(far, rng.uniform(size=(800, 2)) + 5)
    tt.insert(far, tri.values[-800:])
    # duplicates with new values land on their ids, in every tile holding them
    dup = rng.choice(6000, 300, replace=False)
    nv = rng.uniform(size=(300, 2)) - 3
    tri.insert(pts[dup], nv)
    tt.insert(pts[dup], nv)
    q = rng.normal(size=(3000, D)) * 1.2
    _same(tt, tri, q)
    assert tt.halo.min() > 0 and tt.nsimplex == tri.nsimplex
    # the exchange's bytes: every point sent was fetched from its owner's actor and sent
    # to the receiver's (its D coordinates and 2 values, 8 bytes each), beside the scans
    assert tt.stats.sent > 0 and sum(tt.stats.rounds) > 0
    assert host.exchanged >= 2 * tt.stats.sent * (D + 2) * 8
    # each tile in an actor of its own, spread over the nodes
    where = _placed(host, 3)
    assert len(where) == 3 and sum(w["npoints"] for w in where) == tt.npoints + tt.halo.sum()
    assert len({w["node"] for w in where}) >= 2
    # a snapshot's tiles loaded into new actors answer the same bits
    with hosting(host):
        back = TiledTriangulation.from_bytes(tt.to_bytes(), D, tt.tiling_dict())
    assert len(_placed(host, 6)) == 6
    _same(back, tri, q)
    np.testing.assert_array_equal(back.points, tri.points)
    np.testing.assert_array_equal(back.values, tri.values)


def test_auto_a_tile_per_target_samples_cut_again_in_new_actors(cluster, rng):
    host = RayTileHost(Settings(ray_shard_memory=256 << 20, shard_threads=1,
                                ray_tile_samples=6_000))
    D = 3
    tri = Triangulation(D)
    with hosting(host):
        tt = TiledTriangulation(D, tiles="auto")
    pts = rng.uniform(size=(30_000, D))
    vals = pts[:, :1] ** 2
    counts, pids = [], set()
    for lo in range(0, 30_000, 5_000):
        tri.insert(pts[lo:lo + 5_000], vals[lo:lo + 5_000])
        tt.insert(pts[lo:lo + 5_000], vals[lo:lo + 5_000])
        counts.append(tt.ntiles)
        tt.settle()
        pids |= {w["pid"] for w in _placed(host, tt.ntiles)}
    # one tile up to the target, then cut again as the count doubles (1, 2, 4) or the
    # points do: never more tiles than one per target's samples
    assert counts == [1, 2, 2, 4, 4, 4], counts
    assert tt.stats.retiled == 2
    last = {w["pid"] for w in _placed(host, 4)}
    assert len(last) == 4 and len(pids) == 1 + 2 + 4
    # the tiles of earlier cuts ended with them (their processes, not only handles)
    end = time.monotonic() + 30
    while any(_running(p) for p in pids - last) and time.monotonic() < end:
        time.sleep(0.2)
    assert not any(_running(p) for p in pids - last)
    assert all(_running(p) for p in last)
    _same(tt, tri, rng.uniform(size=(2000, D)))


def test_a_damaged_tile_part_is_an_error_of_the_load_not_a_lost_tile(host, rng):
    with hosting(host):
        tt = TiledTriangulation(3, tiles=2)
    tt.insert(rng.uniform(size=(2000, 3)), rng.uniform(size=(2000, 1)), settle=True)
    parts = [bytearray(blob) for _, blob in tt.tile_parts()]
    n = int(np.frombuffer(bytes(parts[1][:8]), np.uint64)[0])
    at = 8 + 9 * n + 8  # tile 1's triangulation snapshot: its magic damaged
    parts[1][at:at + 8] = b"\xff" * 8
    stored = {part_key(bytes(p)): bytes(p) for p in parts}  # (keys of the damaged bytes)
    with hosting(host), pytest.raises(ValueError, match="snapshot|magic|truncated") as err:
        TiledTriangulation.from_parts(stored.__getitem__, list(stored), 3, tt.tiling_dict())
    assert not isinstance(err.value, ShardUnavailableError), err.value
    assert host.lost is None  # the caller replays the log instead: no restart loop


def test_each_tile_stores_and_reads_its_own_part_in_the_fields_storage(cluster, tmp_path, rng):
    """With the field's storage (TileParts), a snapshot's tile parts are stored by the
    tiles' actors and a restore's are read by the new actors: this process never
    holds their bytes (its ``parts`` is never called), and a part damaged in the
    storage is the load's error, not a lost tile."""
    settings = Settings(ray_shard_memory=256 << 20, shard_threads=1, data_dir=tmp_path)
    open_backend(settings).close()  # the data directory (a server's), then the tiles'
    host = RayTileHost(settings, TileParts(settings, 7))
    D = 3
    tri = Triangulation(D)
    with hosting(host):
        tt = TiledTriangulation(D, tiles=2)
    pts, vals = rng.uniform(size=(4000, D)), rng.uniform(size=(4000, 2))
    tri.insert(pts, vals)
    tt.insert(pts, vals, settle=True)
    got = tt.tile_parts()
    keys = [k for k, _ in got]
    assert all(blob is None for _, blob in got) and host.stored > 0
    store = open_backend(settings, follower=True)
    assert store.snapshot_parts(7) == set(keys)
    assert host.stored == sum(len(store.read_part(7, k)) for k in keys)
    stored = host.stored
    assert tt.tile_parts(known=keys) == got  # unchanged: not serialised again
    # a tile whose part is known is not stored again by its actor either
    assert host.part(tt.tiles[0], tt.global_ids(0), {keys[0]}) == (keys[0], None)
    assert host.stored == stored

    def here(key):
        raise AssertionError(f"part {key} read by the group's process")

    with hosting(host):
        back = TiledTriangulation.from_parts(here, keys, D, tt.tiling_dict())
    _same(back, tri, rng.uniform(size=(1000, D)))
    np.testing.assert_array_equal(back.points, tri.points)
    # a part damaged where it is stored: the load's error, named; the tile not lost
    path = store.part_path(7, keys[1])
    path.write_bytes(path.read_bytes()[:-10] + b"x" * 10)
    with hosting(host), pytest.raises(SnapshotError, match="tile 1.*damaged"):
        TiledTriangulation.from_parts(here, keys, D, tt.tiling_dict(), source="snap")
    path.unlink()
    with hosting(host), pytest.raises(SnapshotError, match="missing"):
        TiledTriangulation.from_parts(here, keys, D, tt.tiling_dict())
    assert host.lost is None


def test_a_lost_tile_is_a_503_and_marks_the_host(host, rng):
    import ray

    with hosting(host):
        tt = TiledTriangulation(3, tiles=2)
    tt.insert(rng.uniform(size=(2000, 3)), rng.uniform(size=(2000, 1)), settle=True)
    actor = tt.tiles[1].actor
    ray.kill(actor)
    # ray.kill returns before the actor is gone: a call made at once may still be
    # answered (seen under load); wait until its calls fail
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            ray.get(actor.state.remote(), timeout=5)
        except ray.exceptions.RayActorError:
            break
        except ray.exceptions.GetTimeoutError:
            pass
        time.sleep(0.1)
    else:
        pytest.fail("the killed tile actor still answers after 60 s")
    with pytest.raises(ShardUnavailableError, match="lost"):
        tt.query(rng.uniform(size=(500, 3)))
    assert host.lost is not None


def test_on_sqlite_a_tile_stays_on_this_machines_nodes(cluster, rng):
    """Cluster mode on SQLite (no database_url): each tile's actor holds a share of its
    machine's ``node:<address>`` resource (which Ray gives only the nodes of that
    address), so that a node joining later from another machine, which cannot read
    this machine's data directory, is given none; with a database, no such share."""
    import ray

    from flatserve.service.cluster.ray_env import PIN_SHARE

    key = f"node:{ray.util.get_node_ip_address()}"
    for url, share in ((None, PIN_SHARE), ("postgresql://flatserve@127.0.0.1:9/none", None)):
        host = RayTileHost(Settings(ray_shard_memory=256 << 20, shard_threads=1,
                                    database_url=url))
        with hosting(host):
            tt = TiledTriangulation(3, tiles=2)
        tt.insert(rng.uniform(size=(2000, 3)), rng.uniform(size=(2000, 1)), settle=True)
        actors = [t.actor for t in tt.tiles if t.actor is not None]
        assert len(actors) == 2
        for a in actors:
            got = assigned_resources(a)
            assert got.get(key) == share, (url, got)
            assert got.get("memory") == 256 << 20, got


def test_a_tile_no_node_has_room_for_is_lost_in_time_not_waited_for(cluster, rng):
    """A tile's actor asking for more memory than any node has is never placed: the
    insert that starts it fails within the start timeout (naming the setting) and
    marks the host lost (its group restarts to try again), where its call would
    have waited TILE_CALL_TIMEOUT_S (30 min) for room."""
    host = RayTileHost(Settings(ray_shard_memory=64 << 30, shard_threads=1), start_timeout=5.0)
    with hosting(host):
        tt = TiledTriangulation(3, tiles=2)
    t0 = time.monotonic()
    with pytest.raises(ShardUnavailableError, match=r"not placed within 5 s.*"
                                                    r"68719476736 bytes.*ray_shard_memory"):
        tt.insert(rng.uniform(size=(500, 3)), rng.uniform(size=(500, 1)))
    assert time.monotonic() - t0 < 60
    assert host.lost is not None and "not placed" in host.lost


def test_a_tile_waiting_for_memory_some_node_has_starts_once_it_is_freed(cluster):
    """Every node's memory taken by other tiles: a new tile's actor that a node could
    hold once freed is waited for past the start timeout (not lost), and starts
    when a blocker ends."""
    import threading

    import ray

    big = Settings(ray_shard_memory=3 << 30, shard_threads=1)  # one a node (4 GiB each)
    blockers = [RayTileHost(big).spawn(3) for _ in range(3)]
    host = RayTileHost(big, start_timeout=2.0)
    got: dict = {}
    t = threading.Thread(target=lambda: got.update(actor=host.spawn(3)))
    t0 = time.monotonic()
    t.start()
    t.join(8.0)
    assert t.is_alive() and host.lost is None  # past its start timeout, still waited for
    ray.kill(blockers[0])
    t.join(120)
    assert not t.is_alive() and host.lost is None and got["actor"] is not None
    assert time.monotonic() - t0 > 8.0
    for a in (*blockers[1:], got["actor"]):
        ray.kill(a)
