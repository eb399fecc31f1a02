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
* ``form=points``     (k = 0): ``point (d) | values (C)``                    -> W = d + C

Without ``form`` an ``.npy`` body is rays for a field of lines (k = 1) and points for a
field of points (k = 0).

``application/x-npz``: an ``.npz`` (``numpy.savez`` or ``numpy.savez_compressed``)
with named arrays: ``origins`` + ``directions``, or ``A`` + ``b``, or ``Q`` + ``r``, or
``points``; ``values`` for uploads. Both binary bodies are read by :mod:`..binary`, which judges
every header (and every ``.npz`` member) before it reads or inflates any data.

Query responses per ``Accept``: ``application/json`` (default), ``application/x-npy``
(shape ``(q, C + 1 [+ 2 (D+1)] [+ 1])`` float32 or float64: values, inside as 0/1,
then if asked (``weights=true``) sample ids and barycentric weights, and with
``status=true`` last the status code of each row,
:class:`flatserve.coordinates.Status`), ``application/x-npz`` (``values``,
``inside``, ``status``, ``ids``, ``weights``).
"""
from __future__ import annotations

import io
import re
import math

import numpy as np
import orjson
from fastapi import Response

from ... import _npy
from ..._validate import as_array
from ...errors import InvalidInputError
from ..status import AnswerTooLargeError, BatchTooLargeError, BodyTooLargeError
from ...flats import FORMS, Flats, form_shapes, forms_in_words, infer_form
from ..binary import load_npy, load_npz
from ..logs import note
from .errors import ApiError
from .responses import model_body
from ..rooms.specs import kind_of
from ..reports import QueryResponse

NPY = "application/x-npy"
NPZ = "application/x-npz"
JSON = "application/json"




# -- content types -----------------------------------------------------------
def media_type(content_type: str | None) -> str:
    """The bare media type of a Content-Type header ("" when missing)."""
    return (content_type or "").split(";", 1)[0].strip().lower()


def is_json(content_type: str | None) -> bool:
    """The Content-Type is JSON (``application/json`` or a ``+json`` type)."""
    mt = media_type(content_type)
    return mt == JSON or (mt.startswith("application/") and mt.endswith("+json"))


def body_kind(content_type: str | None) -> str:
    """``json``, ``npy`` or ``npz`` for a batch body's Content-Type; 415 for any other
    type and for none (a page of another site can post a body without one)."""
    mt = media_type(content_type)
    if not mt:
        raise ApiError(415, f"a body needs a Content-Type: {JSON}, {NPY} or {NPZ}")
    if is_json(content_type):
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
_EXPECTED = {"json": "a JSON object", "npy": "an .npy array", "npz": "an .npz archive"}


_TYPES = {"json": JSON, "npy": NPY, "npz": NPZ}


def _sniff(body: bytes) -> str | None:
    """What the body's first bytes say it is: ``npy``, ``npz``, ``json`` or None."""
    if body.startswith(b"\x93NUMPY"):
        return "npy"
    if body.startswith(b"PK\x03\x04"):
        return "npz"
    if body.lstrip()[:1] in (b"{", b"["):
        return "json"
    return None


def check_body(body: bytes, kind: str) -> None:
    """A 422 that says what is wrong with a body that is empty or whose bytes are
    another of the three kinds than its Content-Type says (``kind``: ``json``,
    ``npy`` or ``npz``), rather than a parser's message about a truncated header or
    document (``curl --data-binary @FILE`` sends an empty body when FILE cannot be
    read; ``-H`` forgotten sends a .npy file as a form)."""
    if not body:
        raise InvalidInputError(f"body: empty body (0 bytes); expected {_EXPECTED[kind]}", "body")
    seen = _sniff(body[:64])
    if seen is not None and seen != kind:
        raise InvalidInputError(
            f"body: the Content-Type says {_EXPECTED[kind]} ({_TYPES[kind]}) but the body is "
            f"{_EXPECTED[seen]}: send it with Content-Type: {_TYPES[seen]}", "body")


def load_json(body: bytes) -> dict:
    try:
        obj = orjson.loads(body)
    except orjson.JSONDecodeError as exc:
        raise InvalidInputError(f"body: invalid JSON: {exc}", "body") from None
    if not isinstance(obj, dict):
        raise InvalidInputError("body: expected a JSON object", "body")
    return obj


_BOOLEAN = re.compile(rb"\b(true|false)\b")
#: a member's name in a JSON body (``"points":``)
_MEMBER = re.compile(rb'"(\w+)"\s*:')


