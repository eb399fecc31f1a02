"""The field contract (flatserve/contract.py): both kinds offer it, with the same meaning.

Oracles: mypy on static assignments to the protocol (and on a class that
lacks a member, which must fail); the members' invariants on seeded random
batches (copies against the routing, describe's keys equal between kinds,
shard-by-shard round trips, an atlas field's answer rebuilt from its shards'
answers and its blend).
"""
from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from flatserve import Basis, Field, Flats
from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.contract import (SampledField, describe_definition, load_field, new_field, part_key,
                                part_pointer)
from flatserve.errors import InvalidInputError, SnapshotError
from flatserve.field import QueryResult


def rays(rng, n):
    return Flats.from_rays(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))


@pytest.fixture(scope="module")
def atlas():
    return Atlas.covering(1, 3, oriented=True)


@pytest.fixture(params=["field", "atlas"])
def kind(request, atlas):
    """An empty field of each kind (lines in R^3, 2 channels) and its samples' maker."""
    if request.param == "field":
        return new_field(2, basis=Basis.around_axis(axis=2, scale=0.01))
    return new_field(2, atlas=atlas)


def filled(field, seed=0, n=1500):
    rng = np.random.default_rng(seed)
    if field.blends:
        f = rays(rng, n)
    else:  # lines near the basis's axis, so that most round-trip
        o = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
        s = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
        f = Flats.from_rays(o, s - o)
    v = np.c_[f.arrays["origins"][:, 0], f.arrays["directions"][:, 1]]
    field.add(f, v)
    return f


def _mypy(tmp_path, source: str) -> subprocess.CompletedProcess:
    pytest.importorskip("mypy")
    path = tmp_path / "check.py"
    path.write_text(textwrap.dedent(source))
    return subprocess.run(
        [sys.executable, "-m", "mypy", "--follow-imports=silent", "--ignore-missing-imports",
         "--no-error-summary", "--cache-dir", str(tmp_path / "cache"), str(path)],
        capture_output=True, text=True, timeout=600)


def test_mypy_verifies_both_kinds_implement_the_protocol(tmp_path):
    got = _mypy(tmp_path, """
        from flatserve import Basis, Field
        from flatserve.atlas import Atlas
        from flatserve.atlas_field import AtlasField
        from flatserve.contract import SampledField, load_field, new_field
        from flatserve.service.cluster.front.remote import RemoteField

        one: SampledField = Field(Basis.around_axis())
        many: SampledField = AtlasField(Atlas.covering(1, 3))
        made: SampledField = new_field(1, basis=Basis.around_axis())
        read: SampledField = load_field("f.snap")


        def front(remote: RemoteField) -> None:  # a cluster front's field
            held: SampledField = remote


        class Incomplete:  # no copies, no shards, ...
            k = d = channels = ndim = 1


        wrong: SampledField = Incomplete()
        """)
    out = got.stdout + got.stderr
    errors = [line for line in out.splitlines() if ": error:" in line]
    # exactly one error: the incomplete class (so the check has teeth)
    assert len(errors) == 1 and "Incomplete" in errors[0], out


def test_runtime_protocol_and_blends(kind):
    assert isinstance(kind, SampledField)
    assert kind.blends is isinstance(kind, AtlasField)
    assert kind.k == 1 and kind.d == 3 and kind.channels == 2 and kind.ndim == 4


def test_sizes_and_describe_keys(kind):
    empty = kind.describe()
    assert empty["nsamples"] == 0 and empty["duplication"] is None
    filled(kind)
    d = kind.describe()
    assert set(d) == {"nsamples", "nstored", "nsimplex", "nrejected", "duplication", "shards",
                      "atlas", "charts"}
    assert d["nsamples"] == kind.nsamples > 0
    assert d["nstored"] == kind.nstored == sum(s.nsamples for s in kind.shards)
    assert d["nsimplex"] == kind.nsimplex == sum(s.nsimplex for s in kind.shards)
    assert d["nrejected"] == kind.nrejected
    assert d["shards"] == [{"samples": s.nsamples} for s in kind.shards]
    assert d["duplication"] == pytest.approx(kind.nstored / kind.nsamples)
    if kind.blends:
        assert kind.nstored > kind.nsamples and d["duplication"] > 1
        assert [c["samples"] for c in d["charts"]] == [s["samples"] for s in d["shards"]]
        assert {"method", "oriented", "inner", "trusted", "reach", "unit", "isometric",
                "info", "covering_radius", "max_sample_angle"} <= set(d["atlas"])
    else:
        assert kind.shards == (kind,) and kind.nstored == kind.nsamples
        assert d["duplication"] == 1.0 and d["atlas"] is None and d["charts"] is None


