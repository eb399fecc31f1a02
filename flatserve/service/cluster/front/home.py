"""A front's home for fields whose shards live on a Ray cluster (see :mod:`flatserve.service.assembly`)."""
from __future__ import annotations

from ...rooms.entry import FieldEntry
from .placement import RayCluster
from .remote import RemoteField


class ClusterHome:
    """Fields as :class:`~.remote.RemoteField` over the cluster's actors.

    Raises
    ------
    ShardUnavailableError
        On construction: the cluster cannot be reached (the address named).
    """

    remote = True
    #: every chart of a field is the cluster's (:class:`...rooms.applier.LocalHome`'s ``only``)
    only = None

    def __init__(self, settings) -> None:
        self.settings = settings
        self.cluster = RayCluster(settings)

    def field(self, e: FieldEntry, built=None) -> RemoteField:
        shape = built if built is not None else e.spec.new_field(e.basis)
        groups = self.cluster.groups(e.id, len(shape.shards), e.spec.copies, e.name)
        return RemoteField(shape, groups, lambda: e.indexed_position,
                           self.settings.read_wait_timeout)

    def drop(self, e: FieldEntry) -> None:
        self.cluster.drop(e.id)

    def close(self) -> None:
        self.cluster.close()
