"""Request bodies in, response bodies out: JSON (orjson), ``.npy`` and ``.npz``.

Bulk arrays never pass through pydantic lists of lists (docs/design.md: 250k rays as
pydantic lists 1.1 s, as ``.npy`` 9 ms).

Binary layouts (documented in the OpenAPI description too)
-----------------------------------------------------------
``application/x-npy``: ONE ``.npy`` array of a real number type (float64,
float32, float16 or integers; read as float64), C or Fortran order, shape
``(n, W)`` with n >= 1: per row the flat, then (uploads only) the ``C`` values:

* ``form=rays``       (k = 1): ``origin (d) | direction (d) | values (C)``  -> W = 2d + C
* ``form=parametric``: ``A (d x k, row-major) | b (d) | values (C)``         -> W = dk + d + C
* ``form=flats``:      ``Q (d x d, row-major) | r (d) | values (C)``         -> W = d^2 + d + C

``application/x-npz``: an ``.npz`` (``numpy.savez``) with named arrays:
``origins`` + ``directions``, or ``A`` + ``b``, or ``Q`` + ``r``; ``values`` for
uploads.

Query responses per ``Accept``: ``application/json`` (default), ``application/x-npy``
(shape ``(q, C + 1 [+ 2 (D+1)])`` float64: values, inside as 0/1, then if asked
sample ids and barycentric weights), ``application/x-npz`` (``values``,
``inside``, ``status``, ``ids``, ``weights``).
"""
from __future__ import annotations

import io
import math

import numpy as np
import orjson
from fastapi import Response

from .. import _npy

from .._validate import as_array
from ..errors import InvalidInputError
from ..flats import FORMS, Flats, form_shapes, infer_form
from .errors import ApiError, BatchTooLargeError
from .responses import JSONBytes

NPY = "application/x-npy"
NPZ = "application/x-npz"
JSON = "application/json"




# -- content types -----------------------------------------------------------
def media_type(content_type: str | None) -> str:
    """The bare media type of a Content-Type header ("" when missing)."""
    return (content_type or "").split(";", 1)[0].strip().lower()


def body_kind(content_type: str | None) -> str:
    mt = media_type(content_type)
    if mt in (JSON, "") or mt.endswith("+json"):
        return "json"
    if mt in (NPY, "application/octet-stream"):
        return "npy"
    if mt in (NPZ, "application/zip"):
        return "npz"
    raise ApiError(415, f"unsupported Content-Type {mt!r}: use {JSON}, {NPY} or {NPZ}")


def accept_kind(accept: str | None) -> str:
    a = (accept or "").lower()
    if NPY in a:
        return "npy"
    if NPZ in a:
        return "npz"
    return "json"


# -- decoding ----------------------------------------------------------------
def load_npy(body: bytes, name: str = "body") -> np.ndarray:
    """Parse one ``.npy`` without copying the data (numeric dtypes only)."""
    try:
        dtype, shape, fortran, offset = _npy.header(body)
    except Exception as exc:
        raise InvalidInputError(f"{name}: not a valid .npy array: {exc}", name) from None
    if dtype.kind not in "fiu" or dtype.hasobject:
        raise InvalidInputError(f"{name}: .npy dtype {dtype} is not a real number type", name)
    try:
        return _npy.from_bytes(body, dtype, shape, fortran, offset)
    except ValueError as exc:
        raise InvalidInputError(f"{name}: {exc}", name) from None


def load_npz(body: bytes) -> dict[str, np.ndarray]:
    try:
        with np.load(io.BytesIO(body), allow_pickle=False) as z:
            if not isinstance(z, np.lib.npyio.NpzFile):
                raise ValueError("an .npy, not an .npz")
            out = {k: z[k] for k in z.files}
    except InvalidInputError:
        raise
    except Exception as exc:
        raise InvalidInputError(f"body: not a valid .npz archive: {exc}", "body") from None
    for k, a in out.items():  # the same dtype rule as load_npy
        if a.dtype.kind not in "fiu" or a.dtype.hasobject:
            raise InvalidInputError(f"{k}: .npz array dtype {a.dtype} is not a real number type", k)
    return out


