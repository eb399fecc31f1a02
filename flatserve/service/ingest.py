"""Two-phase insert of an upload batch: ``prepare`` (validate + coordinates, exact
accepted / rejected rows and reasons), then ``insert_prepared`` (the triangulation).

``Field.add*`` does both at once; the service splits them so that an upload with
``?wait=false`` is acknowledged once its coordinates are known and its batch is
committed, and the (much slower) Delaunay insert happens afterwards in the
field's background worker.

This module mirrors ``Field.add`` / ``add_rays`` / ``add_parametric`` step by step
through the Field's internal helpers (``_chart``, ``_reason``, ``_values``,
``_tri``, ``_lock``, ``_nrejected``); ``tests/service/test_service_wait.py``
checks that ``insert_prepared(prepare(...))`` leaves a field identical to
``Field.add*`` so a change of those internals fails loudly. (Proposed to the
lead: public ``Field.prepare(...)`` / ``Field.insert_prepared(...)``.)
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .. import flats as _flats
from ..coordinates import OK, Coordinates
from ..embedding import embed

#: ray batches at least this long compute their coordinates in parallel chunks
PARALLEL_ROWS = 16_384
_THREADS = max(1, min(4, os.cpu_count() or 1))
_pool: ThreadPoolExecutor | None = None


@dataclass(eq=False)
class Prepared:
    """One batch whose coordinates are computed but not yet triangulated."""

    nrows: int
    x: np.ndarray          # (accepted, D) embedded coordinates of the accepted rows
    values: np.ndarray     # (accepted, C) their values
    rejected: np.ndarray   # (j,) int64 row indices not triangulated
    reasons: list[str]

    @property
    def accepted(self) -> int:
        return int(self.x.shape[0])


def prepare(fld, form: str, arrays: dict[str, np.ndarray], values: np.ndarray) -> Prepared:
    """Validate one batch and compute its coordinates (no lock: only the basis is read)."""
    if form == "rays":
        fld._require_lines()
        o, v, _ = _flats._check_rays(arrays["origins"], arrays["directions"])
        chart = {"rays": (o, v)}
        n = o.shape[0]
    else:
        if form == "parametric":
            Q, r = _flats.from_parametric(arrays["A"], arrays["b"])
        else:
            Q, r = arrays["Q"], arrays["r"]
        Q, r = fld._check_flats(Q, r)
        _flats.validate(Q, r, fld.k)
        chart = {"Q": Q, "r": r}
        n = Q.shape[0]
    vals = fld._values(values, n)
    if "rays" in chart and n >= PARALLEL_ROWS and _THREADS > 1:
        status, ok, x, coords = _chart_rays_parallel(fld, *chart["rays"])
    else:
        status, ok, x, coords = fld._chart(**chart)
    rejected = np.flatnonzero(~ok).astype(np.int64)
    reasons = [fld._reason(status[i], coords, i) for i in rejected]
    return Prepared(n, np.ascontiguousarray(x), np.ascontiguousarray(vals[ok]), rejected, reasons)


def insert_prepared(fld, p: Prepared) -> tuple[int, int]:
    """Triangulate a prepared batch; returns ``(duplicates, nsamples)``."""
    with fld._lock:
        duplicates = 0
        if p.accepted:
            duplicates = int(fld._tri.insert(p.x, p.values).n_duplicates)
        fld._nrejected += int(p.rejected.size)
        return duplicates, int(fld.nsamples)


def _chart_rays_parallel(fld, o: np.ndarray, v: np.ndarray):
    """``Field._chart(rays=...)`` with the per-row coordinate kernel run on row chunks
    in threads (it releases the GIL). The kernel is row-independent, and the
    embedding runs once over the whole batch as in ``Field._chart``, so the result
    is bit-identical to the sequential path (the restore replays through it)."""
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(_THREADS, thread_name_prefix="flatserve-chart")
    bounds = np.linspace(0, o.shape[0], _THREADS + 1).astype(int)
    parts = list(_pool.map(
        lambda ab: fld.basis.coordinates_rays(o[ab[0]:ab[1]], v[ab[0]:ab[1]],
                                              roundtrip_tol=fld.roundtrip_tol),
        zip(bounds[:-1], bounds[1:])))
    weights = np.concatenate([np.asarray(p.weights) for p in parts])
    status = np.concatenate([np.asarray(p.status, np.int8) for p in parts])
    residual = np.concatenate([np.asarray(p.residual) for p in parts])
    ok = status == OK
    x = embed(weights[ok]) if ok.any() else np.empty((0, fld.ndim))
    return status, ok, x, Coordinates(weights, status, residual)
