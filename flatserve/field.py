"""A function sampled on flats: a basis + a triangulation + sample values.

This is the paper's Sec. 5 pipeline in one object. Samples (flats with values)
are turned into affine coordinates in a :class:`~flatserve.basis.Basis`
(Sec. 4, Eq. 9 and 12); samples whose coordinates do not round-trip lie outside
the chart the basis spans and are *rejected with a reason*, never triangulated
silently. The accepted coordinates are embedded in R^(m-1) through a regular
simplex (Sec. 5) and inserted into a CGAL Delaunay triangulation whose vertices
carry the values. A query flat goes through the same coordinates and embedding,
is located by a walk, and its value is the barycentric interpolation of the
values at the vertices of its simplex.
"""
from __future__ import annotations

import functools
import json
import math
import os
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import flats as _flats
from ._validate import as_array
from .basis import Basis
from .coordinates import AMBIGUOUS, NOT_REPRESENTABLE, OK, ROUNDTRIP_TOL, SINGULAR
from .embedding import embed
from .errors import InvalidInputError, SnapshotError
from .triangulation import Triangulation

__all__ = ["Field", "AddResult", "PreparedBatch", "QueryResult"]

_MAGIC = b"FSFIELD\x00"
_VERSION = 1
_HEADER = struct.Struct("<8sIQ")  # magic, version, metadata length

_REASONS = {
    NOT_REPRESENTABLE: "not representable: the coordinates do not round-trip "
    "(the flat lies outside the chart the basis spans)",
    SINGULAR: "singular: the coordinate system of the basis is singular at this flat",
    AMBIGUOUS: "ambiguous: the recombined flat has coinciding eigenvalues "
    "(eigen-gap below tolerance)",
}


@dataclass(frozen=True)
class AddResult:
    """Outcome of :meth:`Field.add`.

    Attributes
    ----------
    accepted : int
        Number of input rows inserted (duplicates included: their value
        replaced the earlier one).
    rejected : (j,) int64
        Indices (into the input batch) of rows that were not inserted.
    reasons : list of str
        One human-readable reason per rejected row.
    duplicates : int
        Accepted rows whose embedded coordinates coincided with an existing
        vertex; policy: the later value replaces the earlier one.
    nsamples : int
        Number of distinct samples (vertices) in the field afterwards.
    """

    accepted: int
    rejected: np.ndarray
    reasons: list[str]
    duplicates: int
    nsamples: int


@dataclass(frozen=True)
class PreparedBatch:
    """A batch charted by :meth:`Field.prepare` and not yet inserted.

    Attributes
    ----------
    nrows : int
        Rows in the input batch.
    x : (a, D) float64
        Embedded coordinates of the accepted rows.
    values : (a, C) float64
        Their values.
    rejected : (j,) int64
        Indices (into the input batch) of rows that will not be inserted.
    reasons : list of str
        One reason per rejected row.
    """

    nrows: int
    x: np.ndarray
    values: np.ndarray
    rejected: np.ndarray
    reasons: list[str]

    @property
    def accepted(self) -> int:
        return int(self.x.shape[0])


@dataclass(frozen=True)
class QueryResult:
    """Outcome of :meth:`Field.query`.

    Attributes
    ----------
    values : (q, C) float64
        Interpolated values; NaN where ``inside`` is False (unless
        ``outside="clamp"`` found a hull facet).
    inside : (q,) bool
        The query's coordinates round-trip and lie inside the convex hull of
        the samples.
    status : (q,) int8
        Coordinate status per query (:data:`flatserve.coordinates.OK`, ...).
    ids : (q, D+1) int64 or None
        Sample ids of the simplex's vertices (−1 for none), if requested.
    weights : (q, D+1) float64 or None
        Barycentric weights, if requested.
    """

    values: np.ndarray
    inside: np.ndarray
    status: np.ndarray
    ids: np.ndarray | None = None
    weights: np.ndarray | None = None


