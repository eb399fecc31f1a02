"""``.npy`` bytes in and out, without copies or pickles (shared by the service
and the client; the header of a given dtype and shape is built/parsed once)."""
from __future__ import annotations

import functools
import io
import math

import numpy as np

#: Largest accepted ``.npy`` header, in bytes (NumPy writes about 128 for the arrays
#: flatserve exchanges; a longer one is refused before it is parsed).
MAX_HEADER_BYTES = 4096


@functools.lru_cache(maxsize=256)
def _head(descr: str, shape: tuple) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def to_bytes(arr: np.ndarray) -> bytes:
    """One array as ``.npy`` bytes (C order)."""
    arr = np.ascontiguousarray(arr)
    return _head(np.lib.format.dtype_to_descr(arr.dtype), arr.shape) + arr.tobytes()


def columns_to_buffer(cols: list[np.ndarray]) -> memoryview:
    """``.npy`` bytes of the array ``[c0 | c1 | ...]`` (columns side by side, each
    (n,) or (n, w); float32 if they all fit, else float64), written straight into
    one buffer: no concatenated copy and no second copy for the header."""
    # (widths from the shapes, not -1: zero rows have a width too)
    cols = [c.reshape(c.shape[0], math.prod(c.shape[1:])) if c.ndim != 1 else c[:, None]
            for c in cols]
    n = cols[0].shape[0]
    width = sum(c.shape[1] for c in cols)
    dt = np.dtype(np.result_type(np.float32, *cols))
    head = _head(np.lib.format.dtype_to_descr(dt), (n, width))
    buf = np.empty(len(head) + n * width * dt.itemsize, np.uint8)  # header: multiple of 64
    buf[:len(head)] = np.frombuffer(head, np.uint8)
    out = buf[len(head):].view(dt).reshape(n, width)
    j = 0
    for c in cols:
        out[:, j:j + c.shape[1]] = c
        j += c.shape[1]
    return memoryview(buf)


MAGIC = b"\x93NUMPY"

#: Leading bytes of formats sometimes sent where an ``.npy`` belongs (for messages).
_OTHER_MAGIC = {b"PK\x03\x04": "a zip archive", b"PK\x05\x06": "an empty zip archive",
                b"\x1f\x8b": "gzip data", b"{": "JSON text?", b"[": "JSON text?"}


def _what(prefix: bytes) -> str:
    for magic, what in _OTHER_MAGIC.items():
        if prefix.startswith(magic):
            return f"no .npy magic ({what})"
    return f"no .npy magic (starts with {bytes(prefix[:8])!r})"


def header_size(prefix: bytes) -> int:
    """Length of an ``.npy`` header (magic, version, length field, dict) from its first bytes.

    Parameters
    ----------
    prefix : bytes
        At least the first 10 bytes (version 1) or 12 bytes (versions 2 and 3).

    Returns
    -------
    int
        Offset of the array data, at most :data:`MAX_HEADER_BYTES`.

    Raises
    ------
    ValueError
        No ``.npy`` magic, an unsupported version, a truncated prefix or a header
        longer than :data:`MAX_HEADER_BYTES`.
    """
    if len(prefix) < 10 or prefix[:6] != MAGIC:
        if MAGIC.startswith(bytes(prefix[:6])):
            raise ValueError(f"truncated .npy header: {len(prefix)} bytes")
        raise ValueError(_what(prefix))
    major, minor = prefix[6], prefix[7]
    if major == 1:
        n = 10 + int.from_bytes(prefix[8:10], "little")
    elif major in (2, 3):
        if len(prefix) < 12:
            raise ValueError(f"truncated .npy header: {len(prefix)} bytes")
        n = 12 + int.from_bytes(prefix[8:12], "little")
    else:
        raise ValueError(f"unsupported .npy version {major}.{minor}")
    if n > MAX_HEADER_BYTES:
        raise ValueError(f".npy header declares {n} bytes; at most {MAX_HEADER_BYTES} are accepted")
    return n


@functools.lru_cache(maxsize=256)
def _parse(head: bytes):
    buf = io.BytesIO(head)
    try:
        version = np.lib.format.read_magic(buf)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(buf)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(buf)
        else:
            raise ValueError(f"unsupported .npy version {version[0]}.{version[1]}")
    except ValueError:
        raise
    except Exception as exc:  # the dict is untrusted text: any parse failure is bad input
        raise ValueError(f"unreadable .npy header: {type(exc).__name__}: {exc}") from None
    for dim in shape:  # NumPy lets bools and negative numbers through
        if type(dim) is not int or dim < 0:
            raise ValueError(f".npy shape {shape!r} holds {dim!r}: dimensions are "
                             "non-negative integers")
    return dtype, shape, fortran, buf.tell()


def header(body: bytes):
    """Parse the header of ``.npy`` bytes.

    Parameters
    ----------
    body : bytes
        The whole ``.npy`` (or at least its header).

    Returns
    -------
    tuple
        ``(dtype, shape, fortran_order, data offset)``; every dimension of ``shape``
        is a non-negative ``int``.

    Raises
    ------
    ValueError
        Anything wrong with the magic, version, length or dict of the header.
    """
    n = header_size(body[:12])
    if n > len(body):
        raise ValueError(f"truncated .npy header: it declares {n} bytes, the body has {len(body)}")
    return _parse(bytes(body[:n]))


def read_header(stream):
    """Parse an ``.npy`` header from a binary stream, reading no byte of the data.

    Parameters
    ----------
    stream : binary file-like
        Positioned at the start of an ``.npy`` (e.g. a member of a zip archive opened
        with :meth:`zipfile.ZipFile.open`); left positioned at the data.

    Returns
    -------
    tuple
        ``(dtype, shape, fortran_order, data offset)`` as :func:`header`.

    Raises
    ------
    ValueError
        As :func:`header`; at most :data:`MAX_HEADER_BYTES` are read.
    """
    head = stream.read(10)
    if len(head) == 10 and head[:6] == MAGIC and head[6] in (2, 3):
        head += stream.read(2)
    n = header_size(head)
    head += stream.read(n - len(head))
    if len(head) < n:
        raise ValueError(f"truncated .npy header: it declares {n} bytes, the data ends after {len(head)}")
    return _parse(head)


def from_bytes(body: bytes, dtype, shape, fortran: bool, offset: int) -> np.ndarray:
    """The array a parsed header describes, as a view of ``body`` (no copy).

    Parameters
    ----------
    body : bytes
        The whole ``.npy``.
    dtype, shape, fortran, offset
        As returned by :func:`header`.

    Returns
    -------
    numpy.ndarray
        A read-only view of ``body``.

    Raises
    ------
    ValueError
        The data is shorter or longer than the header declares.
    """
    count = math.prod(shape)
    have, want = len(body) - offset, count * dtype.itemsize
    if have < want:
        raise ValueError(f".npy data is truncated: {have} bytes, the header declares {want}")
    if have > want:
        raise ValueError(f".npy data is {have} bytes, the header declares {want}: "
                         f"{have - want} bytes too many")
    arr = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
    return arr.reshape(shape, order="F" if fortran else "C")
