"""Input validation at the public boundary (done once; C++ gets clean arrays)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .errors import InvalidInputError


def _shape_str(shape: Sequence[int | str | None]) -> str:
    return "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"


def as_array(
    x,
    name: str,
    shape: Sequence[int | str | None],
    *,
    dtype=np.float64,
    finite: bool = True,
    min_rows: int = 0,
    max_abs: float | None = None,
) -> np.ndarray:
    """Convert ``x`` to a C-contiguous array of ``dtype`` and check its shape.

    Parameters
    ----------
    x : array_like
        The user's input.
    name : str
        Argument name used in error messages (``"origins"``).
    shape : sequence of int, str or None
        Expected shape. ``None`` accepts any length on that axis; a string is a
        symbolic name (for the message) that also accepts any length.
    finite : bool
        Reject NaN and infinities (floating dtypes only).
    min_rows : int
        Smallest accepted length of axis 0.
    max_abs : float, optional
        Reject entries larger than this in magnitude (floating dtypes only): the
        arrays of flats, whose products (quadrics, projections) would overflow
        float64 near its limit and make LAPACK fail on the whole batch.

    Raises
    ------
    InvalidInputError
        Naming ``name``, the expected shape and what was given.
    """
    try:
        arr = np.ascontiguousarray(np.asarray(x, dtype=dtype))
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(
            f"{name}: expected a numeric array of shape {_shape_str(shape)}: {exc}", name
        ) from None
    ok = arr.ndim == len(shape) and all(
        want is None or isinstance(want, str) or got == want
        for got, want in zip(arr.shape, shape)
    )
    if not ok:
        raise InvalidInputError(
            f"{name}: expected shape {_shape_str(shape)}, got {arr.shape}", name
        )
    if arr.ndim and arr.shape[0] < min_rows:
        raise InvalidInputError(
            f"{name}: expected at least {min_rows} rows, got {arr.shape[0]}", name
        )
    if finite and np.issubdtype(arr.dtype, np.floating) and arr.size:
        bad = ~np.isfinite(arr)
        if bad.any():
            rows = np.unique(np.nonzero(bad)[0])
            raise InvalidInputError(
                f"{name}: non-finite values (NaN or inf) in rows {rows[:10].tolist()}"
                + (" ..." if rows.size > 10 else ""),
                name,
            )
        if max_abs is not None:
            bad = ~(np.abs(arr) <= max_abs)
            if bad.any():
                rows = np.unique(np.nonzero(bad)[0])
                raise InvalidInputError(
                    f"{name}: entries beyond +-{max_abs:g} in rows {rows[:10].tolist()}"
                    + (" ..." if rows.size > 10 else "") + ": scale the coordinates down",
                    name,
                )
    return arr
