"""The errors of flatserve's library (the math).

The errors the math raises; the native extension raises subclasses of them
(``flatserve._core.SnapshotError`` is a :class:`SnapshotError`). Every class
that signals bad input also derives from :class:`ValueError`, so ``except
ValueError`` keeps working for callers that do not care about flatserve's types.

The service's own errors (fields, storage, limits, replicas) and the table from
error class to HTTP status are in :mod:`flatserve.service.status`, which the
client shares.

This module imports nothing from flatserve (the extension imports it).
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
