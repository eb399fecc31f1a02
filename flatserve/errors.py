"""One error hierarchy for flatserve.

Library code raises these; only :mod:`flatserve.service` maps them to HTTP
statuses. Every class that signals bad input also derives from
:class:`ValueError`, so ``except ValueError`` keeps working for callers that do
not care about flatserve's types.
"""
from __future__ import annotations


class FlatserveError(Exception):
    """Base class of every error flatserve raises on purpose."""


class InvalidInputError(FlatserveError, ValueError):
    """An argument has the wrong shape, dtype, or non-finite values.

    ``argument`` names the offending argument (``"origins"``, ``"Q"``, ...) so
    the service can report the field by name.
    """

    def __init__(self, message: str, argument: str | None = None):
        super().__init__(message)
        self.argument = argument


class InvalidFlatError(InvalidInputError):
    """(Q, r) violates (C1) or (C2) of the paper (Sec. 2.1) for some rows."""


class WeightsError(InvalidInputError):
    """Affine-combination weights do not sum to one (Eq. 4)."""


class BasisError(FlatserveError, ValueError):
    """A basis fails one of the checks of Sec. 3 (count, orthogonality, rank)."""


class SnapshotError(FlatserveError, ValueError):
    """A triangulation snapshot is truncated, corrupted, or of another version."""


class StorageError(FlatserveError):
    """Durable storage failed (disk, database)."""


class FieldNotFoundError(FlatserveError, KeyError):
    """No field with this name exists."""


class FieldExistsError(FlatserveError):
    """A field with this name already exists."""


class LimitExceededError(FlatserveError):
    """A configured limit (batch size, number of fields, ...) was exceeded."""


class StorageFullError(StorageError):
    """Durable storage is out of space (a write was refused; nothing changed)."""


class DataDirInUseError(StorageError):
    """Another server holds the data directory."""
