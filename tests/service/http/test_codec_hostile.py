"""Hostile ``.npy`` / ``.npz`` bodies at the codec level: every one is refused with
:class:`~flatserve.errors.InvalidInputError` (422) or
:class:`~flatserve.service.status.LimitExceededError` (413) naming what is wrong, before
any large allocation; valid bodies read as NumPy reads them."""
from __future__ import annotations

import io
import time
import tracemalloc
import warnings
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flatserve import _npy
from flatserve.errors import InvalidInputError
from flatserve.service import binary
from flatserve.service.status import LimitExceededError
from flatserve.service.status import BatchTooLargeError, BodyTooLargeError
from tests.harness.hostile import (BZIP2, DEFLATED, STORED, Member, descr_header, npy,
                                  npy_bodies, npy_header, npz, npz_bodies, raw_zip, zeros_bomb)

ALLOWED = (InvalidInputError, LimitExceededError)
MiB = 2**20

FUZZ = settings(max_examples=250, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much])


def peak_bytes(fn, *args, **kw):
    """``(result or exception, peak traced bytes)`` of ``fn(*args, **kw)``."""
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        try:
            out = fn(*args, **kw)
        except Exception as exc:  # noqa: BLE001 - the caller judges the type
            out = exc
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# -- .npy ---------------------------------------------------------------------------
def f8(shape, descr="<f8", fortran=False, data: bytes | None = None) -> bytes:
    n = int(np.prod([max(int(s), 0) for s in shape])) * np.dtype(descr).itemsize
    return descr_header(shape, descr, fortran) + (bytes(n) if data is None else data)


BAD_NPY = [  # (body, words the message must hold)
    (f8((True, 7), data=bytes(56)), "True"),
    (f8((7, False), data=bytes(0)), "False"),
    (f8((-1, 7), data=bytes(56)), "-1"),
    (f8((-1, -7), data=bytes(56)), "-1"),
    (npy_header({"descr": "<f8", "fortran_order": False, "shape": [2, 3]}) + bytes(48), "shape"),
    (npy_header({"descr": "<f8", "fortran_order": False, "shape": 6}) + bytes(48), "shape"),
    (npy_header({"descr": "<f8", "fortran_order": False, "shape": (2.0, 3)}) + bytes(48), "shape"),
    (npy_header({"descr": "<f8", "fortran_order": 0, "shape": (2, 3)}) + bytes(48), "fortran"),
    (npy_header({"descr": "<f8", "shape": (2, 3)}) + bytes(48), "header"),
    (npy_header({"descr": 5, "fortran_order": False, "shape": (2, 3)}) + bytes(48), "descr"),
    (npy_header({"descr": "<f8", "fortran_order": False, "shape": (2, 3), "x": 1}), "header"),
    (npy_header("{[1]: 2}") + bytes(48), "header"),
    (npy_header("(" * 300 + ")" * 300) + bytes(48), "header"),
    (npy_header({"descr": "<f8", "fortran_order": False, "shape": (2, 3)}, length=65535) + bytes(48),
     "header declares"),
    (npy_header({"descr": "<f8", "fortran_order": False, "shape": (2, 3)}, version=2,
                length=2**32 - 1) + bytes(48), "header declares"),
    (npy_header({"descr": "<f8", "fortran_order": False, "shape": (2, 3)}, version=7), "version"),
    (b"\x93NUMPX\x01\x00" + bytes(100), "magic"),
    (b"PK\x03\x04" + bytes(100), "zip"),
    (b"\x93NUM", "truncated"),
    (b"", "truncated"),
    (f8((2, 3), data=bytes(47)), "truncated"),
    (f8((2, 3), data=bytes(49)), "too many"),
    (f8((2, 3), "|O", data=bytes(48)), "real number"),
    (f8((2, 3), "|b1"), "real number"),
    (f8((2, 3), "<c16"), "real number"),
    (f8((2, 3), "<M8[s]"), "real number"),
    (npy_header({"descr": [("a", "<f8")], "fortran_order": False, "shape": (2,)}) + bytes(16),
     "real number"),
    (f8((1, 1, 1, 1, 2)), "dimensions"),
]


@pytest.mark.parametrize("body,words", BAD_NPY)
def test_malformed_npy_is_invalid_input_naming_the_body(body, words):
    with pytest.raises(InvalidInputError) as err:
        binary.load_npy(body)
    assert err.value.argument == "body"
    assert str(err.value).startswith("body: ") and words.lower() in str(err.value).lower()


