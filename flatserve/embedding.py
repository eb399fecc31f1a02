"""Euclidean embedding of affine coordinates (paper Sec. 5).

Affine coordinates ``w`` (``m`` entries summing to one) live on a hyperplane of
dimension ``m - 1`` in R^m.  Multiplying them with the vertices of a regular
simplex centred at the origin in R^(m-1) gives Euclidean points that can be
triangulated.  The simplex used here is the standard simplex ``e_1 .. e_m``
expressed in an orthonormal (Helmert) basis of the hyperplane ``sum = 0``, so
the embedding is an *isometry* of ``{w : sum w = 1}`` onto R^(m-1): edge length
``sqrt(2)``, circumradius ``sqrt((m-1)/m)``.

Example
-------
>>> import numpy as np
>>> from flatserve.embedding import embed, unembed
>>> w = np.array([[0.2, 0.3, 0.5]])
>>> x = embed(w)
>>> x.shape, np.allclose(unembed(x), w)
((1, 2), True)
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ._validate import as_array
from .errors import InvalidInputError

__all__ = ["regular_simplex", "embed", "unembed"]


@lru_cache(maxsize=64)
def _helmert(m: int) -> np.ndarray:
    H = np.zeros((m, m - 1))
    for j in range(1, m):
        H[:j, j - 1] = 1.0
        H[j, j - 1] = -float(j)
        H[:, j - 1] /= np.sqrt(j * (j + 1.0))
    H.setflags(write=False)
    return H


def regular_simplex(m: int) -> np.ndarray:
    """Vertices of a regular simplex with ``m`` vertices centred at the origin.

    Parameters
    ----------
    m : int
        Number of vertices, ``m >= 2``.

    Returns
    -------
    ndarray, shape (m, m-1)
        Row ``l`` is vertex ``l``; all edges have length ``sqrt(2)``, the rows
        sum to zero and the columns are orthonormal (``V^T V = I``).

    Examples
    --------
    >>> V = regular_simplex(3)
    >>> np.allclose(np.linalg.norm(V[0] - V[1]), np.sqrt(2))
    True
    """
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 2:
        raise InvalidInputError(f"m: expected an integer >= 2, got {m!r}", "m")
    return np.array(_helmert(int(m)))


#: Rows per block of :func:`row_product` (its temporaries stay in cache).
_ROW_BLOCK = 2048


def row_product(a: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``a @ B``, each row computed on its own in a fixed order.

    BLAS rounds a matrix product differently for different numbers of rows
    (other kernels, other blockings), so ``(a @ B)[i]`` may differ in the last
    bit from ``a[i:i+1] @ B``. The points of a sample and of a query at the same
    flat must be the same bits, whatever else is in their batches: a sample on
    the hull of a triangulation queried alone would otherwise fall just
    outside it. This sums ``a[:, j] * B[j]`` over ``j`` in order (``B`` is
    small: m x (m-1)).

    Parameters
    ----------
    a : ndarray, shape (n, m)
    B : ndarray, shape (m, p)

    Returns
    -------
    ndarray, shape (n, p)

    Examples
    --------
    >>> a = np.random.default_rng(0).normal(size=(500, 5))
    >>> H = np.linalg.qr(np.random.default_rng(1).normal(size=(5, 4)))[0]
    >>> bool((row_product(a[:1], H) == row_product(a, H)[:1]).all())
    True
    """
    n, m = a.shape
    out = np.empty((n, B.shape[1]), dtype=np.result_type(a, B))
    tmp = np.empty((min(n, _ROW_BLOCK), B.shape[1]), dtype=out.dtype)
    # in blocks of rows that stay in cache (one pass over the output instead
    # of 2m over arrays as large as it); the same operations per row
    for lo in range(0, n, _ROW_BLOCK):
        hi = min(n, lo + _ROW_BLOCK)
        o, blk, t = out[lo:hi], a[lo:hi], tmp[:hi - lo]
        np.multiply(blk[:, :1], B[0], out=o)
        for j in range(1, m):
            np.multiply(blk[:, j:j + 1], B[j], out=t)
            o += t
    return out


def embed(w) -> np.ndarray:
    """Map affine coordinates to Euclidean points: ``x = w V`` (Sec. 5).

    Parameters
    ----------
    w : array_like, shape (n, m)
        Affine coordinates (rows are expected to sum to one; this is not
        enforced, the component along ``(1, ..., 1)`` is simply dropped).

    Returns
    -------
    ndarray, shape (n, m-1)
    """
    w = as_array(w, "w", ("n", None))
    if w.shape[1] < 2:
        raise InvalidInputError(f"w: need m >= 2 coordinates, got {w.shape[1]}", "w")
    return row_product(w, _helmert(w.shape[1]))


def unembed(x) -> np.ndarray:
    """Inverse of :func:`embed`: ``w = x V^T + 1/m``.

    Parameters
    ----------
    x : array_like, shape (n, m-1)

    Returns
    -------
    ndarray, shape (n, m)
        Rows sum to one.
    """
    x = as_array(x, "x", ("n", None))
    m = x.shape[1] + 1
    if m < 2:
        raise InvalidInputError("x: need at least one column", "x")
    return row_product(x, _helmert(m).T) + 1.0 / m
