"""What the two kinds of field share, written once.

:class:`~flatserve.field.Field` (one chart) and
:class:`~flatserve.atlas_field.AtlasField` (a Field per chart, blended) both
derive from :class:`FieldBase`: the check of the values, ``prepare`` with its
``defer``, ``add``, ``save`` / ``load`` / ``to_bytes``, ``describe``, and the
one loop over a field's shards (:meth:`FieldBase._over_shards`). Their file
header (magic, version, metadata length, then the metadata as JSON) is read
and written here too, with its error messages. The contract the two kinds
offer is :class:`flatserve.contract.SampledField`.
"""
from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import struct
from pathlib import Path
from typing import Any, Callable, Collection, Iterable, Iterator, Sequence

import numpy as np

from ._validate import as_array
from .errors import InvalidInputError, SnapshotError
from .parallel import shard_pool

__all__ = ["FieldBase", "HEADER", "pack_header", "part_key", "read_header", "corrupted"]

#: Magic (8 bytes), version (uint32), metadata length (uint64): the start of a
#: field file of either kind.
HEADER = struct.Struct("<8sIQ")


def pack_header(magic: bytes, version: int, meta: dict) -> bytes:
    """The header and JSON metadata of a field file."""
    body = json.dumps(meta).encode()
    return HEADER.pack(magic, version, len(body)) + body


def read_header(data, *, magic: bytes, versions: Sequence[int], kind: str,
                source: str) -> tuple[int, dict, int]:
    """Check and parse the header of a field file.

    Parameters
    ----------
    data : bytes-like
        The whole file.
    magic : bytes
        The 8 bytes the file must start with.
    versions : sequence of int
        The versions this reader knows.
    kind : str
        Named in the messages (``"field"``, ``"atlas field"``).
    source : str
        Named first in the messages (a path).

    Returns
    -------
    version : int
    meta : dict
        The metadata JSON.
    offset : int
        Where the payload starts.

    Raises
    ------
    SnapshotError
        Truncated, another format (bad magic), an unknown version, damaged JSON.
    """
    if len(data) < HEADER.size:
        raise SnapshotError(f"{source}: truncated {kind} file ({len(data)} bytes)")
    got, version, mlen = HEADER.unpack_from(data)
    if got != magic:
        raise SnapshotError(f"{source}: not a flatserve {kind} file (bad magic)")
    if version not in versions:
        raise SnapshotError(f"{source}: {kind} file version {version}, expected "
                            + " or ".join(str(v) for v in versions))
    end = HEADER.size + mlen
    if end > len(data):
        raise SnapshotError(f"{source}: truncated {kind} metadata")
    try:
        meta = json.loads(bytes(data[HEADER.size:end]))
        if not isinstance(meta, dict):
            raise ValueError("not an object")
    except ValueError as exc:
        raise corrupted(kind, source, exc) from None
    return version, meta, end


def part_key(data) -> str:
    """The key of a snapshot part: the SHA-256 of its bytes (hex, 32 digits): the
    same bytes, the same key, so an unchanged shard's part is stored once and a
    damaged one is caught on reading."""
    return hashlib.sha256(data).hexdigest()[:32]


def write_part(stage: str | os.PathLike, key: str, blob: bytes) -> None:
    """A new snapshot part at ``<stage>/<key>``, fsync'd."""
    with open(os.path.join(stage, key), "wb") as out:
        out.write(blob)
        out.flush()
        os.fsync(out.fileno())


def read_part(parts: Callable[[str], Any], key: str, source: str, what: str):
    """``parts(key)``, checked against its key (:func:`part_key`).

    Raises
    ------
    SnapshotError
        ``"<source>: <what> <key> is damaged"`` when the bytes are not the key's.
    """
    blob = parts(key)
    if part_key(blob) != key:
        raise SnapshotError(f"{source}: {what} {key} is damaged (its bytes do not match its "
                            "key)")
    return blob


def corrupted(kind: str, source: str, exc: Exception) -> SnapshotError:
    """The error for metadata that parses but does not describe a field."""
    return SnapshotError(f"{source}: corrupted {kind} metadata: {exc}")


