"""The experiment of paper Sec. 4.3: recover random convex coefficients.

For each ``(d, k)`` and each trial: draw a d-simplex ``v_1 .. v_{d+1}`` uniformly
in ``[-1, 1]^d`` (rejecting nearly degenerate ones), pick
``m = (k+1)(d-k)+1`` pairwise distinct index sets of size ``k+1`` (the paper
prints "size d+1", but a k-flat is spanned by k+1 points), let the basis be the
flats through those vertices, draw ``alpha'`` uniform in ``[0, 1]^m``,
normalise to ``alpha``, form ``q+ = P(sum alpha_l q_l)`` (Eq. 4, Sec. 2.3) and
recover ``w`` with the linear system of Fig. 8.  The paper reports
``w == alpha`` in every case.

Some picks of index sets give a degenerate basis whatever the simplex (from
d = 5 on, a few in a hundred: the system of Fig. 8 is singular at the basis's
own barycentre, ``sigma_min / sigma_max`` about 1e-17 where every other basis
has more than 1e-7): such a basis is no basis (:meth:`flatserve.basis.Basis.check`
refuses it), so its trial is redrawn, simplex and sets, and counted in
``ExperimentRow.redrawn``.

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
import math
from typing import NamedTuple, Sequence

import numpy as np

from . import flats as _flats
from .errors import InvalidInputError
from .coordinates import OK, SINGULAR_RCOND, coordinates_unchecked, n_equations, system_matrix
from .embedding import regular_simplex

__all__ = ["CASES", "EXPERIMENT_TOL", "MAX_SIMPLEX_COND", "ExperimentRow", "run",
           "run_all", "format_table"]

#: The (d, k) pairs of the default experiment.
CASES: tuple[tuple[int, int], ...] = ((2, 1), (3, 1), (3, 2), (4, 1), (4, 2), (5, 2), (6, 3))
#: A trial fails when a recovered coefficient differs from the one used by more.
EXPERIMENT_TOL = 1e-8
#: Most index sets of size k+1 enumerated (``C(d+1, k+1)``).
MAX_INDEX_SETS = 100_000
#: Most bytes of the trials' bases ``(trials, m, d, d)`` held at once (the
#: computation holds a few arrays of that size).
MAX_BASES_BYTES = 256 << 20
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
    redrawn : int
        Trials whose basis was degenerate, drawn again.
    """

    d: int
    k: int
    m: int
    trials: int
    max_error: float
    failures: int
    max_residual: float
    redrawn: int = 0


def _simplices(rng, n, d):
    V = rng.uniform(-1.0, 1.0, size=(n, d + 1, d))
    for _ in range(1000):
        bad = ~(np.linalg.cond(V[:, 1:] - V[:, :1]) <= MAX_SIMPLEX_COND)
        if not bad.any():
            return V
        V[bad] = rng.uniform(-1.0, 1.0, size=(int(bad.sum()), d + 1, d))
    raise RuntimeError("could not draw non-degenerate simplices")  # pragma: no cover


def _degenerate(Qb, rb, k: int, rcond: float) -> np.ndarray:
    """(n,) bool: the system of Fig. 8 is singular at each basis's barycentre
    ``P(sum q_l / m)`` (check 3 of :meth:`flatserve.basis.Basis.check`)."""
    n, m = Qb.shape[:2]
    w0 = np.full((n, m), 1.0 / m)
    p = _flats.project_unchecked(np.einsum("nl,nlij->nij", w0, Qb),
                                 np.einsum("nl,nli->ni", w0, rb), k, _flats.GAP_TOL)
    A, N = _flats.frames(p.Q, k)
    s = np.linalg.svd(system_matrix(Qb, rb, A, N, p.r)[:, :-1, :] @ regular_simplex(m),
                      compute_uv=False)
    return p.ambiguous | ~(s[:, -1] > rcond * s[:, 0])


def _bases(rng, n: int, d: int, k: int, combos: np.ndarray, m: int):
    """``n`` trials' simplices and bases: ``(Qb (n, m, d, d), rb (n, m, d))``."""
    V = _simplices(rng, n, d)
    pick = np.argsort(rng.random((n, len(combos))), axis=1)[:, :m]  # distinct sets
    idx = combos[pick]  # (n, m, k+1)
    pts = np.take_along_axis(V[:, None, :, :], idx[..., None], axis=2)  # (n, m, k+1, d)
    Qb, rb = _flats.from_points(pts.reshape(n * m, k + 1, d))
    return Qb.reshape(n, m, d, d), rb.reshape(n, m, d)


