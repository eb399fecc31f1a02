"""A field's shards in other processes: the cluster mode (``serve --ray``).

A field is a set of shards (:class:`flatserve.contract.SampledField`: an atlas
field's charts; a one-chart field is one shard). In cluster mode the charts of
a field are split into *shard groups*, each held by one or more *shard
workers* (:class:`~.worker.shard.ShardWorker`) in processes of their own (Ray actors
on the cluster's nodes, :mod:`.front.placement`). A worker restores its charts
from the field's newest snapshot (only its own parts) and then follows the
shared log for its own rows: the log (PostgreSQL; SQLite for a cluster on one
machine) stays the one truth.

The server processes become stateless *fronts*: a field's entry holds a
:class:`~.front.remote.RemoteField`, which implements the field contract by routing
(a pure function of the field's definition), fanning out to one live copy of
each shard group a request touches, and blending, exactly as the one-process
field does; so the service's rooms are unchanged. Ray is imported only by
:mod:`.ray_env`, on first use (a front connecting, an actor running): the library
and the one-machine service do not need it. What runs in a server is
:mod:`.front`; what runs in Ray actors, :mod:`.worker`; the calls between them,
:mod:`.wire`.
"""
