"""The contract of a field: what every kind of field offers, and how to make one.

Two kinds of field implement :class:`SampledField`:
:class:`~flatserve.field.Field` (one chart: a basis and one triangulation,
paper Sec. 5) and :class:`~flatserve.atlas_field.AtlasField` (one Field per
chart of an atlas, blended by a partition of unity). A caller (the service)
uses only these members, never the class: :func:`new_field` makes an empty
field of either kind, :func:`load_field` reads either kind's file by its magic,
and :func:`describe_definition` describes a field not yet loaded. The
protocol is checked by ``mypy`` (``tests/test_contract.py``).

Shards
------
A field is a set of *shards*, each a :class:`~flatserve.field.Field`: an
atlas field's charts; a one-chart field is one shard (``shards == (self,)``).
Above the shards sit

- routing, a pure function of the field's definition: :meth:`~SampledField.route`
  (per shard the rows it stores) and :meth:`~SampledField.route_query` (per
  shard the queries it answers, with their blending weights);
- blending: :meth:`~SampledField.blend` combines the shards' answers
  (:class:`~flatserve.field.QueryResult` each) into the field's, in shard order.

Each shard's operations are callable on their own: ``shard.prepare`` /
``shard.insert_prepared(part)``, ``shard.query``, ``shard.to_bytes()`` /
``shard.write_to(fh)`` (snapshot) and ``Field.from_bytes`` (restore).

Example
-------
>>> import numpy as np, flatserve
>>> from flatserve.contract import SampledField, new_field
>>> field: SampledField = new_field(1, atlas=flatserve.Atlas.covering(1, 3))
>>> o, v = np.random.default_rng(0).normal(size=(2, 500, 3))
>>> rays = flatserve.Flats.from_rays(o, v)
>>> field.add(rays, o[:, 0]).accepted
500
>>> sorted(field.describe()) == sorted(new_field(1, basis=flatserve.Basis.around_axis()).describe())
True
"""
from __future__ import annotations

import os
from typing import Any, Callable, Collection, Protocol, Sequence, Union, runtime_checkable

import numpy as np

from pathlib import Path

from ._fieldbase import part_key, read_part
from .atlas import Atlas
from .atlas_field import ATLAS_MAGIC, AtlasField
from .basis import Basis
from .errors import InvalidInputError, SnapshotError
from .field import FIELD_MAGIC, AddResult, Field, QueryResult, QueryRoute
from .flats import Flats
from .grassmann import haar_frames
from .options import Interpolant, Order, Outside

__all__ = ["POINTER_MAGIC", "Prepared", "SampledField", "describe_definition", "expected_copies",
           "load_field", "new_field", "part_key", "part_pointer"]


@runtime_checkable
class Prepared(Protocol):
    """A batch charted by ``prepare`` and not yet inserted: opaque but for its
    decisions (``accepted`` rows to be inserted, the ``rejected`` row indices
    (j,) int64 with one of ``reasons`` each)."""

    @property
    def accepted(self) -> int: ...
    @property
    def rejected(self) -> np.ndarray: ...
    @property
    def reasons(self) -> list: ...


