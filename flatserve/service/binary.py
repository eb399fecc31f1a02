"""Readers of ``.npy`` and ``.npz`` request bodies that a hostile client cannot
turn into a crash, a 500 or unbounded memory.

An ``.npz`` body (``numpy.savez`` or ``numpy.savez_compressed``) is read by
:func:`load_npz`, which judges every member's header before it inflates any data:

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

"""
from __future__ import annotations

import io
import math
import struct
import zipfile
import zlib

import numpy as np

from .. import _npy
from ..errors import InvalidInputError
from .status import BatchTooLargeError, BodyTooLargeError

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
    flatserve.service.status.LimitExceededError
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
    flatserve.service.status.LimitExceededError
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


