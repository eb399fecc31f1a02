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

``application/x-npz``: an ``.npz`` (``numpy.savez`` or ``numpy.savez_compressed``)
with named arrays: ``origins`` + ``directions``, or ``A`` + ``b``, or ``Q`` + ``r``;
``values`` for uploads. The archive is read by :func:`load_npz`, which judges every
member's header before it inflates any data:

* every member is named ``<array>.npy`` (the array's name plus ``.npy``), a name
  appears once, and there are at most :data:`MAX_MEMBERS` members; directories,
  other files and nested zips are refused (422 naming the member);
* every member is an ``.npy`` (version 1, 2 or 3; header at most
  ``flatserve._npy.MAX_HEADER_BYTES``) of a real number type (kind ``f``, ``i`` or
  ``u``, any width and byte order; read as float64 later; no objects, no bools, no
  complex), C or Fortran order, at most :data:`MAX_NDIM` dimensions, each a
  non-negative integer;
* members are stored or deflated (no encryption, no other compression), and the
  zip's uncompressed size of a member equals its ``.npy`` header plus the data the
  header declares; data shorter or longer than that, or failing its CRC, is a 422;
* limits, judged on the headers before inflating: no member has more rows
  (``shape[0]``) than the caller's row limit (413), and all members together
  declare at most the caller's byte cap (413; by default :data:`DEFAULT_MAX_BYTES`
  or the body's length, whichever is larger; an empty array's zero dimensions count
  as one). Each member is then inflated in steps of 1 MiB into an array of the
  declared size, so no member can grow past what its header declared.

``application/x-npy`` bodies follow the same header rules (:func:`load_npy`): a
malformed header (magic, version, length, dict, shape) or data of another length
than declared is a 422 naming the body, a declared size beyond the limits a 413.

