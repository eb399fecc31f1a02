"""The storage room's schema, described once: the tables of the SQL backends
(:mod:`.storage`, SQLite; :mod:`.pgstorage`, PostgreSQL) and the DDL of each
dialect made from that description.

A :class:`Table` lists its columns by *kind* (``int``, ``text``, ``blob``...),
one line each;
:data:`TYPES` says what each kind is called in each dialect. A table or column
marked ``only=`` exists in one dialect: PostgreSQL keeps snapshots as rows
(``snapshots``, ``snapshot_chunks``) and its schema version in ``meta``;
SQLite keeps snapshots as files, its version in ``PRAGMA user_version`` and the
``batches.result`` column of its schema 2 (responses are in ``batch_results``
since; the column is read as a fallback and written as ``'null'``).

The SQLite migration from schema 2 adds the columns and tables listed in
:data:`SQLITE_V3_COLUMNS` and :data:`SQLITE_V3_TABLES`, made by
:func:`add_column` and :func:`create_table` from this same description.
"""
from __future__ import annotations

from dataclasses import dataclass

#: The column kinds, by dialect.
TYPES: dict[str, dict[str, str]] = {
    "sqlite": {
        "id": "INTEGER PRIMARY KEY AUTOINCREMENT",   # fields.id: never reused
        "position": "INTEGER PRIMARY KEY AUTOINCREMENT",  # drawn in the write transaction
        "int": "INTEGER", "int4": "INTEGER", "real": "REAL", "text": "TEXT", "blob": "BLOB",
        "deadline": "REAL",                            # unix time
    },
    "postgresql": {
        "id": "bigserial PRIMARY KEY",
        "position": "bigint PRIMARY KEY",              # drawn from the log_position sequence
        "int": "bigint", "int4": "integer", "real": "double precision", "text": "text",
        "blob": "bytea", "deadline": "timestamptz",
    },
}


@dataclass(frozen=True)
class Column:
    """One column: its name, kind (a key of :data:`TYPES`) and constraints.

    ``external``: PostgreSQL stores it out of line uncompressed (float arrays
    hardly compress: no pglz pass). ``only``: the one dialect that has it.
    """

    name: str
    kind: str
    extra: str = ""
    external: bool = False
    only: str | None = None


@dataclass(frozen=True)
class Table:
    """One table: columns, table constraints, and the dialect it is ``only`` in."""

    name: str
    columns: tuple[Column, ...]
    constraints: tuple[str, ...] = ()
    only: str | None = None
    #: constraints of one dialect: (dialect, constraint)
    dialect_constraints: tuple[tuple[str, str], ...] = ()

    def column(self, name: str) -> Column:
        for c in self.columns:
            if c.name == name:
                return c
        raise KeyError(f"{self.name} has no column {name!r}")


def _table(name: str, columns: str, *constraints: str, only: str | None = None,
           dialect_constraints: tuple[tuple[str, str], ...] = ()) -> Table:
    """A :class:`Table` from one line per column: ``name kind [constraints]``,
    ending in ``+external`` (:attr:`Column.external`) or ``@dialect``
    (:attr:`Column.only`)."""
    cols = []
    for line in columns.strip().splitlines():
        words = line.split()
        col_only = words.pop()[1:] if words[-1].startswith("@") else None
        external = words[-1] == "+external"
        if external:
            words.pop()
        cols.append(Column(words[0], words[1], " ".join(words[2:]), external, col_only))
    return Table(name, tuple(cols), constraints, only, dialect_constraints)


