"""AtlasField.write_parts / from_bytes(parts=): snapshots that write only the
charts that changed, and read back to the same field."""
from __future__ import annotations

import io
import os

import numpy as np
import pytest

from flatserve import Flats
from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.contract import load_field
from flatserve.errors import SnapshotError
from flatserve.field import Field
from tests.harness.charts import rays_in_one_chart


def _rays(rng, n):
    return Flats.from_rays(rng.uniform(-1, 1, (n, 3)), rng.standard_normal((n, 3)))


@pytest.fixture
def field():
    rng = np.random.default_rng(3)
    f = AtlasField(Atlas.covering(1, 3, oriented=True), channels=2)
    rays = _rays(rng, 6000)
    f.add(rays, rng.uniform(size=(rays.n, 2)))
    return f


def _store(stage):
    """The parts written to ``stage`` so far, by key."""
    return {p.name: p.read_bytes() for p in stage.iterdir()}


def test_parts_round_trip_to_the_same_field(field, tmp_path):
    buf = io.BytesIO()
    keys = field.write_parts(buf, tmp_path)
    assert len(keys) == field.atlas.ncharts and sorted(set(keys)) == sorted(_store(tmp_path))
    head = buf.getvalue()
    assert len(head) < len(field.to_bytes()) / 20  # it names the parts; the charts are apart
    store = _store(tmp_path)
    back = AtlasField.from_bytes(head, parts=store.__getitem__)
    assert back.to_bytes() == field.to_bytes()
    q = _rays(np.random.default_rng(4), 2000)
    a, b = back.query(q, return_weights=True), field.query(q, return_weights=True)
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.weights, b.weights)
    # through the contract's reader, by magic
    path = tmp_path.parent / "field.fs"
    path.write_bytes(head)
    assert load_field(path, parts=store.__getitem__).to_bytes() == field.to_bytes()


def test_a_batch_in_one_chart_writes_one_part(field, tmp_path):
    first = tmp_path / "1"
    first.mkdir()
    keys1 = field.write_parts(io.BytesIO(), first)
    chart = 5
    rng = np.random.default_rng(8)
    rays = Flats.from_rays(*rays_in_one_chart(field, rng, chart, 300))
    field.add(rays, rng.uniform(size=(rays.n, 2)))
    second = tmp_path / "2"
    second.mkdir()
    calls = []
    real = Field.to_bytes

    def counting(self):
        calls.append(self)
        return real(self)

    Field.to_bytes = counting
    try:
        keys2 = field.write_parts(io.BytesIO(), second, known=set(keys1))
    finally:
        Field.to_bytes = real
    changed = [c for c, (a, b) in enumerate(zip(keys1, keys2)) if a != b]
    assert changed == [chart]
    assert sorted(_store(second)) == [keys2[chart]]  # one part written
    assert calls == [field.fields[chart]]  # and only that chart serialised
    # the new snapshot reads back whole from the old parts plus the new one
    store = {**_store(first), **_store(second)}
    buf = io.BytesIO()
    field.write_parts(buf, second, known=set(store))
    assert AtlasField.from_bytes(buf.getvalue(), parts=store.__getitem__).to_bytes() \
        == field.to_bytes()


def test_a_restored_field_writes_no_part_until_it_changes(field, tmp_path):
    buf = io.BytesIO()
    keys = field.write_parts(buf, tmp_path)
    store = _store(tmp_path)
    back = AtlasField.from_bytes(buf.getvalue(), parts=store.__getitem__)
    again = tmp_path / "again"
    again.mkdir()
    assert back.write_parts(io.BytesIO(), again, known=set(keys)) == keys
    assert not os.listdir(again)


def test_a_part_the_store_lost_is_written_again(field, tmp_path):
    keys = field.write_parts(io.BytesIO(), tmp_path)
    again = tmp_path / "again"
    again.mkdir()
    lost = keys[2]
    field.write_parts(io.BytesIO(), again, known=set(keys) - {lost})
    assert sorted(_store(again)) == [lost]


def test_damaged_or_missing_parts_are_snapshot_errors(field, tmp_path):
    buf = io.BytesIO()
    keys = field.write_parts(buf, tmp_path)
    store = _store(tmp_path)
    store[keys[0]] = store[keys[0]][:-1] + bytes([store[keys[0]][-1] ^ 1])
    with pytest.raises(SnapshotError, match="chart 0: part .* is damaged"):
        AtlasField.from_bytes(buf.getvalue(), parts=store.__getitem__)
    with pytest.raises(SnapshotError, match="pass parts= to read them"):
        AtlasField.from_bytes(buf.getvalue())
    with pytest.raises(SnapshotError, match="bytes after the list of parts"):
        AtlasField.from_bytes(buf.getvalue() + b"x", parts=store.__getitem__)