Query responses per ``Accept``: ``application/json`` (default), ``application/x-npy``
(shape ``(q, C + 1 [+ 2 (D+1)])`` float64: values, inside as 0/1, then if asked
sample ids and barycentric weights), ``application/x-npz`` (``values``,
``inside``, ``status``, ``ids``, ``weights``).
"""
from __future__ import annotations

import io
import re
import math
import struct
import zipfile
import zlib

import numpy as np
import orjson
from fastapi import Response

from .. import _npy

from .._validate import as_array
from ..errors import BatchTooLargeError, BodyTooLargeError, InvalidInputError
from ..flats import FORMS, Flats, form_shapes, infer_form
from .errors import ApiError
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
#: Byte cap of a binary body's arrays when the caller gives none: this, or the
#: body's own length when that is larger (an uncompressed body is already in memory).
DEFAULT_MAX_BYTES = 256 * 2**20
#: Most dimensions of one array (the flats' forms need at most 3).
MAX_NDIM = 4
#: Most members of one ``.npz`` (a body needs at most 3 arrays).
MAX_MEMBERS = 16
_CHUNK = 2**20  # bytes inflated per step
_DEFLATE_MAX_RATIO = 1032  # deflate's best case: 258 bytes from one 2-bit code
_LOCAL, _CENTRAL, _END, _END64_LOC = b"PK\x03\x04", b"PK\x01\x02", b"PK\x05\x06", b"PK\x06\x07"


def _cap(max_bytes: int | None, body) -> int:
    return max(DEFAULT_MAX_BYTES, len(body)) if max_bytes is None else max_bytes


def check_npy_header(name: str, dtype: np.dtype, shape: tuple, *, max_bytes: int,
                     max_rows: int | None = None) -> int:
    """Judge a parsed ``.npy`` header before any of its data is read.

    Parameters
    ----------
    name : str
        What the message names (``"body"``, ``"member 'origins.npy'"``).
    dtype : numpy.dtype
        Declared dtype: a real number type (kind ``f``, ``i`` or ``u``).
    shape : tuple
        Declared shape: at most :data:`MAX_NDIM` non-negative ``int`` dimensions.
    max_bytes : int
        Most data bytes the array may declare; each zero dimension counts as one, so
        an empty array cannot declare absurd dimensions either.
    max_rows : int, optional
        Most rows (``shape[0]``).

    Returns
    -------
    int
        The data size the header declares, in bytes.

    Raises
    ------
    flatserve.errors.InvalidInputError
        Not a real number dtype, too many dimensions, a dimension that is not a
        non-negative integer (422).
    BatchTooLargeError
        More than ``max_rows`` rows (413).
    BodyTooLargeError
        More than ``max_bytes`` declared (413).
    """

    if dtype.kind not in "fiu" or dtype.hasobject:
        raise InvalidInputError(f"{name}: .npy dtype {dtype} is not a real number type "
                                "(float or integer)", _argument(name))
    if not isinstance(shape, tuple) or len(shape) > MAX_NDIM:
        raise InvalidInputError(f"{name}: .npy shape {shape!r} has more than {MAX_NDIM} "
                                "dimensions", _argument(name))
    for dim in shape:
        if type(dim) is not int or dim < 0:
            raise InvalidInputError(f"{name}: .npy shape {shape!r} holds {dim!r}: dimensions "
                                    "are non-negative integers", _argument(name))
    if max_rows is not None and shape and shape[0] > max_rows:
        raise BatchTooLargeError(f"{name}: {shape[0]} rows in one request; the limit is {max_rows}")
    bound = math.prod(max(dim, 1) for dim in shape) * dtype.itemsize
    if bound > max_bytes:
        raise BodyTooLargeError(f"{name}: .npy shape {shape} of {dtype} declares {bound} bytes; "
                                f"the limit is {max_bytes}")
    return math.prod(shape) * dtype.itemsize


def _argument(name: str) -> str:
    """``loc`` of an error about ``name`` ("body", "member 'origins.npy'" -> "origins")."""
    if name.startswith("member ") and name.endswith(".npy'"):
        return name[len("member '"):-len(".npy'")] or "body"
    return "body" if name.startswith("member ") else name


def load_npy(body: bytes, name: str = "body", *, max_bytes: int | None = None,
             max_rows: int | None = None) -> np.ndarray:
    """Parse one ``.npy`` without copying its data.

    Parameters
    ----------
    body : bytes
        The ``.npy`` bytes.
    name : str
        What error messages name.
    max_bytes : int, optional
        Most data bytes the header may declare; by default :data:`DEFAULT_MAX_BYTES`
        or ``len(body)``, whichever is larger.
    max_rows : int, optional
        Most rows (``shape[0]``) the header may declare.

    Returns
    -------
    numpy.ndarray
        A read-only view of ``body`` (any real number dtype, C or Fortran order).

    Raises
    ------
    flatserve.errors.InvalidInputError
        Anything malformed: magic, version, header, dtype, shape, data length (422).
    flatserve.errors.LimitExceededError
        The header declares more than the limits (413), judged before the data.
    """
    try:
        dtype, shape, fortran, offset = _npy.header(body)
    except ValueError as exc:
        raise InvalidInputError(f"{name}: not a valid .npy array: {exc}", _argument(name)) from None
    check_npy_header(name, dtype, shape, max_bytes=_cap(max_bytes, body), max_rows=max_rows)
    try:
        return _npy.from_bytes(body, dtype, shape, fortran, offset)
    except ValueError as exc:
        raise InvalidInputError(f"{name}: {exc}", _argument(name)) from None


#: What a damaged or hostile zip can raise from :mod:`zipfile` and :mod:`zlib`.
_ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, EOFError, OSError,
               ValueError, NotImplementedError, RuntimeError, OverflowError, struct.error)


def _central_entries_bound(body) -> int | None:
    """At most how many central-directory entries :class:`zipfile.ZipFile` can read.

    Found as :mod:`zipfile` finds it (the end record, then the directory before it)
    but counting signatures only, so that a body of tiny entries is refused before
    ``zipfile`` builds an object per entry. ``None`` when there is no end record.
    """
    size = len(body)
    if size >= 22 and body[size - 22:size - 18] == _END and body[size - 2:] == b"\0\0":
        end = size - 22
    else:
        end = body.rfind(_END, max(0, size - 22 - 65535))
        if end < 0 or size - end < 22:
            return None
    if end >= 20 and body[end - 20:end - 16] == _END64_LOC:
        start = 0  # zip64: the directory size comes from another record
    else:
        start = max(0, end - int.from_bytes(body[end + 12:end + 16], "little"))
    return body.count(_CENTRAL, start, end)


def load_npz(body: bytes, *, max_bytes: int | None = None, max_rows: int | None = None,
             max_members: int = MAX_MEMBERS) -> dict[str, np.ndarray]:
    """Read the arrays of an ``.npz`` body, judging every header before inflating anything.

    The rules are those of the module documentation: members named ``<array>.npy``,
    each an ``.npy`` of a real number type, stored or deflated, no duplicates, the
    zip's sizes agreeing with the ``.npy`` headers; the declared shapes are judged
    against the limits first, then each member is inflated incrementally into a
    preallocated array that nothing can overrun.

    Parameters
    ----------
    body : bytes
        The ``.npz`` (zip) bytes.
    max_bytes : int, optional
        Most data bytes all members together may declare; by default
        :data:`DEFAULT_MAX_BYTES` or ``len(body)``, whichever is larger.
    max_rows : int, optional
        Most rows (``shape[0]``) any member may declare.
    max_members : int
        Most members of the archive.

    Returns
    -------
    dict of str to numpy.ndarray
        Array name (member name without ``.npy``) to array, in archive order.

    Raises
    ------
    flatserve.errors.InvalidInputError
        A malformed archive or member (422), naming the member and what is wrong.
    flatserve.errors.LimitExceededError
        The headers declare more rows or bytes than the limits (413).
    """

    if not isinstance(body, bytes):
        body = bytes(body)
    cap = _cap(max_bytes, body)
    if body[:6] == _npy.MAGIC:
        raise InvalidInputError("body: an .npy, not an .npz: send it as application/x-npy", "body")
    bound = _central_entries_bound(body)
    if bound is not None and bound > max_members:
        raise InvalidInputError(f"body: the .npz holds {bound} members or more; at most "
                                f"{max_members} are accepted", "body")
    try:
        zf = zipfile.ZipFile(io.BytesIO(body))
    except _ZIP_ERRORS as exc:
        raise InvalidInputError(f"body: not a valid .npz (zip) archive: {exc}", "body") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise InvalidInputError(f"body: the .npz holds {len(infos)} members; at most "
                                    f"{max_members} are accepted", "body")
        seen: set[str] = set()
        for info in infos:  # names and zip flags: nothing is opened yet
            _check_member_entry(info, seen)
        heads, total = [], 0
        for info in infos:  # headers only, judged before any data is inflated
            what = f"member {info.filename!r}"
            try:
                with zf.open(info) as f:
                    prefix = f.read(4)
                    if prefix.startswith(_LOCAL) or prefix.startswith(_END):
                        raise InvalidInputError(f"{what}: a nested zip archive, not an .npy",
                                                _argument(what))
                    dtype, shape, fortran, offset = _npy.read_header(_Prefixed(prefix, f))
            except ValueError as exc:
                if isinstance(exc, InvalidInputError):
                    raise
                raise InvalidInputError(f"{what}: not a valid .npy: {exc}", _argument(what)) from None
            except _ZIP_ERRORS as exc:
                raise InvalidInputError(f"{what}: unreadable zip member: {exc}",
                                        _argument(what)) from None
            size = check_npy_header(what, dtype, shape, max_bytes=cap, max_rows=max_rows)
            total += size
            if total > cap:
                raise BodyTooLargeError(f"{what}: the .npz members declare {total} bytes or "
                                        f"more in all; the limit is {cap}")
            if offset + size != info.file_size:
                raise InvalidInputError(
                    f"{what}: the zip entry declares {info.file_size} bytes, its .npy header "
                    f"{offset} + {size} = {offset + size}", _argument(what))
            heads.append((info, what, dtype, shape, fortran, offset, size))
        return {info.filename[:-4]: _inflate(zf, info, what, dtype, shape, fortran, offset, size)
                for info, what, dtype, shape, fortran, offset, size in heads}


def _check_member_entry(info: zipfile.ZipInfo, seen: set) -> None:
    what = f"member {info.filename!r}"
    if info.filename.endswith("/"):
        raise InvalidInputError(f"{what}: a directory; an .npz holds .npy members only", "body")
    if not info.filename.endswith(".npy"):
        raise InvalidInputError(f"{what}: not an .npy member (names are <array>.npy)", "body")
    if info.filename == ".npy":
        raise InvalidInputError(f"{what}: the array name is empty", "body")
    if info.filename in seen:
        raise InvalidInputError(f"{what}: appears more than once", _argument(what))
    seen.add(info.filename)
    if info.flag_bits & 0x1:
        raise InvalidInputError(f"{what}: encrypted members are not accepted", _argument(what))
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise InvalidInputError(f"{what}: compression method {info.compress_type} is not "
                                "accepted (stored or deflated only)", _argument(what))
    if info.compress_type == zipfile.ZIP_STORED and info.compress_size != info.file_size:
        raise InvalidInputError(f"{what}: the zip entry declares {info.file_size} bytes, "
                                f"stored in {info.compress_size}", _argument(what))
    if info.file_size > _DEFLATE_MAX_RATIO * info.compress_size + 1024:
        raise InvalidInputError(f"{what}: the zip entry declares {info.file_size} bytes, more "
                                f"than {info.compress_size} deflated bytes can hold",
                                _argument(what))


class _Prefixed:
    """A stream whose first bytes were already read (``read`` only)."""

    def __init__(self, prefix: bytes, stream):
        self._prefix, self._stream = prefix, stream

    def read(self, n: int) -> bytes:
        head, self._prefix = self._prefix[:n], self._prefix[n:]
        return head + self._stream.read(n - len(head)) if n > len(head) else head


def _inflate(zf: zipfile.ZipFile, info: zipfile.ZipInfo, what: str, dtype: np.dtype,
             shape: tuple, fortran: bool, offset: int, size: int) -> np.ndarray:
    """One member's data, inflated step by step into an array of the declared size."""
    out = np.empty(math.prod(shape), dtype)
    buf = memoryview(out.view(np.uint8).reshape(-1)) if size else memoryview(b"")
    done = 0
    try:
        with zf.open(info) as f:
            f.read(offset)  # the header, judged already
            while done < size:
                got = f.readinto(buf[done:done + min(_CHUNK, size - done)])
                if not got:
                    break
                done += got
            extra = f.read(1) if done == size else b""
    except _ZIP_ERRORS as exc:
        raise InvalidInputError(f"{what}: corrupt data: {exc}", _argument(what)) from None
    if done < size:
        raise InvalidInputError(f"{what}: .npy data is truncated: {done} bytes, the header "
                                f"declares {size}", _argument(what))
    if extra:
        raise InvalidInputError(f"{what}: .npy data is longer than its header declares ({size} "
                                "bytes)", _argument(what))
    return out.reshape(shape, order="F" if fortran else "C")


