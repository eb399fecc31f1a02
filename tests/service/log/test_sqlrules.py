"""The rulebook of the SQL backends (flatserve/service/log/sqlrules.py, sqlschema.py),
tested once over both: batch numbers, idempotency, deleting a field, pointing a
field at a snapshot, responses, and the schema each dialect gets."""
from __future__ import annotations

import numpy as np
import pytest

from flatserve.service.log import sqlschema
from flatserve.service import status as fe
from flatserve.service.log.rows import KeyTakenError
from flatserve.service.log.blobs import pack_arrays
from tests.harness.service import save_bytes

BASIS = {"Q": np.eye(3)[None].repeat(5, 0), "r": np.zeros((5, 3))}


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request, tmp_path):
    if request.param == "sqlite":
        from flatserve.service.log.storage import SQLiteBackend

        be = SQLiteBackend(tmp_path / "data")
    else:
        from flatserve.service.log.pgstorage import PostgresBackend

        be = PostgresBackend(request.getfixturevalue("pg_url"), tmp_dir=tmp_path)
    be.check()
    yield be
    be.close()


def add(be, fid, key=None, n=3):
    return be.add_batch(fid, idem_key=key, chash=f"h{key}", form="rays", nrows=n, blob=b"x" * n)


def test_batches_are_numbered_after_the_last_one_and_the_snapshot(backend):
    fid, p0 = backend.create_field("f", {"k": 1}, BASIS)
    other, _ = backend.create_field("g", {"k": 2}, BASIS)
    s1, p1 = add(backend, fid)
    s2, p2 = add(backend, fid)
    assert (s1, s2) == (1, 2) and p0 < p1 < p2
    assert add(backend, other)[0] == 1  # numbered per field
    # a snapshot said to hold batches 1..5: the next batch is 6, never a number again
    backend.write_snapshot(fid, 5, p2, save_bytes(b"snap"))
    assert add(backend, fid)[0] == 6
    assert [b.seq for b in backend.batches(fid)] == [1, 2, 6]
    assert [b.seq for b in backend.batches(fid, after_seq=1, upto_position=p2)] == [2]
    assert backend.batch_stats(fid) == (3, 9, 9, 6)
    kinds = [(e.kind, e.field_id, e.seq) for e in backend.read_log(0)]
    assert kinds == [("create", fid, 0), ("create", other, 0), ("batch", fid, 1),
                     ("batch", fid, 2), ("batch", other, 1), ("snapshot", fid, 5),
                     ("batch", fid, 6)]
    assert backend.head() == backend.read_log(0)[-1].position


def test_an_idempotency_key_is_stored_once_and_its_response_kept(backend):
    fid, _ = backend.create_field("f", {"k": 1}, BASIS)
    seq, pos = backend.add_batch(fid, idem_key="k1", chash="h", form="rays", nrows=3,
                                 blob=b"abc", result_fn=lambda s, p: {"batch": s, "at": p})
    head = backend.head()
    with pytest.raises(KeyTakenError) as ei:
        add(backend, fid, "k1")
    assert ei.value.existing.seq == seq and ei.value.existing.result == {"batch": seq, "at": pos}
    assert backend.head() == head and backend.batch_stats(fid)[0] == 1  # nothing stored
    assert backend.find_batch(fid, "k1").content_hash == "h"
    assert backend.find_batch(fid, "k2") is None
    other, _ = backend.create_field("g", {"k": 2}, BASIS)
    assert add(backend, other, "k1")[0] == 1  # keys are per field
    # responses: replace=False keeps what is stored; a deleted batch is a no-op
    s2, _ = add(backend, fid, "k2")
    assert backend.find_batch(fid, "k2").result is None
    backend.set_result(fid, s2, {"v": 1}, replace=False)
    backend.set_result(fid, s2, {"v": 2}, replace=False)
    assert backend.find_batch(fid, "k2").result == {"v": 1}
    backend.set_result(fid, s2, {"v": 3}, durable=True)
    assert backend.find_batch(fid, "k2").result == {"v": 3}
    backend.set_result(fid, 99, {"v": 4})
    assert [b.seq for b in backend.batches(fid)] == [1, 2]


