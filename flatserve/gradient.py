"""The gradient interpolant: the piecewise linear answer corrected by estimated slopes.

The paper interpolates linearly in a Delaunay cell (Sec. 5): a query's value
is ``sum_i w_i f_i`` over the cell's vertices ``x_i`` with barycentric
weights ``w_i``. Its error is about ``-1/2 sum_i w_i (x_i - x)^T H (x_i - x)``
for a function of Hessian ``H``: in many dimensions, with few samples, cells
are wide and the error is large (docs/costs.md). The *gradient* interpolant
keeps the cell and its weights but blends each vertex's first-order Taylor
expansion instead of its value::

    f(x) ~ sum_i w_i T_i(x),   T_i(x) = f_i + g_i . (x - x_i)

where ``g_i`` is the slope at sample ``i``, fitted by least squares to its
``3 D + 2`` nearest samples in the chart's coordinates (each residual over the
neighbour's distance; :data:`GRADIENT_NEIGHBOURS`). Each ``T_i(x)`` is *limited* to the
range of the values of sample ``i`` and those neighbours, widened to hold
the linear answer ``sum_i w_i f_i``: where the values jump (an object's
silhouette in a light field) a slope fitted across the jump would carry a
vertex's value far past its neighbours' (unlimited, views of the bunny lost
up to 40 dB; limited, they are at the linear interpolant's, +0.1 dB on
average). The answer

- is the sample's value at a sample (``w`` is the vertex's indicator there);
- is continuous across cells (the weights are, and each limited term is);
- is exact for an affine function of the chart (its slopes are exact, and
  every term equals the linear answer; a vertex whose neighbours do not span
  the chart's D directions gets no slope and its term is the linear answer);
- lies within the values of the cell's vertices and their neighbours (a
  weighted mean of terms within them), but is not a weighted mean of the
  cell's values: it may leave their range where the function curves.

Its error on smooth functions is a quarter to a half lower than the linear
interpolant's (in 4 to 6 dimensions at 3,000 samples:
``benchmarks/accuracy_by_kind.py --fit-unit --gradient``).

It assumes exact values: noise, or nearly coincident samples of different
values, make slopes steep, and the limited terms then sit at their
neighbourhoods' extremes (2,000 points in R^2 valued ``sin 3x cos 2y``
plus noise of standard deviation 0.01: median error 0.0067 against the
linear 0.0048; without the noise 0.0011 against 0.0014).

Neighbours are found with scipy's k-d tree (the ``gradient`` extra), built
over a chart's points by the first gradient query of each state of the chart
and dropped at the next insert (:meth:`flatserve.field.Field.query`).

>>> import numpy as np
>>> from scipy.spatial import cKDTree
>>> from flatserve.gradient import slopes
>>> rng = np.random.default_rng(0)
>>> X = rng.uniform(size=(50, 2)); F = (X @ [2.0, -1.0])[:, None] + 3
>>> s = slopes(cKDTree(X), X, F, np.arange(50))
>>> bool(np.allclose(s.slope[:, 0], [2.0, -1.0]))
True
"""
from __future__ import annotations

import contextlib
from typing import NamedTuple

import numpy as np

from .errors import InvalidInputError

__all__ = ["GRADIENT_CHUNK_BYTES", "GRADIENT_NEIGHBOURS", "GRADIENT_RCOND", "Slopes",
           "gradient_chunk", "neighbours_for", "slopes", "taylor_blend"]

#: Nearest samples a slope is fitted to, per chart dimension D: ``3 D + 2``.
#: Measured (3,000 samples, a smooth function, fitted units, two seeds; error
#: over the 8 nearest samples'): ``2 D + 2`` is 4-14 % worse in 3-4 dimensions
#: and up to 4 % better in 6; ``4 D + 2`` 7 % better in 3 dimensions, from 8 %
#: better to 4 % worse in 4, and up to 5 % worse in 6 (docs/costs.md).
GRADIENT_NEIGHBOURS = 3