def check_json_size(body: bytes, limit: int) -> None:
    """413 for a JSON body over ``limit`` bytes (``max_json_bytes``): parsing holds
    the interpreter for the whole body, so bulk arrays travel as ``.npy``."""
    if len(body) > limit:
        raise BodyTooLargeError(
            f"a JSON body of {len(body)} bytes; the limit for JSON is {limit} "
            f"(FLATSERVE_MAX_JSON_BYTES): send bulk arrays as {NPY} or {NPZ}")


#: JSON arrays are converted this many rows at a time: each conversion holds the
#: GIL, so a big body converted in one call would stall the event loop's thread
JSON_CHUNK_ROWS = 4096


def _json_array(x: list, name: str) -> np.ndarray:
    """A JSON array of numbers as an ndarray, converted in slices (see
    :data:`JSON_CHUNK_ROWS`); strings, nulls and ragged rows are a 422."""
    try:
        parts = [np.asarray(x[i:i + JSON_CHUNK_ROWS]) for i in range(0, len(x), JSON_CHUNK_ROWS)]
        a = parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.asarray(x)
    except ValueError as exc:
        raise InvalidInputError(f"{name}: not a regular array of numbers: {exc}", name) from None
    if a.dtype.kind not in "fiu":
        raise InvalidInputError(f"{name}: expected an array of numbers (no strings or nulls)",
                                name)
    return a


def _check_members(names, *, upload: bool, json: bool) -> None:
    """A batch holds a form's arrays (and ``values`` for uploads; in JSON also
    ``form``), nothing else: a misspelt or foreign member is refused, not ignored."""
    arrays = {n for names_ in FORMS.values() for n in names_} | ({"values"} if upload else set())
    allowed = arrays | ({"form"} if json else set())
    for name in names:
        if name not in allowed:
            raise InvalidInputError(f"{name}: unknown member; a batch has "
                                    + ("form, " if json else "")
                                    + ", ".join(sorted(arrays)), name)


