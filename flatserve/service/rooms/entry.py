"""What the server knows of one field: its typed spec, its state, its locks.

Synchronisation of one field (see ``docs/design.md``, "Locks"):

* ``upload_lock`` serialises uploads (commit order, idempotency checks);
* ``index_lock`` serialises changes of the in-memory field (inserts by the log
  follower, rebuilds) and snapshots, which must see a field no insert changes;
* ``pending_lock`` guards ``pending``, the batches committed but not yet applied
  here (describe's pending counts, the ``wait=false`` backlog);
* queries take no service lock: :class:`flatserve.Triangulation` guards its own
  state (readers share, an insert excludes them), so a query sees a whole
  batch or none of it.
"""
from __future__ import annotations

import threading
import time
from dataclasses import asdict, dataclass, field as dc_field
from typing import Optional

from ...atlas import Atlas
from ...basis import Basis
from ...contract import SampledField, describe_definition, load_field, new_field
from ...errors import InvalidInputError
from ...tiles import tile_setting
from .catalogue import FieldState
from ..status import FieldNotFoundError, StorageError


@dataclass(frozen=True)
class FieldSpec:
    """How a field was defined (stored as JSON with the field).

    Attributes
    ----------
    k, d, channels : int
    basis : dict
        The basis spec as stored, for describe (``{"kind": "tangent_simplex", ...}``;
        an atlas spec without ``oriented``, its sample flats replaced by their count).
    roundtrip_tol : float or None
        None: the library's default.
    atlas : dict or None
        Atlas fields: the atlas (:meth:`flatserve.atlas.Atlas.to_dict`: centres,
        scales, radii), built once at creation; None: one chart.
    copies : int
        Cluster mode: copies of each shard, on different nodes (one process holds
        its one copy otherwise).
    tiles : int or "auto"
        One chart: tiles of its triangulation (:mod:`flatserve.tiles`).
    rig : dict or None
        A light field with the depth channel: its capture's cameras
        (``{"eyes": (m, 3), "center": (3,)}``, :class:`~..schemas.RigSpec`), through
        which it renders; None: a plain field (not written by :meth:`to_dict`, so a
        definition without one is stored as before).
    """

    k: int
    d: int
    channels: int
    basis: dict
    roundtrip_tol: Optional[float] = None
    atlas: Optional[dict] = None
    copies: int = 1
    tiles: int | str = 1
    rig: Optional[dict] = None

    @classmethod
    def from_dict(cls, obj: dict) -> "FieldSpec":
        return cls(int(obj["k"]), int(obj["d"]), int(obj["channels"]), dict(obj.get("basis", {})),
                   obj.get("roundtrip_tol"), obj.get("atlas"), int(obj.get("copies", 1)),
                   tile_setting(obj.get("tiles", 1)), obj.get("rig"))

    def to_dict(self) -> dict:
        out = asdict(self)
        if out["rig"] is None:  # (definitions without one stored as before it existed)
            del out["rig"]
        return out

    @property
    def oriented(self) -> bool:
        """Rays keep their direction (atlas fields of lines only; kept in the atlas)."""
        return bool(self.atlas is not None and self.atlas["oriented"])

    def new_field(self, basis: Basis) -> SampledField:
        """An empty field of this spec (:func:`flatserve.contract.new_field`: one chart
        over ``basis``, or the spec's atlas, ``basis`` then being its chart 0's).

        Raises
        ------
        InvalidInputError
            The atlas or basis charts flats of another kind than ``k``, ``d`` (a
            definition edited by hand, e.g. in an export's manifest).
        """
        field = new_field(self.channels, basis=None if self.atlas is not None else basis,
                          atlas=None if self.atlas is None else Atlas.from_dict(self.atlas),
                          roundtrip_tol=self.roundtrip_tol, tiles=self.tiles)
        if (field.k, field.d) != (self.k, self.d):
            what = "atlas" if self.atlas is not None else "basis"
            raise InvalidInputError(f"{what}: charts {field.k}-flats in R^{field.d}, the "
                                    f"field is defined for {self.k}-flats in R^{self.d}", what)
        return field

    @staticmethod
    def load_field(path, parts=None) -> SampledField:
        """The field of a snapshot file written by its ``save`` or ``save_parts``
        (either kind; ``parts(key)``: the bytes of a part it names)."""
        return load_field(path, parts)

    def describe_unloaded(self) -> dict:
        """:meth:`~flatserve.contract.SampledField.describe` of a field of this spec
        not loaded yet: its definition, sizes None."""
        return describe_definition(self.atlas)