@pytest.mark.parametrize("shape,max_rows,cls", [((2**40, 6), None, BodyTooLargeError),
                                                ((2**40, 6), 2000, BatchTooLargeError),
                                                ((0, 2**62), None, BodyTooLargeError),
                                                ((0, 2**20, 2**20, 2**20), 2000, BodyTooLargeError),
                                                ((2001, 6), 2000, BatchTooLargeError),
                                                ((2000, 6, 11), 2000, BodyTooLargeError)])
def test_huge_npy_shapes_are_413_before_anything_is_read(shape, max_rows, cls):
    body = descr_header(shape) + bytes(48)
    (out, peak) = peak_bytes(binary.load_npy, body, max_bytes=MiB, max_rows=max_rows)
    assert isinstance(out, cls), out
    assert peak < MiB
    with pytest.raises(LimitExceededError):  # the default cap (no caller limits) too
        binary.load_npy(descr_header((2**40, 6)) + bytes(48))


def test_npy_limits_let_valid_bodies_through():
    a = np.arange(12.0).reshape(4, 3)
    np.testing.assert_array_equal(binary.load_npy(npy(a), max_bytes=96, max_rows=4), a)
    with pytest.raises(BodyTooLargeError):
        binary.load_npy(npy(a), max_bytes=95)
    with pytest.raises(BatchTooLargeError):
        binary.load_npy(npy(a), max_rows=3)


def test_npy_truncated_at_every_length():
    body = npy(np.arange(35.0).reshape(5, 7))
    for n in range(len(body)):
        with pytest.raises(InvalidInputError):
            binary.load_npy(body[:n])
    assert binary.load_npy(body).shape == (5, 7)


def test_client_header_parser_refuses_bools_and_negatives():
    """``_npy.header`` is shared with the client: its errors stay ValueError."""
    for shape in [(True, 7), (-2, 7)]:
        with pytest.raises(ValueError, match="non-negative"):
            _npy.header(descr_header(shape) + bytes(56))


# -- .npz: valid bodies ---------------------------------------------------------------
@pytest.mark.parametrize("method", [STORED, DEFLATED])
def test_valid_npz_reads_as_numpy_reads_it(method):
    arrays = {"origins": np.arange(12.0).reshape(4, 3),
              "directions": np.asfortranarray(np.arange(12, dtype=">f4").reshape(4, 3)),
              "values": np.arange(4, dtype=np.uint16)[:, None],
              "A": np.arange(24, dtype=np.int8).reshape(2, 3, 4, 1),
              "b": np.float16([1.5, 2]), "e": np.zeros((0, 3)), "s": np.float64(3.0)}
    for body in (npz(method, **arrays), _savez(arrays, method)):
        got = binary.load_npz(body)
        assert list(got) == list(arrays)
        for k, a in arrays.items():
            assert got[k].dtype == a.dtype and got[k].shape == a.shape, k
            np.testing.assert_array_equal(got[k], a)
        assert got["directions"].flags.f_contiguous
        assert binary.load_npz(body, max_bytes=sum(a.nbytes for a in arrays.values()) + 24,
                              max_rows=4)


def _savez(arrays, method):
    buf = io.BytesIO()
    (np.savez_compressed if method == DEFLATED else np.savez)(buf, **arrays)
    return buf.getvalue()


def test_npz_truncated_at_every_length():
    for method in (STORED, DEFLATED):
        body = npz(method, origins=np.arange(6.0).reshape(2, 3), directions=np.ones((2, 3)))
        for n in range(len(body)):
            with pytest.raises(InvalidInputError):
                binary.load_npz(body[:n])


# -- .npz: bombs and limits -------------------------------------------------------------
def test_npz_bomb_is_refused_before_inflating():
    """Two deflated members declaring 1 GiB each in a 2 MiB body: 413 at once."""
    a, b = zeros_bomb(2**27), zeros_bomb(2**27)
    a.name, b.name = "origins.npy", "directions.npy"
    body = raw_zip([a, b])
    assert len(body) < 3 * MiB
    t0 = time.perf_counter()
    out, peak = peak_bytes(binary.load_npz, body)
    assert isinstance(out, BodyTooLargeError), out
    assert "origins.npy" in str(out) and str(binary.DEFAULT_MAX_BYTES) in str(out)
    assert peak < 4 * MiB and time.perf_counter() - t0 < 2
    out, peak = peak_bytes(binary.load_npz, body, max_bytes=2**31, max_rows=10**6)
    assert isinstance(out, BatchTooLargeError) and "origins.npy" in str(out), out
    assert peak < 4 * MiB


