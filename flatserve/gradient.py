"""The gradient interpolant: the piecewise linear answer corrected by estimated slopes.

The paper interpolates linearly in a Delaunay cell (Sec. 5): a query's value
is ``sum_i w_i f_i`` over the cell's vertices ``x_i`` with barycentric
weights ``w_i``. Its error is about ``-1/2 sum_i w_i (x_i - x)^T H (x_i - x)``
for a function of Hessian ``H``: in many dimensions, with few samples, cells
are wide and the error is large (docs/costs.md). The *gradient* interpolant
keeps the cell and its weights but blends each vertex's first-order Taylor
expansion instead of its value::

    f(x) ~ sum_i w_i (f_i + g_i . (x - x_i))

where ``g_i`` is the slope at sample ``i``, estimated by least squares over
its nearest samples in the chart's coordinates (weighted by inverse
distance). It is

- the same value at every sample (``w`` is a vertex's indicator there);
- continuous across cells (the weights are, and each Taylor term is smooth);
- exact for a linear function (its slopes are estimated exactly);
- not a convex combination of the samples' values: it may overshoot them
  (sharp texture in a light field), where the linear interpolant cannot.

With exact slopes its error is ``+1/2 sum_i w_i (x_i - x)^T H (x_i - x)`` to
second order, the linear interpolant's with the other sign; estimated slopes
already carry part of the curvature, and the measured error is lower than
the linear interpolant's by a quarter in 6 dimensions at 3,000 samples
(``benchmarks/accuracy_by_kind.py --interpolant gradient``).

Neighbours are found with scipy's k-d tree (the one dependency of the
library besides NumPy), built over a chart's points once per state of the
chart and kept until the next insert.

>>> import numpy as np
>>> from flatserve.gradient import slopes, taylor_blend
>>> rng = np.random.default_rng(0)
>>> X = rng.uniform(size=(50, 2)); F = (X @ [2.0, -1.0])[:, None] + 3
>>> from scipy.spatial import cKDTree
>>> G = slopes(cKDTree(X), X, F, np.arange(50))
>>> bool(np.allclose(G[:, 0], [2.0, -1.0]))
True
"""
from __future__ import annotations

import numpy as np

from .errors import InvalidInputError

__all__ = ["GRADIENT_NEIGHBOURS", "neighbours_for", "slopes", "taylor_blend"]

#: Nearest samples a slope is fitted to, per chart dimension D: ``2 D + 2``
#: (the D unknowns over-determined twice; measured against ``4 D`` in
#: 6 dimensions: 3-7 % lower error, the nearer samples describe the slope at
#: the sample better).
GRADIENT_NEIGHBOURS = 2


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


def slopes(tree, points: np.ndarray, values: np.ndarray, ids: np.ndarray, *,
           neighbours: int | None = None) -> np.ndarray:
    """Least-squares slopes of the values at some samples.

    Parameters
    ----------
    tree : scipy.spatial.cKDTree
        Over ``points``.
    points : ndarray, shape (n, D)
        The chart's sample coordinates.
    values : ndarray, shape (n, C)
    ids : ndarray, shape (m,), int
        The samples whose slopes are wanted (distinct).
    neighbours : int, optional
        Nearest samples fitted to (see :func:`neighbours_for`); fewer if the
        chart holds fewer.

    Returns
    -------
    ndarray, shape (m, C, D)
        ``g`` minimising ``sum_j ((f_j - f_i) - g . (x_j - x_i))^2 / |x_j - x_i|^2``
        over the neighbours ``j`` of sample ``i`` (a rank-deficient
        neighbourhood gives the least-norm slope).
    """
    n, D = points.shape
    C = values.shape[1]
    m = len(ids)
    out = np.zeros((m, C, D))
    K = min(neighbours_for(D, neighbours), n - 1)
    if m == 0 or K < 1:
        return out
    dist, nb = tree.query(points[ids], K + 1)
    dist, nb = dist[:, 1:], nb[:, 1:]  # the sample itself first (distinct points)
    wt = 1.0 / np.maximum(dist, np.finfo(float).tiny)
    dx = (points[nb] - points[ids][:, None, :]) * wt[..., None]   # (m, K, D)
    df = (values[nb] - values[ids][:, None, :]) * wt[..., None]   # (m, K, C)
    # batched least squares through the SVD (stable for thin neighbourhoods)
    u, s, vt = np.linalg.svd(dx, full_matrices=False)             # (m,K,r) (m,r) (m,r,D)
    cut = s > s[:, :1] * (max(K, D) * np.finfo(float).eps)
    inv = np.where(cut, 1.0 / np.where(cut, s, 1.0), 0.0)
    coef = np.einsum("mkr,mkc->mrc", u, df) * inv[..., None]      # (m, r, C)
    return np.einsum("mrd,mrc->mcd", vt, coef)


def taylor_blend(xv: np.ndarray, fv: np.ndarray, gv: np.ndarray, weights: np.ndarray,
                 xq: np.ndarray) -> np.ndarray:
    """``sum_i w_i (f_i + g_i . (x - x_i))`` per query.

    Parameters
    ----------
    xv : ndarray, shape (q, D+1, D)
        The coordinates of each query's cell's vertices.
    fv : ndarray, shape (q, D+1, C)
        Their values.
    gv : ndarray, shape (q, D+1, C, D)
        Their slopes (:func:`slopes`).
    weights : ndarray, shape (q, D+1)
        The query's barycentric weights in its cell.
    xq : ndarray, shape (q, D)
        The queries' coordinates.

    Returns
    -------
    ndarray, shape (q, C)
    """
    term = fv + np.einsum("qjcd,qjd->qjc", gv, xq[:, None, :] - xv)
    return np.einsum("qj,qjc->qc", weights, term)
