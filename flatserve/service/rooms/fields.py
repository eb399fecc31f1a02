"""The fields room: create, delete, describe and list this service's fields.

A create or delete is committed to the shared log and answered once this
replica's follower has applied it (:mod:`.applier`), as every replica applies
it; descriptions read the catalogue (:mod:`.catalogue`), the field's own
:meth:`describe` (the library's contract, :mod:`flatserve.contract`) and the
storage figures. Every answer is a model of :mod:`..reports`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

from ...basis import Basis
from .applier import LogApplier
from ..log.backend import LogBackend
from .catalogue import FieldCatalogue
from .costs import check_capacity
from .entry import FieldEntry, FieldSpec
from .replica import Follower
from ..reports import (AtlasInfo, BasisInfo, ChartCenter, ChartInfo, FieldInfo, FieldSummary,
                       StorageInfo)
from ..settings import Settings
from ..status import FieldNotFoundError, StorageError

log = logging.getLogger("flatserve.service")


@dataclass
class FieldService:
    """Create, delete and describe fields (see the module doc)."""

    #: ``max_fields``, ``apply_wait_timeout``, ``max_simplices``, ``min_field_samples``
    settings: Settings
    #: commits creates and deletes to the log
    storage: LogBackend
    #: reserves a new name; lists and finds the fields
    catalogue: FieldCatalogue
    #: tells when a create or delete is applied here
    follower: Follower
    #: takes the field a create built (so that it is not built twice)
    applier: LogApplier

    def create(self, name: str, spec: FieldSpec, basis: Basis) -> FieldEntry:
        """Create field ``name``; its entry once applied here.

        Raises
        ------
        FieldExistsError, TooManyFieldsError
            409.
        CostLimitError
            413: a field of this kind could not hold ``min_field_samples`` samples
            under ``max_simplices`` (:func:`.costs.check_capacity`).
        """
        fld = spec.new_field(basis)
        fid = None
        with self.catalogue.reserve(name, self.settings.max_fields):
            check_capacity(name, fld, self.settings)
            try:  # the name is reserved; the commit runs without the catalogue's lock
                fid, pos = self.storage.create_field(name, spec.to_dict(),
                                                     {"Q": basis.Q, "r": basis.r})
                self.applier.offer_built(fid, fld)
                self.follower.await_applied(pos, f"field {name!r}",
                                            self.settings.apply_wait_timeout)
                e = self.catalogue.by_id(fid)
                if e is None:  # deleted meanwhile (by another replica)
                    raise FieldNotFoundError(f"field {name!r} was deleted meanwhile")
            finally:  # the follower may have applied the create before the hand-over
                self.applier.withdraw_built(fid)
        log.info("created field %r (k=%d, d=%d, channels=%d) at log position %d", name,
                 spec.k, spec.d, spec.channels, pos)
        return e

    def delete(self, name: str) -> int:
        """Delete a field; the log position of the delete."""
        e = self.catalogue.get(name, need_ready=False)
        with e.upload_lock:
            if e.deleted:
                raise FieldNotFoundError(f"no field named {name!r}")
            pos = self.storage.delete_field(e.id)
        self.follower.await_applied(pos, f"the delete of {name!r}",
                                    self.settings.apply_wait_timeout)
        log.info("deleted field %r at log position %d", name, pos)
        return pos

    # -- descriptions ---------------------------------------------------------------------------
    @staticmethod
    def summary(e: FieldEntry) -> FieldSummary:
        f = e.field
        return FieldSummary(name=e.name, k=e.spec.k, d=e.spec.d, channels=e.spec.channels,
                            state=e.state, oriented=e.spec.oriented,
                            nsamples=int(f.nsamples) if f is not None else None)

    def summaries(self) -> list[FieldSummary]:
        return [self.summary(e) for e in self.catalogue.entries()]

    def describe(self, e: FieldEntry, verbose: bool = False) -> FieldInfo:
        """Field ``e``: its sizes (null while it loads), storage, atlas summary; with
        ``verbose`` also the basis flats and every chart (several KB for an atlas).

        Raises
        ------
        StorageError
            Its stored definition cannot be read by this version (503).
        """
        if e.basis is None:  # a stored definition this version cannot read
            raise StorageError(f"field {e.name!r} could not be loaded: {e.error}")
        nb, nrows, nbytes, last = self.storage.batch_stats(e.id)
        snap_bytes = self.storage.snapshot_bytes(e.snapshot_file)
        f = e.field
        d = f.describe() if f is not None else e.spec.describe_unloaded()
        m = e.basis.m
        indexed, pending_batches, pending_samples = e.indexed_counts()
        charts = _charts(d)
        kind = {k: v for k, v in (("atlas", _atlas_info(d)),
                                  ("charts", charts if verbose else None),
                                  ("shard_groups", d.get("placement")),
                                  ("rig", e.spec.rig))
                if v is not None}  # (one chart: described by ``basis`` alone)
        flats = dict(Q=e.basis.Q.tolist(), r=e.basis.r.tolist()) if verbose else {}
        return FieldInfo(
            **self.summary(e).model_dump(),
            ndim=m - 1, position=self.follower.applied, indexed_batch=indexed,
            pending_batches=pending_batches, pending_samples=pending_samples,
            nrejected=d["nrejected"], nvertices=d["nstored"], nsimplex=d["nsimplex"],
            created=e.created, error=e.error,
            basis=BasisInfo(m=m, dim=m - 1, spec=e.spec.basis, **flats),
            ncharts=len(charts) if charts is not None else 1, tiles=e.spec.tiles,
            ntiles=f.ntiles if f is not None else None,
            storage=StorageInfo(batches=nb, batch_rows=nrows, batch_bytes=nbytes,
                                last_batch=last,
                                snapshot_batch=e.snapshot_seq if e.snapshot_file else 0,
                                snapshot_bytes=snap_bytes, total_bytes=nbytes + snap_bytes),
            **kind)


def _atlas_info(d: dict) -> AtlasInfo | None:
    at = d["atlas"]
    if at is None:
        return None
    info = at.get("info") or {}
    return AtlasInfo(method=info.get("method"), oriented=at["oriented"], inner=at["inner"],
                     trusted=at["trusted"], reach=at["reach"], unit=at["unit"],
                     unit_from=at["unit_from"],
                     relative=bool(at.get("relative")), isometric=bool(at.get("isometric")),
                     dense_reach=at.get("dense_reach"), dense_after=at.get("dense_after"),
                     seam_spacing=at.get("seam_spacing"),
                     covering_radius=info.get("covering_radius_deg"),
                     max_sample_angle=info.get("max_sample_angle_deg"),
                     nstored=d["nstored"], duplication=d["duplication"])



def _charts(d: dict) -> list[ChartInfo] | None:
    if d["charts"] is None:
        return None
    return [ChartInfo(center=ChartCenter(A=c["center"]["A"], r=c["center"]["r"]),
                      scale=c["scale"], samples=c["samples"]) for c in d["charts"]]