def test_describe_definition_is_describe_without_samples(atlas):
    field = AtlasField(atlas, channels=2)
    filled(field, seed=3, n=400)
    d = field.describe()
    static = describe_definition(field.atlas.to_dict())  # (its unit chosen by the first batch)
    assert set(static) == set(d)
    assert static["atlas"] == d["atlas"]
    assert [{**c, "samples": None} for c in d["charts"]] == static["charts"]
    assert static["shards"] == [{"samples": None}] * atlas.ncharts
    assert all(static[k] is None for k in ("nsamples", "nstored", "nsimplex", "nrejected",
                                           "duplication"))
    one = describe_definition(None)
    assert set(one) == set(d) and one["atlas"] is None and one["charts"] is None
    assert one["shards"] == [{"samples": None}] and one["nstored"] is None
    assert Field(Basis.around_axis()).describe()["charts"] is None


def test_copies_is_the_routing_average(kind):
    rng = np.random.default_rng(7)
    f = rays(rng, 800)
    routed = kind.route(f)
    assert len(routed) == len(kind.shards)
    assert kind.copies(f) == pytest.approx(sum(r.size for r in routed) / f.n)
    for r in routed:
        assert r.dtype == np.int64 and np.all(np.diff(r) > 0)
    if kind.blends:
        assert kind.copies(f) == float(kind.atlas.held(f, kind.atlas.reach).sum()) / f.n
        assert 1.0 <= kind.copies(f) < 3.0
        # a row's shards do not depend on its batch
        alone = kind.route(f.take(np.arange(5)))
        assert [r.tolist() for r in alone] == [r[r < 5].tolist() for r in routed]
    else:
        assert kind.copies(f) == 1.0


def test_query_is_the_blend_of_the_shards_answers(kind):
    filled(kind, seed=1)
    q = rays(np.random.default_rng(11), 300)
    route = kind.route_query(q)
    results = [s.query(q.take(rows), return_weights=True)
               if rows.size and s.nsamples else None
               for s, rows in zip(kind.shards, route.rows)]
    got = kind.blend(route, results, return_weights=True)
    want = kind.query(q, return_weights=True)
    for a, b in ((got.values, want.values), (got.inside, want.inside),
                 (got.status, want.status), (got.ids, want.ids), (got.weights, want.weights)):
        np.testing.assert_array_equal(a, b)
    assert isinstance(want, QueryResult)
    P = 3 if kind.blends else 2
    assert want.ids.ndim == P and want.weights.shape == want.ids.shape


def test_shard_round_trip_and_load_field_by_magic(kind, tmp_path):
    filled(kind, seed=2)
    q = rays(np.random.default_rng(4), 200)
    want = kind.query(q)
    for s in kind.shards:  # each shard's snapshot and restore on its own
        back = Field.from_bytes(s.to_bytes())
        assert back.nsamples == s.nsamples and back.nsimplex == s.nsimplex
        np.testing.assert_array_equal(back.points, s.points)
        np.testing.assert_array_equal(back.values, s.values)
    assert kind.to_bytes()[:8] == (b"FSATLAS\x00" if kind.blends else b"FSFIELD\x00")
    path = tmp_path / "f.snap"
    kind.save(path)
    assert path.read_bytes() == kind.to_bytes()
    back = load_field(path)
    assert type(back) is type(kind) and back.describe() == kind.describe()
    got = back.query(q)
    np.testing.assert_array_equal(got.values, want.values)
    np.testing.assert_array_equal(got.status, want.status)