def load_json(body: bytes) -> dict:
    try:
        obj = orjson.loads(body)
    except orjson.JSONDecodeError as exc:
        raise InvalidInputError(f"body: invalid JSON: {exc}", "body") from None
    if not isinstance(obj, dict):
        raise InvalidInputError("body: expected a JSON object", "body")
    return obj


def _rows(raw: dict, form: str) -> int:
    """Rows of the first array of ``form`` (0 when missing), before any validation."""
    x = raw.get(FORMS[form][0])
    return len(x) if isinstance(x, (list, np.ndarray)) else 0


def split_columns(arr: np.ndarray, form: str, k: int, d: int, channels: int | None) -> dict:
    """Split an ``(n, W)`` binary body into named arrays (see the module doc)."""
    shapes = form_shapes(form, k, d)
    widths = {name: math.prod(shp[1:]) for name, shp in shapes.items()}
    want = sum(widths.values()) + (channels or 0)
    if arr.ndim != 2 or arr.shape[1] != want:
        cols = " | ".join(f"{n} ({w})" for n, w in widths.items())
        if channels:
            cols += f" | values ({channels})"
        raise InvalidInputError(
            f"body: form {form!r} needs a 2-D .npy of shape (n, {want}) = {cols}; got {arr.shape}",
            "body",
        )
    out, col = {}, 0
    for name, shp in shapes.items():
        w = widths[name]
        out[name] = arr[:, col:col + w].reshape((arr.shape[0],) + tuple(shp[1:]))
        col += w
    if channels:
        out["values"] = arr[:, col:col + channels]
    return out


def decode(body: bytes, content_type: str | None, form: str | None, *, k: int, d: int,
           channels: int | None, max_rows: int) -> tuple[Flats, np.ndarray | None, dict]:
    """Parse a batch body into ``(flats, values or None, the JSON object or {})``.

    ``channels=None``: a query (no values); else an upload of ``(n, channels)``
    values. Shapes, finite values, equal row counts, at least one row and at
    most ``max_rows`` are checked here, once.
    """
    kind = body_kind(content_type)
    extra: dict = {}
    if kind == "json":
        raw = load_json(body)
        form = form or raw.get("form")
        extra = raw
    elif kind == "npz":
        raw = load_npz(body)
    else:
        if form is None:
            if k == 1:
                form = "rays"
            else:
                raise InvalidInputError("form: required with application/x-npy", "form")
        raw = split_columns(load_npy(body), form, k, d, channels)
    if form is not None and form not in FORMS:
        raise InvalidInputError(f"form: one of {tuple(FORMS)}, got {form!r}", "form")
    form = form or infer_form(raw)
    if form is None:
        raise InvalidInputError(
            "body: give origins+directions (rays), A+b (parametric) or Q+r (flats)", "body")
    nrows = _rows(raw, form)
    if nrows > max_rows:
        raise BatchTooLargeError(f"{nrows} rows in one request; the limit is {max_rows}")
    flats = Flats.from_arrays(raw, k=k, d=d, form=form, min_rows=1)
    values = None
    if channels is not None:
        if raw.get("values") is None:
            raise InvalidInputError("values: missing", "values")
        values = as_array(raw["values"], "values", ("n", channels))
    if values is not None and values.shape[0] != len(flats):
        raise InvalidInputError(f"rows differ between arrays: {FORMS[form][0]} {len(flats)}, "
                                f"values {values.shape[0]}", "values")
    return flats, values, extra


# -- encoding ----------------------------------------------------------------
npy_bytes = _npy.to_bytes


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def query_response(accept: str | None, values, inside, status, ids=None, weights=None) -> Response:
    kind = accept_kind(accept)
    if kind == "npy":
        cols = [np.asarray(values), np.asarray(inside)]
        if ids is not None:
            cols.append(np.asarray(ids))
        if weights is not None:
            cols.append(np.asarray(weights))
        return Response(_npy.columns_to_buffer(cols), media_type=NPY)
    if kind == "npz":
        arrs = {"values": values, "inside": inside, "status": status}
        if ids is not None:
            arrs["ids"] = ids
        if weights is not None:
            arrs["weights"] = weights
        return Response(npz_bytes(arrs), media_type=NPZ)
    out = {"values": values, "inside": inside, "status": status}
    if ids is not None:
        out["ids"] = ids
    if weights is not None:
        out["weights"] = weights
    return JSONBytes(out)
