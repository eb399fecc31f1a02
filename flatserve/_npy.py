"""``.npy`` bytes in and out, without copies or pickles (shared by the service
and the client; the header of a given dtype and shape is built/parsed once)."""
from __future__ import annotations

import functools
import io
import math

import numpy as np

#: Largest accepted ``.npy`` header (NumPy's own headers are far smaller).
MAX_HEADER_BYTES = 65536


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
    cols = [c.reshape(c.shape[0], -1) if c.ndim != 1 else c[:, None] for c in cols]
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


@functools.lru_cache(maxsize=256)
def _parse(head: bytes):
    buf = io.BytesIO(head)
    version = np.lib.format.read_magic(buf)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(buf)
    elif version in ((2, 0), (3, 0)):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(buf)
    else:
        raise ValueError(f"unsupported .npy version {version}")
    return dtype, shape, fortran, buf.tell()


def header(body: bytes):
    """``(dtype, shape, fortran_order, data offset)`` of ``.npy`` bytes; ValueError if bad."""
    if len(body) < 10 or body[:6] != b"\x93NUMPY":
        raise ValueError("no .npy magic")
    n = (10 + int.from_bytes(body[8:10], "little")) if body[6] == 1 else (
        12 + int.from_bytes(body[8:12], "little"))
    if n > len(body) or n > MAX_HEADER_BYTES:
        raise ValueError("truncated .npy header")
    return _parse(bytes(body[:n]))


def from_bytes(body: bytes, dtype, shape, fortran: bool, offset: int) -> np.ndarray:
    """The array a parsed header describes, as a view of ``body``; ValueError if sizes differ."""
    count = math.prod(shape)
    if len(body) - offset != count * dtype.itemsize:
        raise ValueError(f".npy data is {len(body) - offset} bytes, header says {count * dtype.itemsize}")
    arr = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
    return arr.reshape(shape, order="F" if fortran else "C")
