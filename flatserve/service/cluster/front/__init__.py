"""The cluster mode's side in a server (a *front*): its fields' shards live in Ray actors.

The front's home (:mod:`.home`), its view of a field (:mod:`.remote`), and the
shard groups' placement, calls and failover (:mod:`.ray_shards`). Nothing here runs
in an actor; what does is :mod:`flatserve.service.cluster.worker`.
"""