def test_a_one_chart_field_writes_its_whole_file_and_no_parts(tmp_path):
    from flatserve.service.rooms import specs

    f = Field(specs.build_basis(None, 1, 3), channels=1)
    rng = np.random.default_rng(2)
    rays = _rays(rng, 500)
    f.add(rays, rng.uniform(size=(rays.n, 1)))
    buf = io.BytesIO()
    assert f.write_parts(buf, tmp_path) == []
    assert buf.getvalue() == f.to_bytes() and not os.listdir(tmp_path)


# ---- a shard's half: some charts prepared, inserted, queried, snapshotted and restored
# elsewhere, bit for bit those of the whole field ----------------------------------------

def _split(atlas, groups, batches, slice_rows=700):
    """One field holding everything, and one field per group of charts fed the same
    batches with ``prepare(only=group)``."""
    whole = AtlasField(atlas, channels=2)
    parts = [AtlasField(atlas, channels=2) for _ in groups]
    for rays, values in batches:
        whole.insert_prepared(whole.prepare(rays, values), slice_rows=slice_rows)
        for g, f in zip(groups, parts):
            f.insert_prepared(f.prepare(rays, values, only=g), slice_rows=slice_rows)
    return whole, parts


def test_charts_fed_on_their_own_hold_the_same_bits_as_the_whole_field():
    rng = np.random.default_rng(11)
    atlas = Atlas.covering(1, 3, oriented=True)
    groups = [set(range(g, atlas.ncharts, 3)) for g in range(3)]
    batches = [(_rays(rng, n), rng.uniform(size=(n, 2))) for n in (1500, 2500, 900)]
    whole, parts = _split(atlas, groups, batches)
    for g, f in zip(groups, parts):
        for c in range(atlas.ncharts):
            if c in g:
                assert f.shards[c].to_bytes() == whole.shards[c].to_bytes(), c
            else:
                assert f.shards[c].nsamples == 0
    # each sample counted once, in its nearest chart: the groups' own samples add up
    assert sum(sum(f.own_samples[c] for c in g) for g, f in zip(groups, parts)) == whole.nsamples
    # the query's halves: route and blend here, each group's charts there
    q = _rays(rng, 3000)
    route = whole.route_query(q)
    results = [None] * atlas.ncharts
    for g, f in zip(groups, parts):
        work = [(c, q.take(route.rows[c])) for c in sorted(g) if route.rows[c].size]
        for (c, _), res in zip(work, f.query_shards(work, return_weights=True)):
            results[c] = res
    got = whole.blend(route, results, return_weights=True)
    want = whole.query(q, return_weights=True)
    np.testing.assert_array_equal(got.values, want.values)
    np.testing.assert_array_equal(got.weights, want.weights)
    np.testing.assert_array_equal(got.inside, want.inside)


def test_a_snapshot_assembled_from_parts_made_elsewhere_restores_each_group(tmp_path):
    rng = np.random.default_rng(12)
    atlas = Atlas.covering(1, 3)
    groups = [set(range(0, atlas.ncharts, 2)), set(range(1, atlas.ncharts, 2))]
    whole, parts = _split(atlas, groups, [(_rays(rng, 3000), rng.uniform(size=(3000, 2)))])
    keys, own, store = [None] * atlas.ncharts, [None] * atlas.ncharts, {}
    for g, f in zip(groups, parts):
        for c, key, blob in f.chart_parts(sorted(g)):
            keys[c], own[c], store[key] = key, f.own_samples[c], blob
        # known parts are named, not sent again
        assert all(b is None for _, _, b in f.chart_parts(sorted(g), known=store))
    head = whole.parts_header(keys, own=own, nrejected=whole.nrejected)
    back = AtlasField.from_bytes(head, parts=store.__getitem__)
    assert back.to_bytes() == whole.to_bytes()
    for g in groups:  # a group restores its own charts only, and its own samples
        mine = AtlasField.from_bytes(head, parts=store.__getitem__, only=g)
        assert mine.nsamples == sum(own[c] for c in g)
        for c in range(atlas.ncharts):
            assert (mine.shards[c].to_bytes() == whole.shards[c].to_bytes()) == (
                c in g or whole.shards[c].nsamples == 0)
    with pytest.raises(Exception, match="only"):
        whole.prepare(_rays(rng, 5), np.zeros((5, 2)), only={atlas.ncharts})
