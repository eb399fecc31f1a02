"""The composition root: the service's rooms, built and stopped together (the
application's lifespan), and where a field's shards live (its *home*).

Each room has one job, and a route receives the rooms it needs as their own
dependencies (:mod:`.http.deps`); this module only chooses the home, builds the
rooms in order, starts the restore and stops them in the reverse order:

* :class:`~.rooms.catalogue.FieldCatalogue`: names -> fields and their states;
* :class:`~.rooms.snapshots.SnapshotWriter`: the snapshot lease and writes;
* the fields' home (:func:`open_home`): this process, or a cluster's actors;
* :class:`~.rooms.applier.LogApplier`: what each log entry does; restore and rebuild;
* :class:`~.rooms.replica.Follower`: follows the shared log (owns the applier),
  log positions and the waits for them;
* :class:`~.rooms.fields.FieldService`: create, delete, describe;
* :class:`~.rooms.uploads.UploadService`: durable, idempotent uploads;
* :class:`~.rooms.query.QueryService`: interpolation;
* :class:`~.rooms.transfer.TransferService`: a field exported as one file, and imported.

The applier asks the home for the field of an entry it registers (a create, a
restore) and tells it of a delete:

* :class:`~.rooms.applier.LocalHome` (the default; defined beside the applier,
  which a cluster's shard worker imports without the cluster's front): the field
  is built here, from the log, by the applier itself (a
  :class:`flatserve.contract.SampledField` in memory); a cluster's shard worker
  (:mod:`.cluster.worker.shard`) runs the same applier with a
  ``LocalHome(only=its charts, tile_host=...)``: some charts of one field;
* :class:`~.cluster.front.home.ClusterHome` (``serve --ray ADDRESS``): the field
  is a :class:`~.cluster.front.remote.RemoteField`, its shards held by actors of a
  Ray cluster that restore themselves and follow the log; this process is a
  stateless front (``remote``: the applier neither loads a snapshot nor replays a
  batch).

The service's rooms see a field through the library's contract either way.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from .rooms.applier import LogApplier
from .log.backend import LogBackend, open_backend
from .rooms.catalogue import FieldCatalogue
from .rooms.applier import LocalHome
from .rooms.fields import FieldService
from .rooms.query import QueryService
from .rooms.replica import Follower
from .settings import Settings
from .rooms.snapshots import SnapshotWriter
from .rooms.transfer import TransferService
from .rooms.uploads import UploadService

log = logging.getLogger("flatserve.service")

def open_home(settings):
    """The home of ``settings``: a cluster's when ``ray`` is set (its extra imported
    only then), else this process."""
    if settings.ray is None:
        return LocalHome()
    from .cluster.front.home import ClusterHome

    return ClusterHome(settings)


#: on shutdown, keep applying committed entries this long; the rest are applied on start
DRAIN_TIMEOUT_S = 10.0


@dataclass
class Rooms:
    """The rooms of one replica (see the module doc)."""

    settings: Settings
    storage: LogBackend
    catalogue: FieldCatalogue
    snapshots: SnapshotWriter
    applier: LogApplier
    follower: Follower
    fields: FieldService
    uploads: UploadService
    queries: QueryService
    transfer: TransferService
    metrics: object = None
    _loader: threading.Thread | None = None

    @classmethod
    def open(cls, settings: Settings, metrics=None) -> "Rooms":
        """Open the storage of ``settings`` and build the rooms over it (nothing runs
        yet: :meth:`start`)."""
        storage = open_backend(settings)
        try:
            home = open_home(settings)
        except BaseException:
            storage.close()
            raise
        catalogue = FieldCatalogue()
        snapshots = SnapshotWriter(settings, storage, metrics)
        applier = LogApplier(settings, storage, catalogue, snapshots, metrics, home)
        follower = Follower(storage, applier)
        fields = FieldService(settings, storage, catalogue, follower, applier)
        uploads = UploadService(settings, storage, follower, metrics)
        return cls(settings, storage, catalogue, snapshots, applier, follower, fields, uploads,
                   QueryService(settings, catalogue, follower, metrics),
                   TransferService(settings, storage, catalogue, fields, uploads), metrics)

    def start(self) -> None:
        """Restore the stored fields and follow the log, in a thread (requests are
        answered meanwhile: 503 for fields still loading)."""
        self._loader = threading.Thread(target=self.follower.restore_and_follow,
                                        name="flatserve-restore", daemon=True)
        self._loader.start()

    def close(self, drain_timeout: float | None = None) -> None:
        """Stop: apply committed entries for up to ``drain_timeout`` seconds (default
        :data:`DRAIN_TIMEOUT_S`; the rest are applied from the log on the next
        start), stop background work, close the storage."""
        end = time.monotonic() + (DRAIN_TIMEOUT_S if drain_timeout is None else drain_timeout)
        if not self.follower.stop(max(0.0, end - time.monotonic())):
            log.warning("stopping at log position %d with committed entries not applied; "
                        "they are stored and applied on the next start", self.follower.applied)
        self.uploads.close()
        self.snapshots.close()
        self.follower.join(max(0.0, end - time.monotonic()) + 1.0)
        if self._loader is not None:
            self._loader.join(timeout=30)
        self.applier.home.close()
        self.storage.close()
