"""Hand-made hostile ``.npy`` / ``.npz`` bodies for the codec and service tests.

Zips are written byte by byte here (not with :mod:`zipfile`) so that a test can
declare sizes, CRCs, names and compression methods that do not match the data,
and deflate bombs are built from one repeated block so that a body declaring
gigabytes takes milliseconds to make.
"""
from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass

import numpy as np

STORED, DEFLATED, BZIP2 = 0, 8, 12


def npy(arr) -> bytes:
    """A real ``.npy`` as NumPy writes it."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(arr), allow_pickle=False)
    return buf.getvalue()


def npy_header(d, version: int = 1, length: int | None = None) -> bytes:
    """An ``.npy`` header holding ``d`` (a dict, written with ``repr``, or raw text/bytes).

    ``length`` overrides the header-length field (absurd lengths); the dict is padded
    to a multiple of 64 bytes as NumPy pads it.
    """
    text = d if isinstance(d, bytes) else (d if isinstance(d, str) else repr(d)).encode("utf-8")
    lenbytes = 2 if version == 1 else 4
    pad = (64 - (8 + lenbytes + len(text) + 1) % 64) % 64
    text += b" " * pad + b"\n"
    n = len(text) if length is None else length
    return b"\x93NUMPY" + bytes([version, 0]) + n.to_bytes(lenbytes, "little") + text


def descr_header(shape, descr: str = "<f8", fortran: bool = False) -> bytes:
    return npy_header({"descr": descr, "fortran_order": fortran, "shape": shape})


@dataclass
class Member:
    """One zip entry; ``file_size``/``crc``/``compress_size`` default to the truth."""

    name: str | bytes
    data: bytes  # uncompressed content (ignored when ``raw`` is given)
    method: int = STORED
    raw: bytes | None = None  # the bytes stored in the archive, already compressed
    file_size: int | None = None
    crc: int | None = None
    compress_size: int | None = None
    flags: int = 0


def _compress(m: Member) -> bytes:
    if m.raw is not None:
        return m.raw
    if m.method == DEFLATED:
        c = zlib.compressobj(6, zlib.DEFLATED, -15)
        return c.compress(m.data) + c.flush()
    return m.data


def raw_zip(members: list[Member], comment: bytes = b"") -> bytes:
    """A zip archive of ``members`` exactly as declared (no zip64)."""
    out, central = bytearray(), bytearray()
    for m in members:
        name = m.name.encode("utf-8") if isinstance(m.name, str) else m.name
        flags = m.flags | (0x800 if isinstance(m.name, str) and not m.name.isascii() else 0)
        payload = _compress(m)
        crc = zlib.crc32(m.data) if m.crc is None else m.crc
        usize = len(m.data) if m.file_size is None else m.file_size
        csize = len(payload) if m.compress_size is None else m.compress_size
        offset = len(out)
        out += struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, flags, m.method, 0, 0x21,
                           crc, csize, usize, len(name), 0) + name + payload
        central += struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, 20, flags, m.method, 0, 0x21,
                               crc, csize, usize, len(name), 0, 0, 0, 0, 0, offset) + name
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(members), len(members),
                      len(central), len(out), len(comment))
    return bytes(out + central + end + comment)


def npz(method: int = STORED, **arrays) -> bytes:
    """An ``.npz`` of ``arrays`` (members ``<name>.npy``)."""
    return raw_zip([Member(f"{k}.npy", npy(v), method) for k, v in arrays.items()])


def zeros_bomb(rows: int, cols: int = 1, descr: str = "<f8") -> Member:
    """A deflated member ``<name>.npy`` declaring (rows, cols) zeros, cheap to make.

    The data is one 1 MiB block of zeros deflated once and repeated (each block is
    ended by a full flush, so blocks are independent); ``rows * cols * itemsize``
    must be a multiple of 1 MiB. The CRC is left wrong (computing it would cost
    as much as inflating): a reader that inflates before judging the header fails
    late, and one that judges first never reaches it.
    """
    head = descr_header((rows, cols), descr)
    nbytes = rows * cols * np.dtype(descr).itemsize
    block = 2**20
    if nbytes % block:
        raise ValueError("rows * cols * itemsize must be a multiple of 1 MiB")
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    first = c.compress(head) + c.flush(zlib.Z_FULL_FLUSH)
    zeros = c.compress(bytes(block)) + c.flush(zlib.Z_FULL_FLUSH)
    raw = first + zeros * (nbytes // block) + b"\x03\x00"  # an empty final block
    return Member("bomb.npy", b"", DEFLATED, raw=raw, file_size=len(head) + nbytes, crc=0)
