"""Checks shared by the tests of both storage backends (SQLite and PostgreSQL):
each runs on an open backend and asserts what either must do."""
from __future__ import annotations

import numpy as np
import pytest

from flatserve.service.log.backend import snapshot_lease
from flatserve.service.status import StorageError
from tests.harness.service import save_bytes


def check_clean_up_under_field_leases(be):
    """Each field's snapshot lease is its own, and ``clean_orphans`` removes a live
    field's data not pointed at only under that field's lease: a writer holding it
    keeps what it stored (the field points at it), while a field nobody holds the
    lease of loses it (a dead writer's).

    Parameters
    ----------
    be
        An open backend (:class:`~flatserve.service.log.storage.SQLiteBackend` or
        :class:`~flatserve.service.log.pgstorage.PostgresBackend`) with no field named
        "held" or "free".
    """
    basis = {"Q": np.eye(3)[None].repeat(5, 0), "r": np.zeros((5, 3))}
    held, free = (be.create_field(n, {"k": 1}, basis)[0] for n in ("held", "free"))
    assert be.acquire_lease(snapshot_lease(held), "writer", 300)
    assert be.acquire_lease(snapshot_lease(free), "another", 300)  # independent leases
    assert not be.acquire_lease(snapshot_lease(held), "another", 300)
    be.release_lease(snapshot_lease(free), "another")
    assert be.renew_lease(snapshot_lease(held), "writer", 300)  # untouched by the release
    info = be.write_snapshot(held, 0, 0, save_bytes(b"kept"), be.clean_orphans)
    assert be.field(held).snapshot_file == info.file
    assert be.load_snapshot(be.field(held), lambda p, _: p.read_bytes()) == b"kept"
    with pytest.raises(StorageError):
        be.write_snapshot(free, 0, 0, save_bytes(b"a dead writer's"), be.clean_orphans)
    assert be.field(free).snapshot_file is None
    be.release_lease(snapshot_lease(held), "writer")
    assert be.clean_orphans() == 0
