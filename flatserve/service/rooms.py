"""The service's rooms, built and stopped together (the application's lifespan).

Each room has one job, and a route receives the rooms it needs as their own
dependencies (:mod:`.deps`); this module only builds them in order, starts the
restore and stops them in the reverse order:

* :class:`~.catalogue.FieldCatalogue`: names -> fields and their states;
* :class:`~.snapshots.SnapshotWriter`: the snapshot lease and writes;
* the fields' home (:mod:`.homes`): this process, or a cluster's actors;
* :class:`~.applier.LogApplier`: what each log entry does; restore and rebuild;
* :class:`~.replica.Follower`: follows the shared log (owns the applier),
  log positions and the waits for them;
* :class:`~.fields.FieldService`: create, delete, describe;
* :class:`~.uploads.UploadService`: durable, idempotent uploads;
* :class:`~.query.QueryService`: interpolation;
* :class:`~.transfer.TransferService`: a field exported as one file, and imported.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from .applier import LogApplier
from .backend import LogBackend, open_backend
from .catalogue import FieldCatalogue
from .homes import open_home
from .fields import FieldService
from .query import QueryService
from .replica import Follower
from .settings import Settings
from .snapshots import SnapshotWriter
from .transfer import TransferService
from .uploads import UploadService

log = logging.getLogger("flatserve.service")

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