@runtime_checkable
class SampledField(Protocol):
    """A function sampled on k-flats in R^d: the members both kinds of field offer.

    The same meaning on both kinds; where the kinds differ the member says
    how (``blends``, ``describe``'s ``atlas`` / ``charts``).

    Thread safety: readers (``prepare``, ``query``, ``copies``, ``route*``,
    ``describe``, ``save``) together, a writer (``insert_prepared``, ``add``)
    alone.

    Attributes
    ----------
    k, d : int
        k-flats in R^d.
    channels : int
        Values per sample.
    ndim : int
        Dimension D of each shard's triangulation: ``m - 1`` (Sec. 5).
    roundtrip_tol : float
        Largest round-trip residual of trusted coordinates (Sec. 4, Eq. 9/12).
    blends : bool
        Answers blend several shards: ``query(return_weights=True)`` gives
        ids and weights of shape (q, P, D+1), not (q, D+1).
    nsamples : int
        Distinct samples.
    nstored : int
        Vertices over all shards (a sample counts once per shard holding
        it; ``nsamples`` for one shard).
    nsimplex : int
        Cells over all shards' triangulations.
    nrejected : int
        Rows rejected by ``insert_prepared`` so far.
    shards : sequence of Field
        The field's shards, in order.
    """

    k: int
    d: int
    channels: int
    ndim: int

    @property
    def nsamples(self) -> int: ...
    @property
    def nstored(self) -> int: ...

    roundtrip_tol: float

    @property
    def nsimplex(self) -> int: ...
    @property
    def nrejected(self) -> int: ...

    blends: bool

    @property
    def shards(self) -> Sequence[Field]: ...

    # --------------------------------------------------------------- shards
    def route(self, flats: Flats) -> list[np.ndarray]:
        """Per shard, the rows (increasing int64 indices) it stores."""
        ...

    def route_query(self, flats: Flats) -> QueryRoute:
        """Per shard, the queries it answers and their blending weights."""
        ...

    def blend(self, route: QueryRoute, results: Sequence[QueryResult | None], *,
              return_weights: bool = False) -> QueryResult:
        """The field's answer from each shard's answer on its ``route.rows``
        (None: the shard holds no samples, so its rows are ``NO_SAMPLES`` unless
        another shard answers them; or it routes no rows), combined in shard order."""
        ...

    def copies(self, flats: Flats) -> float:
        """How many shards would store each of these rows on average (1.0 for one shard)."""
        ...

    # -------------------------------------------------------------- writers
    def prepare(self, flats: Flats, values, *, defer: bool = False
                ) -> Prepared | Callable[[], Prepared]:
        """Chart and decide a batch without inserting (a callable doing it when ``defer``)."""
        ...

    def insert_prepared(self, batch, *, slice_rows: int | None = None) -> AddResult:
        """Insert a batch made by this field's ``prepare`` (a writer)."""
        ...

    def add(self, flats: Flats, values) -> AddResult:
        """``insert_prepared(prepare(flats, values))``."""
        ...

    def settle(self) -> None:
        """Finish what the inserts so far left pending (a tiled chart's exchange)."""
        ...

    # -------------------------------------------------------------- readers
    def query(self, flats: Flats, *, outside: Outside | str = Outside.NAN,
              order: Order | str = Order.HILBERT, threads: int | None = None,
              return_weights: bool = False, blocking: bool = True,
              interpolant: Interpolant | str = Interpolant.LINEAR) -> QueryResult | None:
        """Interpolate at ``q`` flats: values (q, C), inside (q,), status (q,);
        None when not ``blocking`` and a writer is in; ``interpolant`` as
        :meth:`flatserve.field.Field.query`'s."""
        ...

    def describe(self) -> dict:
        """``nsamples``, ``nstored``, ``nsimplex``, ``nrejected``, ``duplication``,
        ``shards``, ``atlas``, ``charts`` (see ``FieldBase.describe``)."""
        ...

    # ------------------------------------------- where the shards are held
    #: The shards' triangulations are held in this process (False: a cluster
    #: front's ``RemoteField``, whose answers come from other processes: the
    #: service answers it on the event loop with :meth:`query_async`).
    holds_shards: bool

    async def query_async(self, flats: Flats, *, outside: Outside | str = Outside.NAN,
                          order: Order | str = Order.HILBERT, threads: int | None = None,
                          return_weights: bool = False,
                          interpolant: Interpolant | str = Interpolant.LINEAR
                          ) -> QueryResult | None:
        """``query(flats, **kw)`` awaited; a field held here answers at once, never
        waiting for an insert (``blocking=False``: None while a writer is in)."""
        ...

    def applied_counts(self, position: int, timeout: float) -> dict:
        """Once the batch at log ``position`` is applied where the shards live (at
        most ``timeout`` s), the upload response's ``nsamples`` and ``duplicates``
        counted there; ``{}`` for a field held here (its insert counted them)."""
        ...

    @property
    def own_samples(self) -> list[int] | None:
        """Per shard, the distinct samples whose nearest shard it is (their sum is
        ``nsamples``; a one-chart field: ``[nsamples]``); None for an atlas field
        read from a file that did not record them."""
        ...

    @property
    def ntiles(self) -> int | None:
        """Tiles of a one-chart field's triangulation held here; None otherwise."""
        ...

    # ------------------------------------------------------ the unit of length
    # A field whose unit of length its first batch chooses (an atlas made with
    # ``unit="auto"``); every other field: ``unit_pending`` and ``unit_from_data``
    # False, ``unit`` None, ``settle_unit`` a no-op returning False, ``in_unit``
    # itself.
    @property
    def unit_pending(self) -> bool:
        """The unit is still to be chosen from the first samples."""
        ...

    @property
    def unit_from_data(self) -> bool:
        """The field may still take a unit (:meth:`settle_unit`): no batch inserted yet."""
        ...

    @property
    def unit(self) -> float | None:
        """The unit the field charts in; None while pending, or for a field without one."""
        ...

    def settle_unit(self, unit: float, *, if_empty: bool = False) -> bool:
        """Take ``unit`` (the one recorded with the field's first batch) while it may;
        whether the field changed (a writer)."""
        ...

    def in_unit(self, unit: float) -> Any:
        """What charts a batch in ``unit`` (its ``prepare``): the field itself when
        ``unit`` is its own, else an empty field of the same definition in ``unit``
        whose prepared batches carry it. Reads the definition only."""
        ...

    #: Bytes of snapshot parts the shards stored themselves for the last
    #: :meth:`write_parts` (0: every part was written to ``stage``).
    stored_bytes: int

    # ---------------------------------------------------------- persistence
    def write_to(self, fh) -> int:
        """Write the field file to an open binary file; bytes written."""
        ...

    def to_bytes(self) -> bytes:
        """The field file as bytes."""
        ...

    def save(self, path: str | os.PathLike) -> None:
        """Write the field file, fsync'd."""
        ...

    def write_parts(self, fh, stage: str | os.PathLike, known: Collection[str] = ()) -> list[str]:
        """A snapshot as a field file plus the parts of the shards that changed
        (written to ``stage``); the keys of every part it names."""
        ...

    def save_parts(self, path: str | os.PathLike, stage: str | os.PathLike,
                   known: Collection[str] = ()) -> list[str]:
        """:meth:`write_parts` to a file, fsync'd."""
        ...


