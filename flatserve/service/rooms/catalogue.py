"""The field catalogue: this replica's fields by name and by id, and their states.

One room with one job: which fields exist here and in what state. It holds
the entries (:class:`.entry.FieldEntry`) and nothing else: no storage, no
log. The log applier (:mod:`.applier`) puts and removes entries as it applies
creates and deletes; every other room looks fields up here.

Example
-------
>>> cat = FieldCatalogue()
>>> cat.ready.set()
>>> cat.names()
[]
"""
from __future__ import annotations

import threading
from contextlib import contextmanager
from enum import Enum
from typing import Iterator

from ..status import FieldExistsError, FieldNotFoundError, NotReadyError, StorageError, \
    TooManyFieldsError


class FieldState(str, Enum):
    """The life of a field on this replica."""

    #: being restored (or rebuilt): requests get 503 until it is ready
    LOADING = "loading"
    #: answers queries and takes uploads
    READY = "ready"
    #: could not be restored, or a log entry could not be applied: 503 naming why
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value


class FieldCatalogue:
    """Names -> entries of this replica's fields (thread-safe).

    Attributes
    ----------
    ready : threading.Event
        Set once the stored fields are registered and the log is followed;
        before it, a name not found is "still loading" (503), not 404.
    """

    def __init__(self) -> None:
        self._entries: dict = {}
        self._by_id: dict = {}
        #: names being created (their commit runs without holding ``_lock``)
        self._creating: set[str] = set()
        self._lock = threading.Lock()
        self.ready = threading.Event()

    # -- lookup -------------------------------------------------------------------------
    def entries(self) -> list:
        """Every entry (a copy of the list)."""
        with self._lock:
            return list(self._entries.values())

    def names(self) -> list[str]:
        with self._lock:
            return sorted(self._entries)

    def get(self, name: str, *, need_ready: bool = True):
        """The entry named ``name``.

        Raises
        ------
        FieldNotFoundError
            No such field (404); :class:`NotReadyError` instead while the stored
            fields are still being registered.
        NotReadyError
            ``need_ready`` and the field is loading (503).
        StorageError
            ``need_ready`` and the field failed (503 naming the error).
        """
        with self._lock:
            e = self._entries.get(name)
        if e is None:
            if not self.ready.is_set():
                raise NotReadyError("stored fields are still loading; retry shortly")
            raise FieldNotFoundError(f"no field named {name!r}")
        if need_ready and e.state is FieldState.LOADING:
            raise NotReadyError(f"field {name!r} is still loading; retry shortly")
        if need_ready and e.state is FieldState.FAILED:
            raise StorageError(f"field {name!r} could not be loaded: {e.error}")
        return e

    def by_id(self, field_id: int):
        """The entry of field ``field_id``, or None."""
        with self._lock:
            return self._by_id.get(field_id)

    def counts(self) -> dict[FieldState, list[str]]:
        """Names of the fields in each state."""
        out: dict[FieldState, list[str]] = {s: [] for s in FieldState}
        for e in self.entries():
            out[e.state].append(e.name)
        return out

    # -- changes (the log applier, and creates reserving a name) -----------------------
    @contextmanager
    def reserve(self, name: str, limit: int) -> Iterator[None]:
        """Hold ``name`` for a create while it commits (without the lock).

        Raises
        ------
        FieldExistsError
            The name is taken, or being created (409).
        TooManyFieldsError
            ``limit`` fields exist or are being created (409).
        """
        with self._lock:
            if name in self._entries or name in self._creating:
                raise FieldExistsError(f"field {name!r} already exists")
            if len(self._entries) + len(self._creating) >= limit:
                raise TooManyFieldsError(
                    f"this server holds {len(self._entries)} fields; the limit is {limit}")
            self._creating.add(name)
        try:
            yield
        finally:
            with self._lock:
                self._creating.discard(name)

    def put(self, e) -> None:
        """Register ``e`` (an older entry of the same name is marked deleted)."""
        with self._lock:
            old = self._entries.get(e.name)
            if old is not None and old.id != e.id:  # pragma: no cover - a delete skipped
                old.deleted = True
                self._by_id.pop(old.id, None)
            self._entries[e.name] = e
            self._by_id[e.id] = e

    def remove(self, field_id: int):
        """Unregister field ``field_id``; its entry, or None."""
        with self._lock:
            e = self._by_id.pop(field_id, None)
            if e is not None and self._entries.get(e.name) is e:
                del self._entries[e.name]
        return e