#: Singular values of a neighbourhood's (weighted) offsets below this share of
#: the largest are dropped: its numerical rank (the limiter, not a cut, bounds
#: the slopes of thin neighbourhoods).
GRADIENT_RCOND = 1e-10

#: Working memory of one chunk of a gradient query (:func:`gradient_chunk`): the
#: slopes and Taylor terms of a query row take about ``(D+1) (K (D+C) + C D)``
#: floats, 48 KB in 4 dimensions with 64 channels, so a batch is answered in chunks
#: and its memory stays bounded whatever its rows.
GRADIENT_CHUNK_BYTES = 32 << 20


class Slopes(NamedTuple):
    """Per sample (:func:`slopes`): its slope and the range of its neighbourhood's values."""

    #: (m, C, D) least-squares slopes
    slope: np.ndarray
    #: (m, C) least value of the sample and its neighbours
    low: np.ndarray
    #: (m, C) greatest value of the sample and its neighbours
    high: np.ndarray


def neighbours_for(ndim: int, neighbours: int | None = None) -> int:
    """The number of nearest samples a slope in ``ndim`` dimensions is fitted to:
    ``neighbours`` if given (at least ``ndim``), else ``GRADIENT_NEIGHBOURS *
    ndim + 2``."""
    if neighbours is None:
        return GRADIENT_NEIGHBOURS * ndim + 2
    if isinstance(neighbours, bool) or not isinstance(neighbours, (int, np.integer)) \
            or neighbours < ndim:
        raise InvalidInputError(
            f"neighbours: an integer of at least the chart's dimension {ndim} expected, "
            f"got {neighbours!r}", "neighbours")
    return int(neighbours)