#: What :func:`new_field` and :func:`load_field` return.
AnyField = Union[Field, AtlasField]


def new_field(channels: int, *, basis: Basis | None = None, atlas: Atlas | dict | None = None,
              roundtrip_tol: float | None = None, tiles: int | str = 1) -> AnyField:
    """An empty field: one chart over ``basis``, or one Field per chart of ``atlas``.

    Parameters
    ----------
    channels : int
        Values per sample.
    basis : Basis, optional
        A one-chart :class:`~flatserve.field.Field`.
    atlas : Atlas or dict, optional
        An :class:`~flatserve.atlas_field.AtlasField`; a dict is a stored atlas
        (:meth:`flatserve.atlas.Atlas.to_dict`). Exactly one of ``basis``
        and ``atlas``.
    roundtrip_tol : float, optional
        None: the library's default (:data:`flatserve.coordinates.ROUNDTRIP_TOL`).
    tiles : int or "auto"
        One chart: tiles of its triangulation (:class:`~flatserve.field.Field`'s
        ``tiles``); an atlas field takes 1 only.

    Returns
    -------
    Field or AtlasField
        Both are :class:`SampledField`.
    """
    if (basis is None) == (atlas is None):
        raise InvalidInputError("basis: give exactly one of basis and atlas", "basis")
    kw = {} if roundtrip_tol is None else {"roundtrip_tol": roundtrip_tol}
    if atlas is not None:
        if tiles != 1:
            raise InvalidInputError("tiles: an atlas field's charts are not tiled", "tiles")
        return AtlasField(Atlas.from_dict(atlas) if isinstance(atlas, dict) else atlas,
                          channels, **kw)
    return Field(basis, channels, tiles=tiles, **kw)


#: Magic of a field file that only names the one part holding the whole field
#: (:func:`part_pointer`).
POINTER_MAGIC = b"FSPART\x00\x00"


