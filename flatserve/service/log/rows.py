"""What the log's storage hands out: a stored field, a batch, a log entry, a
snapshot's description, and the two errors of its rules (a key already taken, a
snapshot gone). The interface that hands them out is :mod:`.backend`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FieldRow:
    """One stored field.

    Attributes
    ----------
    id : int
        Never reused (a field created again under a deleted name gets a new id).
    name : str
    spec : dict
        :meth:`flatserve.service.rooms.entry.FieldSpec.to_dict`, as given to
        :meth:`LogBackend.create_field`.
    basis : dict of str to ndarray
        ``{"Q": (m, d, d), "r": (m, d)}`` float64, as given.
    created : float
        Unix time of the creation.
    position : int
        Log position of the field's ``create`` entry.
    snapshot_file : str or None
        The newest snapshot's name (opaque to the caller: pass the row to
        :meth:`LogBackend.load_snapshot`); None: no snapshot.
    snapshot_seq : int
        The snapshot holds the field's batches ``1..snapshot_seq`` (0: none).
    snapshot_position : int
        Log position of the snapshot's last batch (0: none); every batch of the
        field after it has a larger position.
    """

    id: int
    name: str
    spec: dict
    basis: dict[str, np.ndarray]
    created: float
    position: int
    snapshot_file: str | None
    snapshot_seq: int
    snapshot_position: int


@dataclass(frozen=True)
class BatchRow:
    """One stored batch, without its arrays (:meth:`LogBackend.batch_arrays`).

    Attributes
    ----------
    seq : int
        The batch's number within its field (1, 2, ...).
    position : int
        Its log position.
    idem_key : str or None
    content_hash : str
        :func:`flatserve.service.log.blobs.content_hash` of its form and arrays.
    form : str
        ``rays``, ``parametric`` or ``flats``.
    nrows : int
    result : dict or None
        The response stored for it (:meth:`LogBackend.add_batch`'s
        ``result_fn``, or :meth:`LogBackend.set_result`); None if a crash lost
        a response written without fsync.
    """

    seq: int
    position: int
    idem_key: str | None
    content_hash: str
    form: str
    nrows: int
    result: dict | None


@dataclass(frozen=True)
class LogEntry:
    """One entry of the log (metadata only; a batch's arrays are read with
    :meth:`LogBackend.batch_arrays`).

    Attributes
    ----------
    position : int
    kind : {"create", "delete", "batch", "snapshot"}
    field_id : int
    seq : int
        ``batch``: the batch's seq; ``snapshot``: the snapshot's ``snapshot_seq``;
        0 otherwise.
    committed : float
        Unix time of the commit (for the lag in seconds).
    nrows : int
        ``batch``: rows of the batch; 0 otherwise.
    """

    position: int
    kind: str
    field_id: int
    seq: int
    committed: float
    nrows: int = 0


@dataclass(frozen=True)
class SnapshotInfo:
    """A snapshot just written: its name (:attr:`FieldRow.snapshot_file`) and the
    bytes it wrote (its file and its new parts: parts stored already are not
    written again)."""

    file: str
    bytes: int
    position: int


class KeyTakenError(Exception):
    """:meth:`LogBackend.add_batch`: the field already has a batch with this
    idempotency key (stored by this replica or another); ``existing`` is it.
    Internal: the upload path answers it as a retry (or a 422 conflict)."""

    def __init__(self, existing: BatchRow):
        super().__init__(f"idempotency key {existing.idem_key!r} is taken by batch "
                         f"{existing.seq}")
        self.existing = existing


class SnapshotGoneError(Exception):
    """:meth:`LogBackend.load_snapshot`: the row's snapshot was replaced (and
    removed) meanwhile; read the field's row again and retry. Internal."""