class Field:
    """Values sampled on k-flats in R^d, interpolated piecewise linearly.

    Parameters
    ----------
    basis : Basis
        The m flats whose affine coordinates chart the samples.
    channels : int
        Number of values per sample (1 for grey, 3 for RGB).
    roundtrip_tol : float
        Largest round-trip residual (see :func:`flatserve.coordinates.coordinates`)
        for which a sample's or query's coordinates are trusted.

    Examples
    --------
    >>> import numpy as np, flatserve
    >>> basis = flatserve.Basis.around_axis(axis=2, scale=0.01)
    >>> field = flatserve.Field(basis, channels=1)
    >>> rng = np.random.default_rng(0)
    >>> eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (2000, 3))
    >>> screen = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    >>> res = field.add_rays(eyes, screen - eyes, screen[:, :1])
    >>> out = field.query_rays(eyes[:5], screen[:5] - eyes[:5])
    """

    def __init__(self, basis: Basis, channels: int = 1, *, roundtrip_tol: float = ROUNDTRIP_TOL):
        if not isinstance(basis, Basis):
            raise InvalidInputError(f"basis: expected a flatserve.Basis, got {type(basis).__name__}", "basis")
        if not (isinstance(channels, (int, np.integer)) and channels >= 1):
            raise InvalidInputError(f"channels: expected a positive integer, got {channels!r}", "channels")
        if not (np.isfinite(roundtrip_tol) and roundtrip_tol > 0):
            raise InvalidInputError(f"roundtrip_tol: expected a positive number, got {roundtrip_tol!r}", "roundtrip_tol")
        self.basis = basis
        self.channels = int(channels)
        self.roundtrip_tol = float(roundtrip_tol)
        self._tri = Triangulation(basis.m - 1)
        self._nrejected = 0
        self._lock = threading.Lock()  # serialises writers; the triangulation guards readers

    # ------------------------------------------------------------------ sizes
    @property
    def k(self) -> int:
        return self.basis.k

    @property
    def d(self) -> int:
        return self.basis.d

    @property
    def ndim(self) -> int:
        """Dimension of the triangulation, m − 1."""
        return self.basis.m - 1

    @property
    def nsamples(self) -> int:
        """Distinct samples stored (= vertices of the triangulation)."""
        return self._tri.npoints

    nvertices = nsamples

    @property
    def nsimplex(self) -> int:
        return self._tri.nsimplex

    @property
    def nrejected(self) -> int:
        """Total samples rejected by :meth:`add` so far."""
        return self._nrejected

    @property
    def triangulation(self) -> Triangulation:
        return self._tri

    # ------------------------------------------------------------ internals
    def _check_flats(self, Q, r):
        Q = as_array(Q, "Q", (None, self.d, self.d))
        r = as_array(r, "r", (Q.shape[0], self.d))
        return Q, r

    def _values(self, values, n: int) -> np.ndarray:
        v = np.asarray(values)
        if v.ndim == 1 and self.channels == 1:
            v = v[:, None]
        return as_array(v, "values", (n, self.channels))

    def _chart(self, Q=None, r=None, *, rays=None):
        """Coordinates, status and embedded points of flats (rows).

        ``rays=(origins, directions)`` takes the lines' fast path (no Q built).
        """
        if rays is not None:
            coords = self.basis.coordinates_rays(*rays, roundtrip_tol=self.roundtrip_tol)
        else:
            coords = self.basis.coordinates(Q, r, roundtrip_tol=self.roundtrip_tol, check=False)
        status = np.asarray(coords.status, dtype=np.int8)
        ok = status == OK
        x = embed(coords.weights[ok]) if ok.any() else np.empty((0, self.ndim))
        return status, ok, x, coords

    # --------------------------------------------------------------- writers
    def prepare(self, Q, r, values, *, defer: bool = False
                ) -> "PreparedBatch | Callable[[], PreparedBatch]":
        """First half of :meth:`add`: validate and chart a batch, without inserting.

        Computes the coordinates (paper Sec. 4) and their embedding, and decides
        which rows are accepted and why the others are not. Reads only the
        basis, so it needs no lock and may run while the field is queried or
        written. :meth:`insert_prepared` completes it. (The service uses the
        split to acknowledge an upload before the slower Delaunay insert.)

        Parameters
        ----------
        Q : (n, d, d) float
            Flats' quadrics (paper Eq. 3); (C1) must hold.
        r : (n, d) float
            Flats' offsets; (C2) must hold.
        values : (n, C) float, or (n,) when C == 1
        defer : bool
            Validate now (raising :class:`~flatserve.errors.InvalidInputError`
            for bad input) but return a zero-argument callable that computes
            the coordinates when called. Once validation has passed, charting
            cannot reject the batch as a whole: every row gets a status. (The
            service commits the batch durably while the coordinates are
            computed.)

        Returns
        -------
        PreparedBatch, or a callable returning one when ``defer``
        """
        Q, r = self._check_flats(Q, r)
        _flats.validate(Q, r, self.k)
        return self._prepare(self._values(values, Q.shape[0]), defer, Q=Q, r=r)

    def prepare_parametric(self, A, b, values, *, defer: bool = False
                           ) -> "PreparedBatch | Callable[[], PreparedBatch]":
        """:meth:`prepare` for flats in parametric form, A (n, d, k) and b (n, d)."""
        Q, r = _flats.from_parametric(A, b)
        return self.prepare(Q, r, values, defer=defer)

    def prepare_rays(self, origins, directions, values, *, defer: bool = False
                     ) -> "PreparedBatch | Callable[[], PreparedBatch]":
        """:meth:`prepare` for lines (k = 1): origins, directions (n, d); values (n, C)."""
        self._require_lines()
        o, v, _ = _flats._check_rays(origins, directions)
        return self._prepare(self._values(values, o.shape[0]), defer, rays=(o, v))

    def _prepare(self, values, defer: bool = False, **chart):
        if defer:
            return functools.partial(self._prepare, values, False, **chart)
        status, ok, x, coords = self._chart(**chart)
        rejected = np.flatnonzero(~ok).astype(np.int64)
        return PreparedBatch(
            nrows=int(status.shape[0]),
            x=np.ascontiguousarray(x),
            values=np.ascontiguousarray(values[ok]),
            rejected=rejected,
            reasons=self._reasons(status, coords, rejected),
        )

    def insert_prepared(self, batch: "PreparedBatch") -> AddResult:
        """Second half of :meth:`add`: insert a :meth:`prepare`-d batch.

        The whole batch is inserted under the triangulation's write lock, so a
        concurrent query sees all of it or none of it.
        """
        if not isinstance(batch, PreparedBatch) or batch.x.shape[1:] != (self.ndim,) or (
            batch.values.shape[1:] != (self.channels,)
        ):
            raise InvalidInputError("batch: expected a PreparedBatch made by this field", "batch")
        with self._lock:
            duplicates = 0
            if batch.accepted:
                duplicates = int(self._tri.insert(batch.x, batch.values).n_duplicates)
            self._nrejected += int(batch.rejected.size)
            return AddResult(
                accepted=batch.accepted,
                rejected=batch.rejected,
                reasons=batch.reasons,
                duplicates=duplicates,
                nsamples=self.nsamples,
            )

    def add(self, Q, r, values) -> AddResult:
        """Add samples given as flats (Q, r) with their values.

        Rows whose coordinates do not round-trip are rejected with a reason
        (they lie outside the chart the basis spans); the others are embedded
        and inserted. Equivalent to ``insert_prepared(prepare(Q, r, values))``.

        Parameters
        ----------
        Q : (n, d, d) float
            Flats' quadrics (paper Eq. 3); (C1) must hold.
        r : (n, d) float
            Flats' offsets; (C2) must hold.
        values : (n, C) float, or (n,) when C == 1

        Returns
        -------
        AddResult
        """
        return self.insert_prepared(self.prepare(Q, r, values))

    def add_parametric(self, A, b, values) -> AddResult:
        """Add samples given in parametric form; see :func:`flatserve.flats.from_parametric`."""
        return self.insert_prepared(self.prepare_parametric(A, b, values))

    def add_rays(self, origins, directions, values) -> AddResult:
        """Add samples on lines (k = 1) through ``origins`` along ``directions``.

        Parameters
        ----------
        origins, directions : (n, d) float
        values : (n, C) float, or (n,) when C == 1
        """
        return self.insert_prepared(self.prepare_rays(origins, directions, values))

    def _reasons(self, status: np.ndarray, coords, rows: np.ndarray) -> list[str]:
        """One human-readable reason per rejected row (``rows`` index the batch)."""
        tol = f"{self.roundtrip_tol:.3g}"
        resid = getattr(coords, "residual", None)
        res = resid[rows].tolist() if resid is not None else [math.nan] * rows.size
        return [
            _REASONS.get(st, f"status {st}")
            + (f" (residual {r:.3g}, tolerance {tol})" if math.isfinite(r) else "")
            for st, r in zip(status[rows].tolist(), res)
        ]

    def _require_lines(self):
        if self.k != 1:
            raise InvalidInputError(f"rays are lines (k=1) but this field holds {self.k}-flats", "origins")

    # --------------------------------------------------------------- readers
    def query(
        self,
        Q,
        r,
        *,
        outside: str = "nan",
        order: str = "hilbert",
        threads: int | None = None,
        return_weights: bool = False,
    ) -> QueryResult:
        """Interpolate the field at flats (Q, r).

        Parameters
        ----------
        Q : (q, d, d) float
        r : (q, d) float
        outside : {"nan", "clamp"}
            Value for queries outside the samples' convex hull; see
            :meth:`flatserve.Triangulation.interpolate`. Queries whose
            coordinates do not round-trip are always NaN and not inside.
        order : {"hilbert", "given"}
            Walk order; "given" keeps the caller's (coherent) order.
        threads : int, optional
            Threads for locate/interpolate (default all cores).
        return_weights : bool
            Also return the simplex's sample ids and barycentric weights.
        """
        Q, r = self._check_flats(Q, r)
        _flats.validate(Q, r, self.k)
        return self._query(Q.shape[0], dict(Q=Q, r=r), outside, order, threads, return_weights)

    def _query(self, n, chart, outside, order, threads, return_weights) -> QueryResult:
        if outside not in ("nan", "clamp"):
            raise InvalidInputError(f"outside: expected 'nan' or 'clamp', got {outside!r}", "outside")
        status, ok, x, _ = self._chart(**chart)
        values = np.full((n, self.channels), np.nan)
        inside = np.zeros(n, dtype=bool)
        ids = weights = None
        if return_weights:
            D = self.ndim
            ids = np.full((n, D + 1), -1, dtype=np.int64)
            weights = np.full((n, D + 1), np.nan)
        if ok.any() and self._tri.npoints > 0:
            v, ins = self._tri.interpolate(x, outside=outside, order=order, threads=threads)
            values[ok] = v
            inside[ok] = ins
            if return_weights:
                loc = self._tri.locate(x, order=order, threads=threads)
                ids[ok] = loc.ids
                weights[ok] = loc.weights
        return QueryResult(values=values, inside=inside, status=status, ids=ids, weights=weights)

    def query_parametric(self, A, b, **kwargs) -> QueryResult:
        """:meth:`query` for flats in parametric form (A, b)."""
        Q, r = _flats.from_parametric(A, b)
        return self.query(Q, r, **kwargs)

    def query_rays(
        self,
        origins,
        directions,
        *,
        outside: str = "nan",
        order: str = "hilbert",
        threads: int | None = None,
        return_weights: bool = False,
    ) -> QueryResult:
        """:meth:`query` for lines through ``origins`` along ``directions``, (q, d) each.

        Takes the lines' fast coordinate path (no (Q, r) is built).
        """
        self._require_lines()
        o, v, _ = _flats._check_rays(origins, directions)
        return self._query(o.shape[0], dict(rays=(o, v)), outside, order, threads, return_weights)

    # ----------------------------------------------------------- persistence
    def _metadata(self) -> dict:
        return {
            "version": _VERSION,
            "k": self.k,
            "d": self.d,
            "channels": self.channels,
            "roundtrip_tol": self.roundtrip_tol,
            "nrejected": self._nrejected,
            "basis_Q": self.basis.Q.tolist(),
            "basis_r": self.basis.r.tolist(),
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the field (basis, values, triangulation) to one file.

        Layout: 8-byte magic, uint32 version, uint64 metadata length, the
        metadata as JSON (basis, channels, counters), then the native
        triangulation snapshot (see :meth:`flatserve.Triangulation.save`).
        Not atomic by itself: the service writes to a temporary file and
        renames it.
        """
        meta = json.dumps(self._metadata()).encode()
        with self._lock:
            payload = self._tri.to_bytes()
        with open(path, "wb") as fh:
            fh.write(_HEADER.pack(_MAGIC, _VERSION, len(meta)))
            fh.write(meta)
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Field":
        """Read a field written by :meth:`save`; raises SnapshotError if damaged."""
        data = Path(path).read_bytes()
        if len(data) < _HEADER.size:
            raise SnapshotError(f"{path}: truncated field file ({len(data)} bytes)")
        magic, version, mlen = _HEADER.unpack_from(data)
        if magic != _MAGIC:
            raise SnapshotError(f"{path}: not a flatserve field file (bad magic)")
        if version != _VERSION:
            raise SnapshotError(f"{path}: field file version {version}, expected {_VERSION}")
        start = _HEADER.size
        if start + mlen > len(data):
            raise SnapshotError(f"{path}: truncated field metadata")
        try:
            meta = json.loads(data[start : start + mlen])
            basis = Basis(np.array(meta["basis_Q"]), np.array(meta["basis_r"]), int(meta["k"]))
        except (ValueError, KeyError, TypeError) as exc:
            raise SnapshotError(f"{path}: corrupted field metadata: {exc}") from None
        obj = cls(basis, int(meta["channels"]), roundtrip_tol=float(meta["roundtrip_tol"]))
        obj._tri = Triangulation.from_bytes(data[start + mlen :])
        if obj._tri.ndim != obj.ndim:
            raise SnapshotError(f"{path}: triangulation dimension {obj._tri.ndim} does not match basis")
        obj._nrejected = int(meta.get("nrejected", 0))
        return obj

    def __repr__(self) -> str:
        return (
            f"Field(k={self.k}, d={self.d}, channels={self.channels}, "
            f"nsamples={self.nsamples}, nsimplex={self.nsimplex}, nrejected={self.nrejected})"
        )