def run(d: int, k: int, trials: int = 1000, seed: int | None = 0, rng=None, *,
        basis_rcond: float = SINGULAR_RCOND, tol: float = EXPERIMENT_TOL) -> ExperimentRow:
    """Run the Sec. 4.3 experiment for one ``(d, k)``.

    Parameters
    ----------
    d, k : int
        ``1 <= d``, ``0 <= k < d`` with ``C(d+1, k+1) >= (k+1)(d-k)+1``.
    trials : int
    seed : int or None
        Seed of ``np.random.default_rng`` (ignored when ``rng`` is given).
    basis_rcond : float
        A trial's basis is degenerate, and redrawn, when the system of Fig. 8
        at its barycentre has ``sigma_min <= basis_rcond * sigma_max``.
    tol : float
        A trial fails when a recovered coefficient differs by more.

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
    n = int(trials)
    if n < 1:
        raise InvalidInputError(f"trials: expected >= 1, got {trials!r}", "trials")
    sets = math.comb(d + 1, k + 1)
    if sets < m:
        raise ValueError(f"(d, k) = ({d}, {k}): only {sets} index sets for m = {m}")
    if sets > MAX_INDEX_SETS:
        raise ValueError(f"(d, k) = ({d}, {k}): {sets} index sets of size k+1; at most "
                         f"{MAX_INDEX_SETS} are enumerated")
    if n * m * d * d * 8 > MAX_BASES_BYTES:
        most = max(1, MAX_BASES_BYTES // (m * d * d * 8))
        raise InvalidInputError(f"trials: {n} trials of (d, k) = ({d}, {k}) hold "
                                f"{n * m * d * d * 8 / 2**20:.0f} MiB of bases; at most {most} "
                                "at once (run several seeds)", "trials")
    combos = np.array(list(itertools.combinations(range(d + 1), k + 1)))
    Qb, rb = _bases(rng, n, d, k, combos, m)
    redrawn = 0
    for _ in range(1000):
        bad = np.flatnonzero(_degenerate(Qb, rb, k, basis_rcond))
        if not bad.size:
            break
        redrawn += bad.size
        Qb[bad], rb[bad] = _bases(rng, bad.size, d, k, combos, m)
    else:  # pragma: no cover - a case whose every pick is degenerate
        raise RuntimeError(f"(d, k) = ({d}, {k}): could not draw non-degenerate bases")
    alpha = rng.random((n, m))
    alpha /= alpha.sum(axis=1, keepdims=True)
    target = _flats.project_unchecked(
        np.einsum("nl,nlij->nij", alpha, Qb), np.einsum("nl,nli->ni", alpha, rb), k,
        _flats.GAP_TOL)
    c = coordinates_unchecked(Qb, rb, k, target.Q, target.r)
    err = np.abs(c.weights - alpha).max(axis=1)
    fail = ~(err <= tol) | (c.status != OK) | target.ambiguous
    return ExperimentRow(d, k, m, n, float(err.max(initial=0.0)), int(fail.sum()),
                         float(c.residual.max(initial=0.0)), redrawn)


def run_all(trials: int = 1000, seed: int | None = 0,
            cases: Sequence[tuple[int, int]] = CASES) -> list[ExperimentRow]:
    """Run :func:`run` for every ``(d, k)`` in ``cases`` from one seeded generator."""
    rng = np.random.default_rng(seed)
    return [run(d, k, trials, rng=rng) for d, k in cases]


def format_table(rows: Sequence[ExperimentRow]) -> str:
    """Plain-text table: d, k, m, trials, largest coefficient error, failures."""
    head = (f"{'d':>2} {'k':>2} {'m':>3} {'trials':>8} {'max |w-alpha|':>14} {'failures':>9} "
            f"{'max residual':>13} {'redrawn':>8}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r.d:>2} {r.k:>2} {r.m:>3} {r.trials:>8} {r.max_error:>14.3e} "
                     f"{r.failures:>9} {r.max_residual:>13.3e} {r.redrawn:>8}")
    return "\n".join(lines)
