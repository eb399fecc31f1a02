"""The storage room's SQLite migrations: schema 2 as it was written (the history
a migration starts from; new databases are made from :mod:`.sqlschema`) and its
migration to schema 3, run by :class:`flatserve.service.log.storage.SQLiteBackend`
when it opens an older database.
"""
from __future__ import annotations

import logging
import sqlite3

from . import sqlschema

log = logging.getLogger("flatserve.service.log.storage")

#: Schema 2 as it was written (frozen).
SCHEMA_V2 = """
CREATE TABLE IF NOT EXISTS fields (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    name TEXT NOT NULL UNIQUE,
    spec TEXT NOT NULL,
    basis BLOB NOT NULL,
    created REAL NOT NULL,
    snapshot_file TEXT,
    snapshot_seq INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS batches (
    field_id INTEGER NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
    seq INTEGER NOT NULL,
    idem_key TEXT,
    content_hash TEXT NOT NULL,
    form TEXT NOT NULL,
    nrows INTEGER NOT NULL,
    arrays BLOB NOT NULL,
    result TEXT NOT NULL,
    created REAL NOT NULL,
    PRIMARY KEY (field_id, seq)
);
CREATE UNIQUE INDEX IF NOT EXISTS batches_idem ON batches(field_id, idem_key)
    WHERE idem_key IS NOT NULL;
-- responses written after their batch's commit (batches.result is then 'null'):
-- kept apart so that writing one does not rewrite the batch's arrays
CREATE TABLE IF NOT EXISTS batch_results (
    field_id INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    result TEXT NOT NULL,
    PRIMARY KEY (field_id, seq)
);
"""


def run_script(db: sqlite3.Connection, script) -> None:
    """Run statements (a script's text, or a list) one by one inside the caller's
    transaction (``executescript`` would commit it first)."""
    if isinstance(script, str):
        script = "\n".join(ln for ln in script.splitlines() if not ln.strip().startswith("--"))
        script = script.split(";")
    for sql in script:
        if sql.strip():
            db.execute(sql)


def migrate_v2(db: sqlite3.Connection, version: int) -> None:
    """Schema 2 -> 3 inside the caller's write transaction: the columns and tables
    schema 3 added (:data:`.sqlschema.SQLITE_V3_COLUMNS`, ``SQLITE_V3_TABLES``);
    the log is backfilled field by field (ids in creation order), each field's
    ``create`` then its batches in seq order; snapshots get the position of
    their last batch."""
    run_script(db, [sqlschema.add_column(t, c, "sqlite") for t, c in sqlschema.SQLITE_V3_COLUMNS])
    for name in sqlschema.SQLITE_V3_TABLES:
        run_script(db, sqlschema.create_table(sqlschema.table(name), "sqlite"))
    fields = db.execute("SELECT id, created, snapshot_seq FROM fields ORDER BY id").fetchall()
    nb = 0
    for fid, created, snap_seq in fields:
        pos = db.execute("INSERT INTO log(kind, field_id, committed) VALUES ('create', ?, ?)",
                         (fid, created)).lastrowid
        db.execute("UPDATE fields SET position=? WHERE id=?", (pos, fid))
        snap_pos = pos if snap_seq else 0
        for seq, nrows, bcreated in db.execute(
                "SELECT seq, nrows, created FROM batches WHERE field_id=? ORDER BY seq",
                (fid,)).fetchall():
            bpos = db.execute("INSERT INTO log(kind, field_id, seq, nrows, committed) VALUES "
                              "('batch', ?, ?, ?, ?)", (fid, seq, nrows, bcreated)).lastrowid
            db.execute("UPDATE batches SET position=? WHERE field_id=? AND seq=?",
                       (bpos, fid, seq))
            if seq <= snap_seq:
                snap_pos = bpos
            nb += 1
        db.execute("UPDATE fields SET snapshot_position=? WHERE id=?", (snap_pos, fid))
    log.info("database migrated to schema %d: log backfilled with %d field(s), %d batch(es)",
             version, len(fields), nb)