def part_pointer(key: str) -> bytes:
    """A field file naming the part ``key`` that holds a whole field (a field
    file of either kind, stored as a snapshot part by the process that holds
    the field: its bytes never travel through the one that writes the
    snapshot). :func:`load_field` follows it.

    Examples
    --------
    >>> part_pointer("00" * 16)[:8] == POINTER_MAGIC
    True
    """
    if len(key) != 32 or any(ch not in "0123456789abcdef" for ch in key):
        raise InvalidInputError(f"key: expected 32 lowercase hex digits, got {key!r}", "key")
    return POINTER_MAGIC + key.encode("ascii")


def load_field(path: str | os.PathLike, parts=None,
               only: Collection[int] | None = None) -> AnyField:
    """Read a field file of either kind, told apart by its magic.

    ``FSFIELD\\0``: :meth:`Field.from_bytes`; ``FSATLAS\\0``:
    :meth:`AtlasField.from_bytes`, with ``parts(key) -> bytes-like`` for a
    file whose charts are parts (:meth:`SampledField.write_parts`), and
    ``only``: the shards to restore (the others left empty; a one-chart
    field's file is its one shard). A :func:`part_pointer` file is read as
    the part it names (``parts`` needed; the part checked against its key).

    Raises
    ------
    SnapshotError
        Neither magic, or a damaged file.
    """
    data = Path(path).read_bytes()
    if bytes(data[:8]) == POINTER_MAGIC:
        key = bytes(data[8:]).decode("ascii", "replace")
        if parts is None:
            raise SnapshotError(f"{path}: names the part {key!r}, and no parts were given")
        data = bytes(read_part(parts, key, str(path), "the part it names"))
        if bytes(data[:8]) == POINTER_MAGIC:
            raise SnapshotError(f"{path}: the part {key!r} it names is a pointer itself")
    kind = {FIELD_MAGIC: Field, ATLAS_MAGIC: AtlasField}.get(bytes(data[:8]))
    if kind is None:
        raise SnapshotError(f"{path}: not a flatserve field file (bad magic)"
                            if len(data) >= 8 else
                            f"{path}: truncated field file ({len(data)} bytes)")
    return kind.from_bytes(data, source=str(path), parts=parts, only=only)


def describe_definition(atlas: dict | None) -> dict:
    """``describe`` of a field not loaded yet: its definition, its sizes None.

    Parameters
    ----------
    atlas : dict or None
        The stored atlas (:meth:`flatserve.atlas.Atlas.to_dict`), None for a
        one-chart field.

    Returns
    -------
    dict
        The keys of ``describe``: ``atlas`` and ``charts`` as a loaded field's
        (both None for a one-chart field; the charts' ``samples`` None),
        ``shards`` one ``{"samples": None}`` per shard, ``nsamples``,
        ``nstored``, ``nsimplex``, ``nrejected`` and ``duplication`` None.
    """
    part = {"atlas": None, "charts": None} if atlas is None else Atlas.describe_spec(atlas)
    nshards = 1 if atlas is None else len(part["charts"])
    return {"nsamples": None, "nstored": None, "nsimplex": None, "nrejected": None,
            "duplication": None, "shards": [{"samples": None} for _ in range(nshards)], **part}


#: Random flats :func:`expected_copies` routes (its figure varies by about 1 % between seeds).
EXPECTED_COPIES_N = 2000


def expected_copies(field: SampledField, n: int = EXPECTED_COPIES_N, seed: int = 0) -> float:
    """How many shards would store a sample of ``field`` on average, before it holds any:
    ``field.copies`` of ``n`` random flats of its kind (Haar-random orientations, seeded;
    lines as rays of directions uniform on the sphere, as an oriented atlas takes them).

    1.0 for a one-chart field; for the default covering atlases about 1.75 in R^3, 2.4 for
    lines in R^4, 3.4 for planes in R^4 (every row up to the charts' reach: their net
    of the outer seam stores about 2.4 at 3,000 samples, 2.3 at 12,000), 7.3 for
    3-flats in R^5 (``docs/costs.md``).
    Offsets do not matter: a shard holds a flat by its orientation.
    """
    k, d = field.k, field.d
    rng = np.random.default_rng(seed)
    if k == 1:
        flats = Flats.from_rays(np.zeros((n, d)), rng.standard_normal((n, d)))
    else:
        flats = Flats.from_parametric(haar_frames(n, d, k, rng), np.zeros((n, d)))
    return float(field.copies(flats))
