"""Where a field's shards live: in this process, or in a cluster.

The log applier (:mod:`.applier`) asks the server's *home* for the field of an
entry it registers (a create, a restore) and tells it of a delete:

* :class:`LocalHome` (the default): the field is built here, from the log, by
  the applier itself (a :class:`flatserve.contract.SampledField` in memory);
* :class:`~.cluster.fronts.ClusterHome` (``serve --ray ADDRESS``): the field is
  a :class:`~.cluster.remote.RemoteField`, its shards held by actors of a Ray
  cluster that restore themselves and follow the log; this process is a
  stateless front (``remote``: the applier neither loads a snapshot nor
  replays a batch).

The service's rooms see a field through the library's contract either way.
"""
from __future__ import annotations

from .entry import FieldEntry, SampledField


class LocalHome:
    """Fields held in this process (see the module doc)."""

    #: the fields' shards live elsewhere: nothing to load or replay here
    remote = False

    def field(self, e: FieldEntry, built: SampledField | None = None) -> SampledField:
        """The field of entry ``e`` (``built``: the one its create request made)."""
        return built if built is not None else e.spec.new_field(e.basis)

    def drop(self, e: FieldEntry) -> None:
        """``e`` was deleted (its memory goes with the entry)."""

    def close(self) -> None:
        pass


def open_home(settings):
    """The home of ``settings``: a cluster's when ``ray`` is set (its extra imported
    only then), else this process."""
    if settings.ray is None:
        return LocalHome()
    from .cluster.fronts import ClusterHome

    return ClusterHome(settings)
