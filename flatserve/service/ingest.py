"""Two-phase insert of an upload batch, over :meth:`flatserve.Field.prepare`.

``prepare`` (validate + coordinates: exact accepted / rejected rows and
reasons; with ``defer`` the coordinates are left for later) runs without a lock; ``insert_prepared`` (the Delaunay insert) runs
later, under the field's write lock. The split lets an upload with
``?wait=false`` be acknowledged once its coordinates are known and its batch
is committed, while the much slower insert happens in the field's background
worker. HTTP forms map to the Field's input forms here; no math lives here.
"""
from __future__ import annotations

import numpy as np

from ..field import Field, PreparedBatch

Prepared = PreparedBatch


def prepare(fld: Field, form: str, arrays: dict[str, np.ndarray], values: np.ndarray,
            *, defer: bool = False) -> PreparedBatch:
    """Validate one batch of the upload form ``form`` and chart it (reads the basis
    only); with ``defer``, validate now and return the charting as a callable."""
    if form == "rays":
        return fld.prepare_rays(arrays["origins"], arrays["directions"], values, defer=defer)
    if form == "parametric":
        return fld.prepare_parametric(arrays["A"], arrays["b"], values, defer=defer)
    return fld.prepare(arrays["Q"], arrays["r"], values, defer=defer)


def insert_prepared(fld: Field, p: PreparedBatch) -> tuple[int, int]:
    """Triangulate a prepared batch; returns ``(duplicates, nsamples)``."""
    res = fld.insert_prepared(p)
    return res.duplicates, res.nsamples