def _check_json_members(raw: dict, body: bytes, *, upload: bool) -> None:
    """A JSON batch holds ``form``, one form's arrays (and ``values`` for uploads),
    nothing else; arrays hold numbers only (no strings, no booleans)."""
    _check_members(raw, upload=upload, json=True)
    if raw.get("form") is not None and not isinstance(raw["form"], str):
        raise InvalidInputError("form: expected a string", "form")
    for name, x in raw.items():
        if name != "form" and isinstance(x, list) and x:  # [] is judged with its shape later
            raw[name] = _json_array(x, name)
    # no member of a batch is a boolean: one is in an array (a quick scan first)
    m = _BOOLEAN.search(body) if b"true" in body or b"false" in body else None
    if m is not None:  # in the member whose name comes last before it (arrays hold no strings)
        keys = _MEMBER.findall(body, 0, m.start())
        name = keys[-1].decode() if keys and keys[-1].decode() in raw else "body"
        raise InvalidInputError(f"{name}: {m.group(0).decode()} is not a number", name)


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
        said = getattr(form, "value", form)
        raise InvalidInputError(
            f"body: form {said!r} needs a 2-D .npy of shape (n, {want}) = {cols}; got {arr.shape}",
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


def check_form(form: str, k: int, d: int, field: str | None = None) -> dict[str, tuple]:
    """The shapes of ``form``'s arrays for this field (:func:`~flatserve.flats.form_shapes`);
    a form that cannot give its flats (rays for planes, points for lines) is refused
    naming the ``field`` and what it holds (:func:`kind_of`)."""
    try:
        return form_shapes(form, k, d)
    except InvalidInputError as exc:
        if field is None or form not in FORMS:
            raise
        raise type(exc)(f"{exc} (field {field!r} holds {kind_of(k, d)})", exc.argument) from None


def decode(body: bytes, content_type: str | None, form: str | None, *, k: int, d: int,
           channels: int | None, max_rows: int, max_json_bytes: int | None = None,
           field: str | None = None) -> tuple[Flats, np.ndarray | None, dict]:
    """Parse a batch body into ``(flats, values or None, the JSON object or {})``.

    ``channels=None``: a query (no values); else an upload of ``(n, channels)``
    values. Shapes, finite values, equal row counts, at least one row and at
    most ``max_rows`` are checked here, once. A flat of the wrong shape is
    refused naming the ``field`` and what it holds (:func:`kind_of`).
    """
    kind = body_kind(content_type)
    check_body(body, kind)
    extra: dict = {}
    # what a legitimate body can need once read as float64: max_rows rows of the
    # widest form (Q, r) plus the values; larger declared arrays are refused unread
    max_bytes = max_rows * 8 * (d * d + d + (channels or 0))
    if kind == "json":
        if max_json_bytes is not None:
            check_json_size(body, max_json_bytes)
        raw = load_json(body)
        _check_json_members(raw, body, upload=channels is not None)
        form = form or raw.get("form")
        extra = raw
    elif kind == "npz":
        raw = load_npz(body, max_bytes=max_bytes, max_rows=max_rows)
        _check_members(raw, upload=channels is not None, json=False)
    else:
        if form is None:
            form = {1: "rays", 0: "points"}.get(k)
            if form is None:
                raise InvalidInputError("form: required with application/x-npy", "form")
        check_form(form, k, d, field)
        raw = split_columns(load_npy(body, max_bytes=max_bytes, max_rows=max_rows), form, k, d,
                            channels)
    if form is not None and form not in FORMS:
        raise InvalidInputError(f"form: one of {tuple(FORMS)}, got {form!r}", "form")
    form = form or infer_form(raw)
    if form is None:
        raise InvalidInputError(f"body: give {forms_in_words()}", "body")
    check_form(form, k, d, field)
    nrows = _rows(raw, form)
    note(rows=nrows)
    if nrows > max_rows:
        raise BatchTooLargeError(f"{nrows} rows in one request; the limit is {max_rows}")
    try:
        flats = Flats.from_arrays(raw, k=k, d=d, form=form, min_rows=1)
    except InvalidInputError as exc:
        if "expected shape" not in str(exc):
            raise
        whose = f"field {field!r} holds " if field is not None else "expected "
        raise type(exc)(f"{exc} ({whose}{kind_of(k, d)})", exc.argument) from None
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

#: the most bytes orjson writes for one number of an answer, with its separator
#: (``-1.2345678901234567e-300,``): the estimate of a JSON answer's size
JSON_BYTES_PER_NUMBER = 25


def check_answer(rows: int, per_row: int, kind: str, *, max_json: int, max_binary: int,
                 bytes_per_number: int = 8, bulk: str = "") -> None:
    """Refuse (413) an answer of ``rows`` rows of ``per_row`` numbers before it is
    computed: as JSON (``kind`` ``"json"``) over ``max_json`` bytes (the
    ``max_json_answer_bytes`` setting), as binary over ``max_binary``
    (``max_answer_bytes``), at ``bytes_per_number`` bytes a number. The message
    names the estimate, the limit, the rows that fit and ``bulk``: where to go
    instead."""
    json = kind == "json"
    each = per_row * (JSON_BYTES_PER_NUMBER if json else bytes_per_number)
    limit = max_json if json else max_binary
    size = rows * each
    if size <= limit:
        return
    setting = "FLATSERVE_MAX_JSON_ANSWER_BYTES" if json else "FLATSERVE_MAX_ANSWER_BYTES"
    fits = max(limit // max(each, 1), 0)
    raise AnswerTooLargeError(
        f"the answer would be up to {size:,} bytes{' of JSON' if json else ''} ({rows:,} rows "
        f"of {per_row} numbers); the limit is {limit:,} ({setting}): "
        + (f"{bulk}, or send" if bulk else "send") + f" at most {fits:,} rows a request")


def query_numbers(kind: str, channels: int, ndim: int, weights: bool,
                  status: bool = False) -> int:
    """Numbers per row of a query's answer (see :func:`query_response`)."""
    per = channels + 1 + (kind != "npy" or status)  # values, inside (+ status)
    return per + (2 * (ndim + 1) if weights else 0)


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def query_response(accept: str | None, values, inside, status, ids=None, weights=None, *,
                   npy_status: bool = False) -> Response:
    """A query's answer per ``Accept``: JSON and ``.npz`` carry every array by name;
    ``.npy`` is one array of rows ``values | inside [| ids | weights] [| status]``
    (``status`` only with ``npy_status``, the query's ``status=true``)."""
    kind = accept_kind(accept)
    if kind == "npy":
        cols = [np.asarray(values), np.asarray(inside)]
        if ids is not None:
            cols.append(np.asarray(ids))
        if weights is not None:
            cols.append(np.asarray(weights))
        if npy_status:
            cols.append(np.asarray(status))
        return Response(_npy.columns_to_buffer(cols), media_type=NPY)
    if kind == "npz":
        arrs = {"values": values, "inside": inside, "status": status}
        if ids is not None:
            arrs["ids"] = ids
        if weights is not None:
            arrs["weights"] = weights
        return Response(npz_bytes(arrs), media_type=NPZ)
    return model_body(QueryResponse, values=values, inside=inside, status=status,
                      **({} if ids is None else {"ids": ids}),
                      **({} if weights is None else {"weights": weights}))
