"""The service's domain: its rooms, each with one job, in the server's process.

The field catalogue and each field's entry (:mod:`.catalogue`, :mod:`.entry`), the
field specifications (:mod:`.specs`, :mod:`.units`, :mod:`.costs`), the fields room
(:mod:`.fields`), uploads (:mod:`.uploads`), queries (:mod:`.query`), snapshots
(:mod:`.snapshots`), export and import (:mod:`.transfer`), and the log engine: the
follower that reads the shared log (:mod:`.replica`, the one reader of the log) and
the applier that applies its entries (:mod:`.applier`). A cluster's shard worker
(:mod:`flatserve.service.cluster.worker`) runs the same follower and applier on
some charts of one field. Storage is below (:mod:`flatserve.service.log`); HTTP above
(:mod:`flatserve.service.http`); :mod:`flatserve.service.assembly` builds the rooms.
"""