def test_npz_byte_cap_counts_all_members():
    body = npz(DEFLATED, origins=np.zeros((1000, 3)), directions=np.zeros((1000, 3)))
    assert len(binary.load_npz(body, max_bytes=48000)) == 2
    with pytest.raises(BodyTooLargeError, match="directions.npy"):
        binary.load_npz(body, max_bytes=47999)
    with pytest.raises(BodyTooLargeError, match="origins.npy"):
        binary.load_npz(body, max_bytes=23999)


def test_small_npz_declaring_huge_sizes_stays_small_in_memory():
    bodies = [raw_zip([Member("origins.npy", descr_header((2**28, 3)) + bytes(64))]),
              raw_zip([Member("origins.npy", descr_header((2**28, 3)) + bytes(64), DEFLATED)]),
              raw_zip([Member("origins.npy", descr_header((2**20, 3)) + bytes(64), DEFLATED,
                              file_size=128 + 2**20 * 24)]),
              raw_zip([Member("origins.npy", descr_header((2**20, 3)) + bytes(64),
                              file_size=128 + 2**20 * 24)]),
              raw_zip([Member("origins.npy", descr_header((2**20, 3)) + bytes(64), DEFLATED,
                              file_size=2**32 - 1)])]
    for body in bodies:
        out, peak = peak_bytes(binary.load_npz, body, max_bytes=64 * MiB)
        assert isinstance(out, ALLOWED), out
        assert peak < 2 * MiB, (out, peak)


def test_many_tiny_members_are_refused_before_zipfile_reads_them():
    body = raw_zip([Member(f"a{i}.npy", b"") for i in range(20000)])
    out, peak = peak_bytes(binary.load_npz, body)
    assert isinstance(out, InvalidInputError) and "members" in str(out), out
    assert peak < len(body)
    with pytest.raises(InvalidInputError, match="17 members"):
        binary.load_npz(npz(**{f"a{i}": np.zeros(1) for i in range(17)}))
    assert len(binary.load_npz(npz(**{f"a{i}": np.zeros(1) for i in range(16)}))) == 16


# -- .npz: malformed members ---------------------------------------------------------------
GOOD = npy(np.zeros((2, 3)))
NESTED = npz(origins=np.zeros((2, 3)))


@pytest.mark.parametrize("members,words,loc", [
    ([Member("origins.npy", NESTED)], ["'origins.npy'", "nested zip"], "origins"),
    ([Member("origins.npy", NESTED, DEFLATED)], ["'origins.npy'", "nested zip"], "origins"),
    ([Member("inner.npz", NESTED)], ["'inner.npz'", "not an .npy member"], "body"),
    ([Member("origins.npy", GOOD), Member("readme.txt", b"hi")], ["'readme.txt'", ".npy"], "body"),
    ([Member("origins.npy", b"raw bytes, no header")], ["'origins.npy'", "magic"], "origins"),
    ([Member("origins.npy", GOOD), Member("origins.npy", GOOD)], ["'origins.npy'", "more than once"],
     "origins"),
    ([Member("d/", b"")], ["'d/'", "directory"], "body"),
    ([Member(".npy", GOOD)], ["'.npy'", "empty"], "body"),
    ([Member("origins.npy", GOOD, flags=1)], ["'origins.npy'", "encrypted"], "origins"),
    ([Member("origins.npy", GOOD, BZIP2, raw=GOOD)], ["'origins.npy'", "method 12"], "origins"),
    ([Member("origins.npy", f8((True, 3)))], ["'origins.npy'", "True"], "origins"),
    ([Member("origins.npy", f8((2, 3), "|O"))], ["'origins.npy'", "real number"], "origins"),
    ([Member("origins.npy", f8((1, 1, 1, 1, 3)))], ["'origins.npy'", "dimensions"], "origins"),
    ([Member("origins.npy", GOOD[:60])], ["'origins.npy'", "truncated"], "origins"),
    ([Member("origins.npy", GOOD, file_size=len(GOOD) + 8)], ["'origins.npy'", "zip entry declares"],
     "origins"),
    ([Member("origins.npy", GOOD, file_size=len(GOOD) - 8)], ["'origins.npy'", "zip entry declares"],
     "origins"),
    ([Member("origins.npy", GOOD[:-8])], ["'origins.npy'", "zip entry declares"], "origins"),
    ([Member("origins.npy", GOOD + bytes(8))], ["'origins.npy'", "zip entry declares"], "origins"),
    # the zip's size agrees with the header, the deflated stream ends early
    ([Member("origins.npy", GOOD[:-8], DEFLATED, file_size=len(GOOD))], ["'origins.npy'"], "origins"),
    ([Member("origins.npy", GOOD, crc=1)], ["'origins.npy'", "CRC"], "origins"),
    ([Member("origins.npy", GOOD, DEFLATED, crc=1)], ["'origins.npy'", "CRC"], "origins"),
    ([Member("origins.npy", GOOD, compress_size=10**6)], ["'origins.npy'", "stored in"], "origins"),
    ([Member("origins.npy", GOOD, DEFLATED, file_size=10**6)], ["'origins.npy'", "can hold"],
     "origins"),
    ([Member("origins.npy", GOOD, DEFLATED, raw=b"\xff" * 300)], ["'origins.npy'"], "origins"),
])
def test_malformed_npz_names_the_member_and_what_is_wrong(members, words, loc):
    with pytest.raises(InvalidInputError) as err:
        binary.load_npz(raw_zip(members))
    for w in words:
        assert w in str(err.value), err.value
    assert err.value.argument == loc


