"""The experiment of paper Sec. 4.3: recover random convex coefficients.

For each ``(d, k)`` and each trial: draw a d-simplex ``v_1 .. v_{d+1}`` uniformly
in ``[-1, 1]^d`` (rejecting nearly degenerate ones), pick
``m = (k+1)(d-k)+1`` pairwise distinct index sets of size ``k+1`` (the paper
prints "size d+1", but a k-flat is spanned by k+1 points), let the basis be the
flats through those vertices, draw ``alpha'`` uniform in ``[0, 1]^m``,
normalise to ``alpha``, form ``q+ = P(sum alpha_l q_l)`` (Eq. 4, Sec. 2.3) and
recover ``w`` with the linear system of Fig. 8.  The paper reports
``w == alpha`` in every case.

All trials of one ``(d, k)`` run as one batch (a basis per row).

Example
-------
>>> from flatserve.experiment import run
>>> row = run(3, 1, trials=50, seed=0)
>>> row.failures, row.max_error < 1e-8
(0, True)
"""
from __future__ import annotations

import itertools
from typing import NamedTuple, Sequence

import numpy as np

from . import flats as _flats
from .coordinates import OK, coordinates_unchecked, n_equations

__all__ = ["CASES", "EXPERIMENT_TOL", "MAX_SIMPLEX_COND", "ExperimentRow", "run",
           "run_all", "format_table"]

#: The (d, k) pairs of the default experiment.
CASES: tuple[tuple[int, int], ...] = ((2, 1), (3, 1), (3, 2), (4, 1), (4, 2), (5, 2), (6, 3))
#: A trial fails when a recovered coefficient differs from the one used by more.
EXPERIMENT_TOL = 1e-8
#: Simplices whose edge matrix ``[v_2 - v_1, ..., v_{d+1} - v_1]`` has a
#: condition number above this are redrawn (affine independence, with margin).
MAX_SIMPLEX_COND = 1e3


class ExperimentRow(NamedTuple):
    """One ``(d, k)`` row of the experiment table.

    Attributes
    ----------
    d, k, m : int
        Ambient dimension, flat dimension, basis size ``(k+1)(d-k)+1``.
    trials : int
    max_error : float
        Largest ``|w_l - alpha_l|`` over all trials and coefficients.
    failures : int
        Trials with error above ``EXPERIMENT_TOL`` or status other than OK.
    max_residual : float
        Largest round-trip residual.
    """

    d: int
    k: int
    m: int
    trials: int
    max_error: float
    failures: int
    max_residual: float


def _simplices(rng, n, d):
    V = rng.uniform(-1.0, 1.0, size=(n, d + 1, d))
    for _ in range(1000):
        bad = ~(np.linalg.cond(V[:, 1:] - V[:, :1]) <= MAX_SIMPLEX_COND)
        if not bad.any():
            return V
        V[bad] = rng.uniform(-1.0, 1.0, size=(int(bad.sum()), d + 1, d))
    raise RuntimeError("could not draw non-degenerate simplices")  # pragma: no cover


def run(d: int, k: int, trials: int = 1000, seed: int | None = 0, rng=None) -> ExperimentRow:
    """Run the Sec. 4.3 experiment for one ``(d, k)``.

    Parameters
    ----------
    d, k : int
        ``1 <= d``, ``0 <= k < d`` with ``C(d+1, k+1) >= (k+1)(d-k)+1``.
    trials : int
    seed : int or None
        Seed of ``np.random.default_rng`` (ignored when ``rng`` is given).

    Returns
    -------
    ExperimentRow

    Raises
    ------
    ValueError
        When there are fewer distinct index sets than basis elements.
    """
    k = _flats.check_k(k, d)
    rng = np.random.default_rng(seed) if rng is None else rng
    m = n_equations(k, d)
    combos = np.array(list(itertools.combinations(range(d + 1), k + 1)))
    if len(combos) < m:
        raise ValueError(f"(d, k) = ({d}, {k}): only {len(combos)} index sets for m = {m}")
    n = int(trials)
    V = _simplices(rng, n, d)
    pick = np.argsort(rng.random((n, len(combos))), axis=1)[:, :m]  # distinct sets
    idx = combos[pick]  # (n, m, k+1)
    pts = np.take_along_axis(V[:, None, :, :], idx[..., None], axis=2)  # (n, m, k+1, d)
    Qb, rb = _flats.from_points(pts.reshape(n * m, k + 1, d))
    Qb = Qb.reshape(n, m, d, d)
    rb = rb.reshape(n, m, d)
    alpha = rng.random((n, m))
    alpha /= alpha.sum(axis=1, keepdims=True)
    target = _flats.project_unchecked(
        np.einsum("nl,nlij->nij", alpha, Qb), np.einsum("nl,nli->ni", alpha, rb), k,
        _flats.GAP_TOL)
    c = coordinates_unchecked(Qb, rb, k, target.Q, target.r)
    err = np.abs(c.weights - alpha).max(axis=1)
    fail = ~(err <= EXPERIMENT_TOL) | (c.status != OK) | target.ambiguous
    return ExperimentRow(d, k, m, n, float(err.max(initial=0.0)), int(fail.sum()),
                         float(c.residual.max(initial=0.0)))


def run_all(trials: int = 1000, seed: int | None = 0,
            cases: Sequence[tuple[int, int]] = CASES) -> list[ExperimentRow]:
    """Run :func:`run` for every ``(d, k)`` in ``cases`` from one seeded generator."""
    rng = np.random.default_rng(seed)
    return [run(d, k, trials, rng=rng) for d, k in cases]


def format_table(rows: Sequence[ExperimentRow]) -> str:
    """Plain-text table: d, k, m, trials, largest coefficient error, failures."""
    head = f"{'d':>2} {'k':>2} {'m':>3} {'trials':>8} {'max |w-alpha|':>14} {'failures':>9} {'max residual':>13}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r.d:>2} {r.k:>2} {r.m:>3} {r.trials:>8} {r.max_error:>14.3e} "
                     f"{r.failures:>9} {r.max_residual:>13.3e}")
    return "\n".join(lines)