def load_json(body: bytes) -> dict:
    try:
        obj = orjson.loads(body)
    except orjson.JSONDecodeError as exc:
        raise InvalidInputError(f"body: invalid JSON: {exc}", "body") from None
    if not isinstance(obj, dict):
        raise InvalidInputError("body: expected a JSON object", "body")
    return obj


_BOOLEAN = re.compile(rb"\b(true|false)\b")


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


def _check_json_members(raw: dict, body: bytes, *, upload: bool) -> None:
    """A JSON batch holds ``form``, one form's arrays (and ``values`` for uploads),
    nothing else; arrays hold numbers only (no strings, no booleans)."""
    allowed = {"form", *(n for names in FORMS.values() for n in names)}
    if upload:
        allowed.add("values")
    for name in raw:
        if name not in allowed:
            raise InvalidInputError(f"{name}: unknown member; a batch has form, "
                                    + ", ".join(sorted(allowed - {"form"})), name)
    if raw.get("form") is not None and not isinstance(raw["form"], str):
        raise InvalidInputError("form: expected a string", "form")
    for name, x in raw.items():
        if name != "form" and isinstance(x, list) and x:  # [] is judged with its shape later
            raw[name] = _json_array(x, name)
    # no member of a batch is a boolean: one is in an array (a quick scan first)
    m = _BOOLEAN.search(body) if b"true" in body or b"false" in body else None
    if m is not None:
        raise InvalidInputError(f"body: {m.group(0).decode()} is not a number", "body")


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
           channels: int | None, max_rows: int, max_json_bytes: int | None = None
           ) -> tuple[Flats, np.ndarray | None, dict]:
    """Parse a batch body into ``(flats, values or None, the JSON object or {})``.

    ``channels=None``: a query (no values); else an upload of ``(n, channels)``
    values. Shapes, finite values, equal row counts, at least one row and at
    most ``max_rows`` are checked here, once.
    """
    kind = body_kind(content_type)
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
    else:
        if form is None:
            if k == 1:
                form = "rays"
            else:
                raise InvalidInputError("form: required with application/x-npy", "form")
        raw = split_columns(load_npy(body, max_bytes=max_bytes, max_rows=max_rows), form, k, d,
                            channels)
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