TABLES: tuple[Table, ...] = (
    _table("meta", """
        key                text PRIMARY KEY
        value              text NOT NULL
    """, only="postgresql"),
    _table("fields", """
        id                 id
        name               text NOT NULL UNIQUE
        spec               text NOT NULL
        basis              blob NOT NULL
        created            real NOT NULL
        position           int NOT NULL DEFAULT 0
        snapshot_file      text
        snapshot_seq       int NOT NULL DEFAULT 0
        snapshot_position  int NOT NULL DEFAULT 0
    """),
    _table("batches", """
        field_id           int NOT NULL REFERENCES fields(id) ON DELETE CASCADE
        seq                int NOT NULL
        position           int NOT NULL DEFAULT 0
        idem_key           text
        content_hash       text NOT NULL
        form               text NOT NULL
        nrows              int NOT NULL
        arrays             blob NOT NULL +external
        result             text NOT NULL @sqlite
        created            real NOT NULL
    """, "PRIMARY KEY (field_id, seq)"),
    # batches.result: schema 2's responses (SQLite); since, responses are kept
    # apart, so that writing one does not rewrite the batch's arrays
    _table("batch_results", """
        field_id           int NOT NULL
        seq                int NOT NULL
        result             text NOT NULL
    """, "PRIMARY KEY (field_id, seq)", dialect_constraints=(
        ("postgresql", "FOREIGN KEY (field_id, seq) REFERENCES batches(field_id, seq) "
                       "ON DELETE CASCADE"),)),
    # the log of field operations; no foreign key: a delete outlives its field
    _table("log", """
        position           position
        kind               text NOT NULL
        field_id           int NOT NULL
        seq                int NOT NULL DEFAULT 0
        nrows              int NOT NULL DEFAULT 0
        committed          real NOT NULL
    """),
    _table("snapshots", """
        name               text PRIMARY KEY
        field_id           int NOT NULL
        bytes              int NOT NULL
        created            real NOT NULL
    """, only="postgresql"),
    _table("snapshot_chunks", """
        name               text NOT NULL REFERENCES snapshots(name) ON DELETE CASCADE
        idx                int4 NOT NULL
        data               blob NOT NULL +external
    """, "PRIMARY KEY (name, idx)", only="postgresql"),
    _table("leases", """
        name               text PRIMARY KEY
        owner              text NOT NULL
        expires            deadline NOT NULL
    """),
)

#: Indexes of every dialect (after the tables).
INDEXES: tuple[str, ...] = (
    "CREATE UNIQUE INDEX IF NOT EXISTS batches_idem ON batches(field_id, idem_key)"
    " WHERE idem_key IS NOT NULL",
)

#: What SQLite's schema 3 added to schema 2: columns (table, column) and tables.
SQLITE_V3_COLUMNS: tuple[tuple[str, str], ...] = (
    ("fields", "position"), ("fields", "snapshot_position"), ("batches", "position"))
SQLITE_V3_TABLES: tuple[str, ...] = ("log", "leases")


def table(name: str) -> Table:
    """The table ``name`` of :data:`TABLES`."""
    for t in TABLES:
        if t.name == name:
            return t
    raise KeyError(f"no table {name!r}")


def has_column(table_name: str, column: str, dialect: str) -> bool:
    """Whether the dialect's ``table_name`` has ``column``."""
    try:
        c = table(table_name).column(column)
    except KeyError:
        return False
    return c.only in (None, dialect)


def _column_sql(c: Column, dialect: str) -> str:
    return " ".join(p for p in (c.name, TYPES[dialect][c.kind], c.extra) if p)


def create_table(t: Table, dialect: str) -> list[str]:
    """``CREATE TABLE IF NOT EXISTS`` of ``t`` in ``dialect`` (and, in
    PostgreSQL, the storage of its ``external`` columns)."""
    cols = [_column_sql(c, dialect) for c in t.columns if c.only in (None, dialect)]
    cols += list(t.constraints) + [s for d, s in t.dialect_constraints if d == dialect]
    body = ",\n    ".join(cols)
    out = [f"CREATE TABLE IF NOT EXISTS {t.name} (\n    {body}\n)"]
    if dialect == "postgresql":
        out += [f"ALTER TABLE {t.name} ALTER COLUMN {c.name} SET STORAGE EXTERNAL"
                for c in t.columns if c.external]
    return out


def add_column(table_name: str, column: str, dialect: str) -> str:
    """``ALTER TABLE ... ADD COLUMN`` of one described column (migrations)."""
    return f"ALTER TABLE {table_name} ADD COLUMN " + _column_sql(
        table(table_name).column(column), dialect)


def ddl(dialect: str) -> list[str]:
    """Every statement that creates the dialect's schema on an empty database
    (idempotent: ``IF NOT EXISTS``)."""
    if dialect not in TYPES:
        raise ValueError(f"unknown SQL dialect {dialect!r} (known: {', '.join(TYPES)})")
    out: list[str] = []
    if dialect == "postgresql":
        out.append("CREATE SEQUENCE IF NOT EXISTS log_position")
    for t in TABLES:
        if t.only in (None, dialect):
            out += create_table(t, dialect)
    return out + list(INDEXES)