def test_names_fields_and_deletes(backend):
    fid, _ = backend.create_field("f", {"k": 1, "nested": [1, 2]}, BASIS)
    with pytest.raises(fe.FieldExistsError):
        backend.create_field("f", {}, BASIS)
    row = backend.field(fid)
    assert (row.name, row.spec, row.snapshot_file, row.snapshot_seq) == \
        ("f", {"k": 1, "nested": [1, 2]}, None, 0)
    np.testing.assert_array_equal(row.basis["Q"], BASIS["Q"])
    seq, _ = backend.add_batch(fid, idem_key=None, chash="h", form="rays", nrows=2,
                               blob=pack_arrays({"values": np.arange(2.0)}))
    np.testing.assert_array_equal(backend.batch_arrays(fid, seq)["values"], [0.0, 1.0])
    backend.write_snapshot(fid, seq, 0, save_bytes(b"snap"))
    pos = backend.delete_field(fid)
    assert backend.head() == pos and backend.read_log(pos - 1)[-1].kind == "delete"
    for call in (lambda: backend.field(fid), lambda: backend.delete_field(fid),
                 lambda: add(backend, fid), lambda: backend.batch_arrays(fid, seq)):
        with pytest.raises(fe.FieldNotFoundError):
            call()
    assert backend.clean_orphans() == 0  # its snapshot went with it
    fid2, _ = backend.create_field("f", {}, BASIS)
    assert fid2 != fid and backend.state()[1][0].id == fid2  # ids are never reused


def test_a_field_points_at_its_newest_snapshot_and_only_at_stored_data(backend):
    fid, _ = backend.create_field("f", {"k": 1}, BASIS)
    _, pos = add(backend, fid)
    first = backend.write_snapshot(fid, 1, pos, save_bytes(b"one"))
    row = backend.field(fid)
    assert (row.snapshot_file, row.snapshot_seq, row.snapshot_position) == (first.file, 1, pos)
    assert backend.snapshot_bytes(row) == first.bytes == 3
    assert backend.load_snapshot(row, lambda p, _: p.read_bytes()) == b"one"
    _, pos2 = add(backend, fid)
    second = backend.write_snapshot(fid, 2, pos2, save_bytes(b"second"))
    row = backend.field(fid)
    assert (row.snapshot_file, row.snapshot_seq, row.snapshot_position) == (second.file, 2, pos2)
    assert backend.snapshot_bytes(first.file) == 0  # the replaced one is removed
    assert backend.read_log(0)[-1].kind == "snapshot" and backend.head() == second.position
    # a check that fails abandons the snapshot: nothing kept, the field unchanged
    with pytest.raises(RuntimeError, match="lost"):
        backend.write_snapshot(fid, 3, pos2, save_bytes(b"third"),
                               lambda: (_ for _ in ()).throw(RuntimeError("lease lost")))
    assert backend.field(fid).snapshot_file == second.file and backend.clean_orphans() == 0
    # data removed meanwhile (a clean-up under a lost lease) is never pointed at
    with pytest.raises(fe.StorageError):
        backend.write_snapshot(fid, 3, pos2, save_bytes(b"fourth"),
                               lambda: backend.clean_orphans())
    assert backend.field(fid).snapshot_file == second.file
    assert backend.load_snapshot(backend.field(fid), lambda p, _: p.read_bytes()) == b"second"
    backend.delete_field(fid)
    with pytest.raises(fe.FieldNotFoundError):
        backend.write_snapshot(fid, 1, pos, save_bytes(b"gone"))
    assert backend.clean_orphans() == 0


def test_the_schema_is_one_description_for_both_dialects():
    lite, pg = sqlschema.ddl("sqlite"), sqlschema.ddl("postgresql")
    tables = {t.name for t in sqlschema.TABLES if t.only is None}
    for ddl in (lite, pg):
        made = {s.split()[5] for s in ddl if s.startswith("CREATE TABLE")}
        assert tables <= made
    assert not any("snapshot_chunks" in s for s in lite)
    assert any("SET STORAGE EXTERNAL" in s for s in pg) and not any("bytea" in s for s in lite)
    assert sqlschema.has_column("batches", "result", "sqlite")
    assert not sqlschema.has_column("batches", "result", "postgresql")
    assert sqlschema.add_column("fields", "position", "sqlite") == \
        "ALTER TABLE fields ADD COLUMN position INTEGER NOT NULL DEFAULT 0"
    with pytest.raises(ValueError, match="unknown SQL dialect"):
        sqlschema.ddl("oracle")
