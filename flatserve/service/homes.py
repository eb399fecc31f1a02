"""Where a field's shards live: in this process, or in a cluster.

The log applier (:mod:`.applier`) asks the server's *home* for the field of an
entry it registers (a create, a restore) and tells it of a delete:

* :class:`LocalHome` (the default; defined beside the applier, :mod:`.applier`,
  which a cluster's shard worker imports without this module's cluster side):
  the field is built here, from the log, by the applier itself (a
  :class:`flatserve.contract.SampledField` in memory);
  a cluster's shard worker (:mod:`.cluster.shard`) runs the same applier with a
  ``LocalHome(only=its charts, tile_host=...)``: some charts of one field;
* :class:`~.cluster.fronts.ClusterHome` (``serve --ray ADDRESS``): the field is
  a :class:`~.cluster.remote.RemoteField`, its shards held by actors of a Ray
  cluster that restore themselves and follow the log; this process is a
  stateless front (``remote``: the applier neither loads a snapshot nor
  replays a batch).

The service's rooms see a field through the library's contract either way.
"""
from __future__ import annotations

from .applier import LocalHome

__all__ = ["LocalHome", "open_home"]


def open_home(settings):
    """The home of ``settings``: a cluster's when ``ray`` is set (its extra imported
    only then), else this process."""
    if settings.ray is None:
        return LocalHome()
    from .cluster.fronts import ClusterHome

    return ClusterHome(settings)