@dataclass(eq=False)
class FieldEntry:
    """One field of the server (:class:`~.catalogue.FieldState` ``LOADING`` until
    restored, then ``READY``; ``FAILED`` with ``error`` saying why).

    Its state changes through :meth:`mark_ready`, :meth:`mark_loading` and
    :meth:`mark_failed` only (the log applier's), its pending batches through
    :meth:`add_pending` / :meth:`drop_pending`."""

    id: int
    name: str
    spec: FieldSpec
    basis: Basis
    created: float = dc_field(default_factory=time.time)
    snapshot_file: str | None = None
    snapshot_seq: int = 0
    field: SampledField | None = None
    state: FieldState = FieldState.LOADING
    error: str | None = None
    #: log position of the field's ``create`` entry
    position: int = 0
    #: last batch inserted into the triangulation, and its log position
    indexed_seq: int = 0
    indexed_position: int = 0
    #: ``(nstored, nsimplex)`` of the field when it last held every batch up to
    #: ``indexed_seq`` whole (:meth:`mark_indexed`): the cost guard's measure, never
    #: taken from a triangulation with a batch half inserted
    complete_size: tuple[int, int] = (0, 0)
    snapshot_position: int = 0
    #: samples inserted since the last snapshot
    new_samples: int = 0
    snapshot_pending: bool = False
    #: no background snapshot attempt before this time.monotonic() (another replica
    #: held the lease)
    snapshot_not_before: float = 0.0
    deleted: bool = False
    #: batches committed (here or by another replica) and not yet applied here:
    #: log position -> accepted samples (rows for another replica's batch)
    pending: dict = dc_field(default_factory=dict)
    #: rows an import running here has passed the cost guard with and not stored yet
    #: (an upload's cost guard meanwhile counts them as pending)
    reserved: int = 0
    pending_lock: threading.Lock = dc_field(default_factory=threading.Lock)
    upload_lock: threading.Lock = dc_field(default_factory=threading.Lock)
    index_lock: threading.Lock = dc_field(default_factory=threading.Lock)

    # -- state ----------------------------------------------------------------------------
    def mark_ready(self) -> None:
        self.state, self.error = FieldState.READY, None

    def mark_loading(self, why: str) -> None:
        self.state, self.error = FieldState.LOADING, why

    def mark_failed(self, why: str) -> None:
        self.state, self.error = FieldState.FAILED, why

    def mark_indexed(self, seq: int, position: int) -> None:
        """The field holds every batch up to ``seq`` (at log ``position``) whole: record
        them, the field's size then (``complete_size``), and that the batch at
        ``position`` is no longer pending, at once (:meth:`indexed_counts` sees all or
        none of it). Called by the field's one writer, under ``index_lock`` (or
        before the field is published)."""
        size = (int(self.field.nstored), int(self.field.nsimplex))
        with self.pending_lock:
            self.indexed_seq, self.indexed_position = seq, position
            self.complete_size = size
            self.pending.pop(position, None)

    def indexed_counts(self) -> tuple[int, int, int]:
        """``(indexed_seq, pending batches, their samples)``, read together."""
        with self.pending_lock:
            return self.indexed_seq, len(self.pending), sum(self.pending.values())

    # -- batches committed, not yet applied here -----------------------------------------
    def add_pending(self, position: int, samples: int, *, keep: bool = False) -> None:
        """Count the batch at log ``position`` as pending (``keep``: unless counted)."""
        with self.pending_lock:
            if keep:
                self.pending.setdefault(position, samples)
            else:
                self.pending[position] = samples

    def drop_pending(self, position: int | None = None) -> None:
        """The batch at ``position`` is applied (or not stored); None: all of them."""
        with self.pending_lock:
            if position is None:
                self.pending.clear()
            else:
                self.pending.pop(position, None)

    def pending_counts(self) -> tuple[int, int]:
        """``(pending batches, their samples)``."""
        with self.pending_lock:
            return len(self.pending), sum(self.pending.values())

    def reserve(self, rows: int) -> None:
        """Add ``rows`` (negative: release them) to :attr:`reserved`."""
        with self.pending_lock:
            self.reserved = max(0, self.reserved + int(rows))

    def check_writable(self) -> None:
        """Raise unless uploads may change this field now."""
        if self.deleted:
            raise FieldNotFoundError(f"no field named {self.name!r}")
        if self.state is not FieldState.READY:
            raise StorageError(f"field {self.name!r} is not ready ({self.state})")
