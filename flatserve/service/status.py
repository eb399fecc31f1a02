"""The service's errors and the one table from error class to HTTP status.

The library's errors (:mod:`flatserve.errors`: bad input, a bad basis, a
damaged snapshot) are the math's; the classes here are the service's own:
fields by name, storage, limits, replicas. :data:`HTTP_STATUS` maps both to
HTTP statuses: the service answers with :func:`status_of`, and
:mod:`flatserve.client` raises :func:`error_class` of the status it receives,
so a caller catches the same classes whether it talks to the service or not.

This module imports nothing but :mod:`flatserve.errors` (no FastAPI): the
client shares it.
"""
from __future__ import annotations

from ..errors import BasisError, FlatserveError, InvalidInputError, SnapshotError

__all__ = [
    "StorageError", "FieldNotFoundError", "FieldExistsError", "LimitExceededError",
    "StorageFullError", "StorageUnavailableError", "DataDirInUseError", "TooManyFieldsError",
    "BatchTooLargeError", "BodyTooLargeError", "AnswerTooLargeError", "BacklogFullError",
    "CostLimitError",
    "CostPendingError",
    "NotReadyError", "ReplicaBehindError", "ShardUnavailableError", "IdempotencyConflictError",
    "InvalidParameterError",
    "HTTP_STATUS",
    "status_of", "error_class",
]


class StorageError(FlatserveError):
    """Durable storage failed (disk, database).

    ``public``, when set, is what a client is told instead of the text (which may
    name the database's host, user, files)."""

    public: str | None = None


class FieldNotFoundError(FlatserveError, KeyError):
    """No field with this name exists."""


class FieldExistsError(FlatserveError):
    """A field with this name already exists."""


class LimitExceededError(FlatserveError):
    """A configured limit (batch size, number of fields, ...) was exceeded."""


class StorageFullError(StorageError):
    """Durable storage is out of space (a write was refused; nothing changed)."""


class StorageUnavailableError(StorageError):
    """The database cannot be reached right now (a restart, a network failure): a
    write in flight may or may not be stored (a retry with its idempotency key
    tells); retry after a moment."""


class DataDirInUseError(StorageError):
    """Another server holds the data directory."""


class TooManyFieldsError(LimitExceededError):
    """The configured number of fields is reached."""


class BatchTooLargeError(LimitExceededError):
    """Too many rows in one upload or query."""


class BodyTooLargeError(LimitExceededError):
    """A request body is larger than the configured limit."""


class AnswerTooLargeError(LimitExceededError):
    """The answer to a request would be larger than the configured limit (judged
    before the work is done)."""


class BacklogFullError(LimitExceededError):
    """Too many acknowledged samples of a field wait for their insert."""


class CostLimitError(LimitExceededError):
    """An upload would make a field's triangulation larger than allowed."""


class CostPendingError(BacklogFullError):
    """An upload would pass the cell limit only counting the samples acknowledged and
    not yet indexed: it may pass once they are (429, ``Retry-After``)."""


class NotReadyError(FlatserveError):
    """Stored fields are still being restored (or the server is shutting down)."""


class ReplicaBehindError(NotReadyError):
    """This replica has not yet applied the log position a read asked for
    (``min_position``) within the configured wait; another replica, or a retry,
    will have."""


class ShardUnavailableError(NotReadyError):
    """Cluster mode: a shard a request needs has no live copy now (its node was lost
    and it is being placed again and restored, or the cluster is unreachable), or
    has not applied the log position the answer must reflect within the wait. The
    answer is never given in part: 503 with ``Retry-After``."""


class InvalidParameterError(InvalidInputError):
    """Bad input in a query parameter (422 located at ``["query", name]``, not in the
    body)."""

    location = "query"


class IdempotencyConflictError(FlatserveError):
    """An idempotency key was reused with a different request body."""


#: HTTP status of each error class: the one table. :func:`status_of` looks an
#: exception's classes up in method resolution order; :func:`error_class`
#: inverts the table (the first class listed with a status wins).
HTTP_STATUS: dict[type, int] = {
    FieldNotFoundError: 404,
    FieldExistsError: 409,
    TooManyFieldsError: 409,
    LimitExceededError: 413,
    BacklogFullError: 429,
    InvalidInputError: 422,
    BasisError: 422,
    IdempotencyConflictError: 422,
    ValueError: 422,  # bad input reported by NumPy or other libraries
    NotReadyError: 503,
    ReplicaBehindError: 503,
    ShardUnavailableError: 503,
    StorageFullError: 507,
    StorageError: 503,
    SnapshotError: 503,
    MemoryError: 503,  # this request did not fit in the server's memory now: nothing of it kept
}

_CLASS_OF_STATUS: dict[int, type] = {status: cls for cls, status in reversed(HTTP_STATUS.items())}


def status_of(exc: BaseException) -> int:
    """HTTP status of an exception: its nearest class in :data:`HTTP_STATUS`.

    Parameters
    ----------
    exc : BaseException

    Returns
    -------
    int
        The status of the first class of ``type(exc).__mro__`` in the table;
        500 when there is none.
    """
    for cls in type(exc).__mro__:
        status = HTTP_STATUS.get(cls)
        if status is not None:
            return status
    return 500


def error_class(status: int) -> type[Exception] | None:
    """The library class for an HTTP status (:data:`HTTP_STATUS` inverted).

    Parameters
    ----------
    status : int

    Returns
    -------
    type or None
        The first class listed with ``status`` in :data:`HTTP_STATUS`
        (404 :class:`FieldNotFoundError`, 409 :class:`FieldExistsError`,
        413 :class:`LimitExceededError`, 422 :class:`InvalidInputError`,
        429 :class:`BacklogFullError`, 503 :class:`NotReadyError`,
        507 :class:`StorageFullError`), or None for a status it does not list.
    """
    return _CLASS_OF_STATUS.get(status)
