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

import numpy as np

from ..atlas import Atlas
from ..atlas_field import AtlasField
from ..basis import Basis
from .status import FieldNotFoundError, StorageError
from ..field import AddResult, Field, PreparedBatch


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
    """

    k: int
    d: int
    channels: int
    basis: dict
    roundtrip_tol: Optional[float] = None
    atlas: Optional[dict] = None

    @classmethod
    def from_dict(cls, obj: dict) -> "FieldSpec":
        return cls(int(obj["k"]), int(obj["d"]), int(obj["channels"]), dict(obj.get("basis", {})),
                   obj.get("roundtrip_tol"), obj.get("atlas"))

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def is_atlas(self) -> bool:
        return self.atlas is not None

    @property
    def oriented(self) -> bool:
        """Rays keep their direction (atlas fields of lines only; kept in the atlas)."""
        return bool(self.atlas is not None and self.atlas["oriented"])

    def new_field(self, basis: Basis) -> "Field | AtlasField":
        """An empty field of this spec: a :class:`flatserve.Field` over ``basis``, or
        for an atlas spec an :class:`flatserve.atlas.AtlasField` (``basis`` is then
        its chart 0's). Both offer what the service uses: ``prepare``,
        ``insert_prepared``, ``add``, ``query``, ``save`` / ``load``, ``nsamples``,
        ``nsimplex``, ``nrejected``, ``ndim``."""
        kw = {} if self.roundtrip_tol is None else {"roundtrip_tol": self.roundtrip_tol}
        if self.atlas is not None:
            return AtlasField(Atlas.from_dict(self.atlas), channels=self.channels, **kw)
        return Field(basis, channels=self.channels, **kw)

    def load_field(self, path) -> "Field | AtlasField":
        """The field of a snapshot file written by its ``save``."""
        return (AtlasField if self.atlas is not None else Field).load(path)


@dataclass(frozen=True)
class UploadResult:
    """The response to an upload (stored with its batch for idempotent retries)."""

    batch: int
    accepted: int
    rejected: list
    reasons: list
    duplicates: Optional[int]
    nsamples: int
    indexed: bool
    pending_samples: int
    replayed: bool = False
    #: the batch's log position (read-your-writes: pass it back as ``min_position``)
    position: int = 0

    @classmethod
    def of(cls, seq: int, res: "AddResult | PreparedBatch", *, nsamples: int, indexed: bool,
           pending: int, position: int) -> "UploadResult":
        """From an :class:`AddResult` (indexed: duplicates known) or a
        :class:`PreparedBatch` (not yet indexed: duplicates null)."""
        return cls(seq, int(res.accepted), np.asarray(res.rejected, np.int64).tolist(),
                   [str(x) for x in res.reasons],
                   int(res.duplicates) if isinstance(res, AddResult) else None,
                   int(nsamples), indexed, int(pending), False, int(position))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(eq=False)
class FieldEntry:
    """One field of the server (state ``loading`` until restored, then ``ready``)."""

    id: int
    name: str
    spec: FieldSpec
    basis: Basis
    created: float = dc_field(default_factory=time.time)
    snapshot_file: str | None = None
    snapshot_seq: int = 0
    field: Field | AtlasField | None = None
    state: str = "loading"
    error: str | None = None
    #: log position of the field's ``create`` entry
    position: int = 0
    #: last batch inserted into the triangulation, and its log position
    indexed_seq: int = 0
    indexed_position: int = 0
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
    pending_lock: threading.Lock = dc_field(default_factory=threading.Lock)
    upload_lock: threading.Lock = dc_field(default_factory=threading.Lock)
    index_lock: threading.Lock = dc_field(default_factory=threading.Lock)

    def pending_counts(self) -> tuple[int, int]:
        """``(pending batches, their samples)``."""
        with self.pending_lock:
            return len(self.pending), sum(self.pending.values())

    def check_writable(self) -> None:
        """Raise unless uploads may change this field now."""
        if self.deleted:
            raise FieldNotFoundError(f"no field named {self.name!r}")
        if self.state != "ready":
            raise StorageError(f"field {self.name!r} is not ready ({self.state})")