def test_npy_body_sent_as_npz():
    with pytest.raises(InvalidInputError, match="application/x-npy"):
        binary.load_npz(GOOD)


# -- property-based fuzz (the strategies: tests/harness/hostile.py) ----------------------
def assert_codec_judges(fn, body, **kw):
    """Only the two documented error families escape, and nothing big is allocated."""
    out, peak = peak_bytes(fn, body, **kw)
    if isinstance(out, BaseException) and not isinstance(out, ALLOWED):
        raise AssertionError(f"{type(out).__name__} escaped the codec: {out}") from out
    assert peak < 2 * MiB + 4 * len(body), peak
    return out


@FUZZ
@given(npy_bodies())
def test_fuzz_npy(body):
    out = assert_codec_judges(binary.load_npy, body)
    if isinstance(out, np.ndarray):  # whatever is accepted is a consistent real array
        assert out.dtype.kind in "fiu" and out.ndim <= binary.MAX_NDIM
        dtype, shape, _, offset = _npy.header(body)
        assert out.shape == shape and offset + out.nbytes == len(body)


@FUZZ
@given(npz_bodies(), st.sampled_from([None, 4096]), st.sampled_from([None, 3]))
def test_fuzz_npz(body, max_bytes, max_rows):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = assert_codec_judges(binary.load_npz, body, max_bytes=max_bytes, max_rows=max_rows)
    if isinstance(out, dict):  # whatever is accepted is what NumPy reads, within the limits
        with np.load(io.BytesIO(body), allow_pickle=False) as ref:
            assert sorted(ref.files) == sorted(out)
            for k, a in out.items():
                assert a.dtype.kind in "fiu" and a.ndim <= binary.MAX_NDIM
                assert max_rows is None or a.ndim == 0 or a.shape[0] <= max_rows
                np.testing.assert_array_equal(ref[k], a)
        assert sum(a.nbytes for a in out.values()) <= (max_bytes or binary.DEFAULT_MAX_BYTES)


def test_fuzz_strategies_reach_every_outcome():
    """The generators make valid bodies, 422s and 413s alike (else the fuzz is blind)."""
    seen = set()

    @settings(max_examples=300, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(npz_bodies())
    def run(body):
        try:
            binary.load_npz(body, max_bytes=4096, max_rows=3)
            seen.add("ok")
        except InvalidInputError:
            seen.add("422")
        except LimitExceededError:
            seen.add("413")

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run()
    assert seen == {"ok", "422", "413"}


def test_zipfile_agrees_the_bodies_are_zips():
    """The hand-made zips are zips to :mod:`zipfile` (the helpers are not the bug)."""
    body = raw_zip([Member("origins.npy", GOOD, DEFLATED), Member("readme.txt", b"hi")])
    with zipfile.ZipFile(io.BytesIO(body)) as zf:
        assert zf.testzip() is None and zf.read("origins.npy") == GOOD