class FieldBase:
    """The code both kinds of field share (see :class:`flatserve.contract.SampledField`).

    A subclass provides ``channels``, ``shards``, ``_flats(flats)`` (check a
    batch, return it), ``_prepare(flats, values)``, ``insert_prepared``,
    ``write_to(fh)``, ``from_bytes(data, source=...)``, the sizes and
    ``_definition()`` (the ``atlas`` and ``charts`` parts of :meth:`describe`).
    """

    channels: int
    #: the answers blend several shards (ids / weights of shape (q, P, D+1))
    blends: bool = False
    #: the shards' triangulations are held in this process (a cluster front's
    #: ``RemoteField``: False, its answers come from other processes, :meth:`query_async`)
    holds_shards: bool = True
    #: bytes of snapshot parts the field's shards stored themselves for the last
    #: ``write_parts`` (0: every part was written to ``stage``)
    stored_bytes: int = 0

    # ------------------------------------------------ the unit of length (neutral)
    # A field whose unit of length is chosen from its first batch (an atlas field
    # made with ``unit="auto"``) overrides these; every other field has no unit to
    # choose: it never waits for one and ignores one offered.
    @property
    def unit_pending(self) -> bool:
        """The field's unit of length is still to be chosen from its first samples
        (False: it has one, or charts in no unit)."""
        return False

    @property
    def unit_from_data(self) -> bool:
        """The field may still take a unit of length (:meth:`settle_unit`)."""
        return False

    @property
    def unit(self) -> float | None:
        """The unit of length the field charts in; None while it is still to be
        chosen, and for a field without one (a one-chart field)."""
        return None

    def settle_unit(self, unit: float, *, if_empty: bool = False) -> bool:
        """Take ``unit`` as the field's unit of length while it may
        (:attr:`unit_from_data`); whether it changed anything (here: never)."""
        return False

    def in_unit(self, unit: float) -> Any:
        """What charts a batch in ``unit`` (a field that takes no unit: itself)."""
        return self

    # ------------------------------------------------------- counts (neutral)
    @property
    def own_samples(self) -> list[int] | None:
        """Per shard, the distinct samples whose nearest shard it is (their sum is
        ``nsamples``): a one-chart field's one shard owns them all. None only for an
        atlas field read from a file that did not record them."""
        return [int(self.nsamples)]  # type: ignore[attr-defined]

    @property
    def ntiles(self) -> int | None:
        """Tiles of the one chart's triangulation held here; None for a field of
        several charts."""
        return None

    def applied_counts(self, position: int, timeout: float) -> dict:
        """Once the batch at log ``position`` is applied where the shards live, the
        response's ``nsamples`` and ``duplicates`` counted there: ``{}`` for a field
        whose shards are held here (its insert counted them)."""
        return {}

    async def query_async(self, flats, **kw) -> Any:
        """:meth:`query` awaited: a field held here answers at once without waiting for
        an insert (``blocking=False``: None while a writer is in)."""
        return self.query(flats, blocking=False, **kw)  # type: ignore[attr-defined]

    # ------------------------------------------------------------------ writers
    def _values(self, values, n: int) -> np.ndarray:
        """``values`` as (n, C) float64 ((n,) accepted when C == 1)."""
        v = np.asarray(values)
        if v.ndim == 1 and self.channels == 1:
            v = v[:, None]
        return as_array(v, "values", (n, self.channels))

    def prepare(self, flats, values, *, defer: bool = False,
                only: Collection[int] | None = None) -> Any:
        """First half of :meth:`add`: chart a batch and decide its rows, without inserting.

        Reads only the field's definition (bases, atlas), so it may run while
        the field is queried or written; ``insert_prepared`` completes it.

        Parameters
        ----------
        flats : Flats
            ``n`` k-flats in R^d (validated when built).
        values : (n, C) float, or (n,) when C == 1
        defer : bool
            Validate now (raising :class:`~flatserve.errors.InvalidInputError`
            for bad input) but return a zero-argument callable that charts
            when called. Once validation has passed, charting cannot reject
            the batch as a whole: every row gets a decision.
        only : collection of int, optional
            Chart for these shards only (a shard held elsewhere is left out: its
            part of the batch is None). Each shard's part is what it is in the
            whole batch, so a shard inserting it holds the same bits as the
            whole field's; the batch's decisions then say only which rows no
            shard's domain holds. Default: every shard.

        Returns
        -------
        The field's prepared batch, or a callable returning one when ``defer``
        """
        flats = self._flats(flats)
        values = self._values(values, flats.n)
        if only is not None:
            only = frozenset(int(c) for c in only)
            if not only <= set(range(len(self.shards))):
                raise InvalidInputError(f"only: expected shard indices below "
                                        f"{len(self.shards)}, got {sorted(only)}", "only")
        if defer:
            return functools.partial(self._prepare, flats, values, only)
        return self._prepare(flats, values, only)

    def add(self, flats, values):
        """Add samples (a writer): ``insert_prepared(prepare(flats, values))``.

        Parameters
        ----------
        flats : Flats
            ``n`` k-flats in R^d, any form.
        values : (n, C) float, or (n,) when C == 1

        Returns
        -------
        AddResult
        """
        return self.insert_prepared(self.prepare(flats, values))

    def settle(self) -> None:
        """Finish what the inserts so far left pending (a writer): the exchange
        between the tiles of a chart in tiles
        (:meth:`flatserve.tiles.TiledTriangulation.settle`), run once for
        every insert since the last. Queries and snapshots settle first on their
        own; an owner that inserts in bursts calls it as a burst ends, so that no
        query waits for it. Nothing to do for charts without tiles.

        Examples
        --------
        >>> import numpy as np, flatserve
        >>> f = flatserve.Field(flatserve.Basis.around_axis(), tiles=2)
        >>> o, v = np.random.default_rng(0).normal(size=(2, 500, 3))
        >>> _ = f.add(flatserve.Flats.from_rays(o, v + [0, 0, 4]), np.ones(500))
        >>> f.triangulation.settled, f.settle(), f.triangulation.settled
        (False, None, True)
        """
        for shard in self.shards:
            shard.triangulation.settle()

    @staticmethod
    def _slice_rows(slice_rows) -> int | None:
        if slice_rows is not None and not (isinstance(slice_rows, (int, np.integer))
                                           and slice_rows >= 1):
            raise InvalidInputError(f"slice_rows: expected a positive integer or None, got "
                                    f"{slice_rows!r}", "slice_rows")
        return None if slice_rows is None else int(slice_rows)

    # ------------------------------------------------------------------ shards
    def _over_shards(self, fn: Callable[[Any, Any], Any],
                     work: Iterable[tuple[int, Any]]) -> Iterator[Any]:
        """``fn(shard, item)`` for each ``(shard index, item)`` of ``work``, in order.

        The one loop over a field's shards (prepare, insert, query, snapshot,
        restore), each shard at most once per call: on the process's shard
        pool (:func:`flatserve.parallel.shard_pool`, every core), the results
        in the order of ``work`` whatever the number of threads; remote shards
        would replace this loop only. Lazy, with a bounded window: a snapshot
        holds a few shards' bytes at a time, not the field's.
        """
        shards = self.shards
        return shard_pool().map(lambda w: fn(shards[w[0]], w[1]), work)

    def query_shards(self, work, **kw) -> list | None:
        """Each shard's answer on its own flats (a shard's half of ``query``:
        ``route_query`` and ``blend`` are the other): ``work`` is
        ``[(shard, flats), ...]``; per pair the shard's ``query(flats, **kw)``,
        None (the whole answer) when not ``blocking`` and a writer is in."""
        out = []
        for c, flats in work:
            res = self.shards[c].query(flats, **kw)
            if res is None:
                return None
            out.append(res)
        return out

    # ----------------------------------------------------------- description
    def describe(self) -> dict:
        """JSON-able summary, the same keys for both kinds of field.

        Returns
        -------
        dict
            ``nsamples`` (distinct samples), ``nstored`` (vertices over all
            shards), ``nsimplex``, ``nrejected``, ``duplication``
            (``nstored / nsamples``: 1.0 for a one-chart field, None while
            empty), ``shards`` (``[{"samples": int}, ...]``), ``atlas`` and
            ``charts`` (:func:`flatserve.contract.describe_definition`, with
            the charts' samples; None for a one-chart field).
        """
        n, stored = self.nsamples, self.nstored
        return {
            "nsamples": n, "nstored": stored, "nsimplex": self.nsimplex,
            "nrejected": self.nrejected,
            "duplication": stored / n if n else None,
            "shards": [{"samples": s.nsamples} for s in self.shards],
            **self._definition(),
        }

    # ----------------------------------------------------------- persistence
    def to_bytes(self) -> bytes:
        """The field file (layout of ``save``) as bytes: a snapshot."""
        buf = io.BytesIO()
        self.write_to(buf)
        return buf.getvalue()

    def save(self, path: str | os.PathLike) -> None:
        """Write the field to one file: written, flushed and fsync'd.

        Not atomic by itself: the service writes to a temporary file and
        renames it. A reader: may run beside queries, not beside a writer
        (an atlas field's batch waits for it).
        """
        with open(path, "wb") as fh:
            self.write_to(fh)
            fh.flush()
            os.fsync(fh.fileno())

    def write_parts(self, fh, stage: str | os.PathLike, known: Collection[str] = ()) -> list[str]:
        """Write a snapshot as a small field file plus its shards' *parts*.

        A part is one shard's field file, named by its key (:func:`part_key`, a
        digest of its bytes), written to the directory ``stage`` unless its
        key is in ``known`` (the parts stored already); the field file
        written to ``fh`` names the parts in shard order. A field whose shards
        do not change between snapshots writes only the changed ones. This
        kind holds its one shard in the field file itself: it writes
        :meth:`write_to` and no parts.

        Parameters
        ----------
        fh : binary file
            Where the field file goes.
        stage : path-like
            An existing directory for the new parts (``<stage>/<key>``).
        known : collection of str
            Keys of the parts already stored (not written again).

        Returns
        -------
        list of str
            The keys the field file names (all of them: new and known).
        """
        self.write_to(fh)
        return []

    def save_parts(self, path: str | os.PathLike, stage: str | os.PathLike,
                   known: Collection[str] = ()) -> list[str]:
        """:meth:`write_parts` to the file ``path``, flushed and fsync'd (as are
        the new parts)."""
        with open(path, "wb") as fh:
            keys = self.write_parts(fh, stage, known)
            fh.flush()
            os.fsync(fh.fileno())
        return keys

    @classmethod
    def load(cls, path: str | os.PathLike):
        """Read a field written by ``save``; raises SnapshotError if damaged."""
        return cls.from_bytes(Path(path).read_bytes(), source=str(path))