def test_a_part_pointer_loads_the_part_it_names(kind, tmp_path):
    filled(kind, seed=3)
    q = rays(np.random.default_rng(5), 200)
    blob = kind.to_bytes()
    key = part_key(blob)
    path = tmp_path / "pointer"
    path.write_bytes(part_pointer(key))
    parts = {key: blob}
    back = load_field(path, parts.__getitem__)
    assert type(back) is type(kind) and back.describe() == kind.describe()
    np.testing.assert_array_equal(back.query(q).values, kind.query(q).values)
    with pytest.raises(SnapshotError, match="no parts were given"):
        load_field(path)
    with pytest.raises(SnapshotError, match="damaged"):  # the bytes must be the key's
        load_field(path, lambda k: blob[:-1] + b"x")
    with pytest.raises(InvalidInputError, match="key: expected 32 lowercase hex digits"):
        part_pointer("../etc/passwd")


def test_load_field_refuses_other_files(tmp_path):
    bad = tmp_path / "bad"
    bad.write_bytes(b"NOTAFIELD" + bytes(40))
    with pytest.raises(SnapshotError, match="bad magic"):
        load_field(bad)
    bad.write_bytes(b"FS")
    with pytest.raises(SnapshotError, match="truncated"):
        load_field(bad)
    good = tmp_path / "good"
    Field(Basis.around_axis()).save(good)
    data = good.read_bytes()
    good.write_bytes(data[:20])
    with pytest.raises(SnapshotError, match="truncated field metadata"):
        load_field(good)


def test_new_field_takes_exactly_one_definition(atlas):
    with pytest.raises(InvalidInputError):
        new_field(1)
    with pytest.raises(InvalidInputError):
        new_field(1, basis=Basis.around_axis(), atlas=atlas)
    from_dict = new_field(3, atlas=atlas.to_dict(), roundtrip_tol=1e-5)
    assert isinstance(from_dict, AtlasField) and from_dict.channels == 3
    assert from_dict.roundtrip_tol == 1e-5 and len(from_dict.shards) == atlas.ncharts
    one = new_field(1, basis=Basis.around_axis())
    assert isinstance(one, Field) and one.shards == (one,)


def test_prepare_defer_and_insert_per_kind(kind):
    rng = np.random.default_rng(9)
    f = rays(rng, 300)
    later = kind.prepare(f, rng.normal(size=(300, 2)), defer=True)
    assert callable(later)
    with pytest.raises(InvalidInputError, match="values"):
        kind.prepare(f, np.zeros((299, 2)), defer=True)
    batch = later()
    assert batch.nrows == 300 and batch.accepted + batch.rejected.size == 300
    assert len(batch.reasons) == batch.rejected.size
    res = kind.insert_prepared(batch, slice_rows=50)
    assert res.accepted == batch.accepted and res.nsamples == kind.nsamples
    with pytest.raises(InvalidInputError, match="slice_rows"):
        kind.insert_prepared(batch, slice_rows=0)


def test_capabilities_of_each_kind(kind):
    """Where the shards are, the counts and the unit of length: a real answer on both
    kinds (a one-chart field's neutral ones)."""
    import asyncio
    assert kind.holds_shards is True and kind.stored_bytes == 0
    assert kind.applied_counts(0, 0.0) == {}
    f = filled(kind, seed=5, n=400)
    assert sum(kind.own_samples) == kind.nsamples
    got = asyncio.run(kind.query_async(f.take(np.arange(20))))
    want = kind.query(f.take(np.arange(20)))
    np.testing.assert_array_equal(got.values, want.values)
    assert kind.unit_pending is False and kind.unit_from_data is False
    if kind.blends:
        assert kind.ntiles is None and kind.unit == kind.atlas.unit
    else:
        assert kind.ntiles == 1 and kind.unit is None and kind.own_samples == [kind.nsamples]
        assert kind.settle_unit(2.0) is False and kind.in_unit(2.0) is kind


def test_an_atlas_field_with_a_unit_from_its_data_has_none_until_its_first_batch():
    field = new_field(2, atlas=Atlas.covering(1, 3, oriented=True, unit=None))
    assert field.unit_pending and field.unit_from_data and field.unit is None
    filled(field, seed=6, n=300)
    assert not field.unit_pending and field.unit == field.atlas.unit