def gradient_chunk(ndim: int, channels: int, *, neighbours: int | None = None,
                   budget: int = GRADIENT_CHUNK_BYTES) -> int:
    """Query rows of one chunk of a gradient query in ``ndim`` dimensions with
    ``channels`` values: those whose slopes, neighbourhoods and Taylor terms
    (about three copies of ``(D+1) (K (D+C) + C D)`` floats a row, ``K`` the
    neighbours, :func:`neighbours_for`) fit in ``budget`` bytes; at least 1.

    >>> gradient_chunk(4, 64)
    219
    """
    K = neighbours_for(ndim, neighbours)
    per_row = 8 * 3 * (ndim + 1) * (K * (ndim + channels) + channels * ndim + channels)
    return max(1, int(budget) // per_row)


def slopes(tree, points: np.ndarray, values: np.ndarray, ids: np.ndarray, *,
           neighbours: int | None = None, rcond: float = GRADIENT_RCOND,
           workers: int = 1) -> Slopes:
    """Least-squares slopes of the values at some samples.

    Parameters
    ----------
    tree : scipy.spatial.cKDTree
        Over ``points``.
    points : ndarray, shape (n, D)
        The chart's sample coordinates (distinct).
    values : ndarray, shape (n, C)
    ids : ndarray, shape (m,), int
        The samples whose slopes are wanted.
    neighbours : int, optional
        Nearest samples fitted to (see :func:`neighbours_for`); fewer if the
        chart holds fewer.
    rcond : float
        Singular values below this share of the largest are dropped; a sample
        whose neighbourhood then spans fewer than D directions (its neighbours
        on a line or plane of the chart) has no trusted slope: its range is
        empty (``low`` +inf, ``high`` -inf), so :func:`taylor_blend` keeps the
        linear answer for its term.
    workers : int
        Threads of the neighbour search (scipy's; -1: all cores).

    Returns
    -------
    Slopes
        ``slope`` minimising ``sum_j ((f_j - f_i) - g . (x_j - x_i))^2 / |x_j -
        x_i|^2`` over the neighbours ``j`` of sample ``i``, and the range of
        ``f_i`` and the ``f_j``. Where the neighbourhood is rank-deficient
        (every channel), or a channel's slope overflows (values near the float
        range), the slope is 0 and the range empty: :func:`taylor_blend` then
        keeps the linear answer.
    """
    n, D = points.shape
    m = len(ids)
    K = min(neighbours_for(D, neighbours), n - 1)
    own = values[ids]
    if m == 0 or K < 1:
        return Slopes(np.zeros((m, values.shape[1], D)), own, own)
    dist, nb = tree.query(points[ids], K + 1, workers=workers)
    dist, nb = dist[:, 1:], nb[:, 1:]  # the sample itself first (distinct points)
    wt = 1.0 / np.maximum(dist, np.finfo(float).tiny)
    dx = (points[nb] - points[ids][:, None, :]) * wt[..., None]   # (m, K, D)
    with np.errstate(over="ignore", invalid="ignore"):  # values near the float range
        df = (values[nb] - own[:, None, :]) * wt[..., None]       # (m, K, C)
        # batched least squares through the SVD (stable for thin neighbourhoods)
        u, s, vt = np.linalg.svd(dx, full_matrices=False)         # (m,K,r) (m,r) (m,r,D)
        cut = s > s[:, :1] * max(rcond, max(K, D) * np.finfo(float).eps)
        inv = np.where(cut, 1.0 / np.where(cut, s, 1.0), 0.0)
        coef = np.einsum("mkr,mkc->mrc", u, df) * inv[..., None]  # (m, r, C)
        slope = np.einsum("mrd,mrc->mcd", vt, coef)
    near = values[nb]
    low = np.minimum(own, near.min(axis=1))
    high = np.maximum(own, near.max(axis=1))
    # no slope across the missing directions (every channel), nor in a channel whose
    # slope overflowed (values near the float range): the linear term
    bad = (cut.sum(axis=1) < D)[:, None] | ~np.isfinite(slope).all(axis=2)  # (m, C)
    low[bad], high[bad] = np.inf, -np.inf
    slope[bad] = 0.0
    return Slopes(slope, low, high)


def taylor_blend(xv: np.ndarray, fv: np.ndarray, gv: np.ndarray, weights: np.ndarray,
                 xq: np.ndarray, low: np.ndarray | None = None,
                 high: np.ndarray | None = None) -> np.ndarray:
    """``sum_i w_i T_i(x)``, each vertex's Taylor term ``T_i(x) = f_i + g_i . (x - x_i)``
    limited to ``[min(low_i, L), max(high_i, L)]`` with ``L = sum_i w_i f_i``.

    Parameters
    ----------
    xv : ndarray, shape (q, D+1, D)
        The coordinates of each query's cell's vertices.
    fv : ndarray, shape (q, D+1, C)
        Their values.
    gv : ndarray, shape (q, D+1, C, D)
        Their slopes (:attr:`Slopes.slope`).
    weights : ndarray, shape (q, D+1)
        The query's barycentric weights in its cell.
    xq : ndarray, shape (q, D)
        The queries' coordinates.
    low, high : ndarray, shape (q, D+1, C), optional
        The vertices' neighbourhood ranges (:attr:`Slopes.low`, ``high``);
        None: the terms are not limited.

    Returns
    -------
    ndarray, shape (q, C)
    """
    limited = low is not None  # (not limited: an overflow shows)
    with np.errstate(over="ignore", invalid="ignore") if limited else contextlib.nullcontext():
        term = fv + np.einsum("qjcd,qjd->qjc", gv, xq[:, None, :] - xv)
    if limited:
        lin = np.einsum("qj,qjc->qc", weights, fv)[:, None, :]
        # a term that overflowed (values near the float range) is the linear answer
        term = np.where(np.isfinite(term), term, lin)
        term = np.clip(term, np.minimum(low, lin), np.maximum(high, lin))
    return np.einsum("qj,qjc->qc", weights, term)
