"""The cluster mode's side in a server (a *front*): its fields' shards live in Ray actors.

The front's home (:mod:`.home`), its view of a field (:mod:`.remote`), and the
shard groups' placement (:mod:`.placement`), the transport of a call to an actor
(:mod:`.transport`), failover between a group's copies (:mod:`.failover`) and what
is known of each copy (:mod:`.health`). Nothing here runs
in an actor; what does is :mod:`flatserve.service.cluster.worker`.
"""
