"""Hand-made hostile ``.npy`` / ``.npz`` bodies for the codec and service tests.

Zips are written byte by byte here (not with :mod:`zipfile`) so that a test can
declare sizes, CRCs, names and compression methods that do not match the data,
and deflate bombs are built from one repeated block so that a body declaring
gigabytes takes milliseconds to make. :func:`npy_bodies` and :func:`npz_bodies` are
Hypothesis strategies of fuzzed bodies (the property tests of the codec and the routes).
"""
from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass

import numpy as np
from hypothesis import strategies as st

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


# -- property-based fuzz: Hypothesis strategies of bodies-----------------------------------------------------------------
REAL = ["<f8", "<f4", "<f2", ">f8", "|u1", "<i8", ">i2", "<u4"]
OTHER = ["|b1", "<c16", "|O", "<U3", "|V8", "|S0", "<M8[s]", "<f16", 5, None, "", "garbage",
         [("a", "<f8")], ("<f8", (2,))]
DIMS = st.one_of(st.integers(0, 5), st.integers(0, 5), st.integers(-3, 2**70), st.booleans(),
                 st.sampled_from([2**27, 2**31, 2**63 - 1, 2**64, -(2**63)]))
SHAPES = st.one_of(st.lists(DIMS, max_size=6).map(tuple), st.lists(DIMS, max_size=6).map(tuple),
                   st.lists(DIMS, max_size=3), st.integers(-3, 10), st.none(), st.text(max_size=5),
                   st.tuples(st.floats(allow_nan=True), st.integers(0, 3)))
FORTRAN = st.sampled_from([True, False, True, False, 0, 1, None, "x"])


def rarely(draw, n: int = 4) -> bool:
    """True about once in ``n`` draws."""
    return draw(st.integers(0, n - 1)) == 0


@st.composite
def header_dicts(draw):
    d = {"descr": draw(st.sampled_from(REAL) if not rarely(draw, 3) else
                       st.sampled_from(OTHER) | st.text(max_size=6)),
         "fortran_order": draw(FORTRAN), "shape": draw(SHAPES)}
    if rarely(draw, 6):
        d.pop(draw(st.sampled_from(sorted(d))))
    if rarely(draw, 6):
        d[draw(st.text(max_size=4))] = draw(st.integers())
    return d


@st.composite
def npy_bodies(draw):
    """An ``.npy``-ish body: a fuzzed header (dict, text or bytes), then data."""
    kind = draw(st.sampled_from(["dict", "dict", "dict", "text", "real", "bytes"]))
    if kind == "real":  # a real .npy, cut or padded anywhere
        shape = tuple(draw(st.lists(st.integers(0, 4), max_size=4)))
        body = npy(np.zeros(shape, draw(st.sampled_from(REAL))))
        cut = draw(st.integers(0, len(body) + 8))
        return body[:cut] + bytes(max(0, cut - len(body)))
    if kind == "bytes":
        return draw(st.binary(max_size=300))
    version = draw(st.sampled_from([1, 2, 3, 0, 4]) if rarely(draw) else st.just(1))
    length = None
    if rarely(draw, 6):
        length = draw(st.integers(0, 2**16 - 1 if version == 1 else 2**32 - 1))
    d = draw(st.text(max_size=80)) if kind == "text" else draw(header_dicts())
    head = npy_header(d, version, length)
    exact = _exact_size(d)
    if exact is not None and not rarely(draw, 3):  # data of the size the header declares
        return head + bytes(exact)
    if rarely(draw, 3):
        return head + draw(st.binary(max_size=200))
    return head + bytes(draw(st.sampled_from([0, 8, 16, 24, 48, 96, 4096])))


def _exact_size(d) -> int | None:
    """Data bytes a header dict declares, when that is small and computable."""
    try:
        n = int(np.prod([int(x) for x in d["shape"]])) * np.dtype(d["descr"]).itemsize
    except Exception:  # noqa: BLE001 - any odd header: no exact size
        return None
    return n if 0 <= n <= 4096 else None


VALID_NAMES = ["origins.npy", "directions.npy", "values.npy", "Q.npy", "r.npy"]
ODD_NAMES = st.sampled_from(["x.txt", "d/", ".npy", "a/b.npy", "origins", "ä.npy", ""]) | st.text(
    max_size=8)


@st.composite
def member_contents(draw):
    kind = draw(st.sampled_from(["npy", "npy", "fuzz", "fuzz", "bytes", "nested", "huge"]))
    if kind == "npy":
        shape = tuple(draw(st.lists(st.integers(0, 5), max_size=3)))
        return npy(np.ones(shape, draw(st.sampled_from(["<f8", "<f4", ">i4", "|u1", "|b1"]))))
    if kind == "fuzz":
        return draw(npy_bodies())
    if kind == "bytes":
        return draw(st.binary(max_size=200))
    if kind == "nested":
        return npz(draw(st.sampled_from([STORED, DEFLATED])), origins=np.zeros((2, 3)))
    rows = draw(st.sampled_from([4, 2**20, 2**27, 2**40, 2**62]))
    return descr_header((rows, 3)) + draw(st.binary(max_size=64))


@st.composite
def npz_bodies(draw):
    """A zip of fuzzed members, sometimes with lying sizes/CRCs, flipped bytes or cut."""
    members, names = [], draw(st.permutations(VALID_NAMES))
    for i in range(draw(st.integers(0, 3))):
        data = draw(member_contents())
        name = names[i]
        if rarely(draw, 8):
            name = draw(ODD_NAMES | st.just(names[0]))  # odd or duplicate
        m = Member(name, data, draw(st.sampled_from([STORED, DEFLATED])))
        if rarely(draw, 12):
            m.method, m.raw = BZIP2, data
        if rarely(draw, 5):  # lie about the sizes or the CRC
            m.file_size = draw(st.sampled_from([0, len(data) + 1, max(0, len(data) - 1),
                                                2**31, 2**32 - 1]))
        if rarely(draw, 8):
            m.crc = draw(st.integers(0, 2**32 - 1))
        if rarely(draw, 8):
            m.compress_size = draw(st.integers(0, 2**32 - 1))
        members.append(m)
    body = bytearray(raw_zip(members))
    if rarely(draw, 8):
        for _ in range(draw(st.integers(1, 3))):  # flip bytes
            if body:
                body[draw(st.integers(0, len(body) - 1))] = draw(st.integers(0, 255))
    if rarely(draw, 8):
        body = body[:draw(st.integers(1, len(body) - 1))]  # never empty: b"" is tested apart
    return bytes(body)
