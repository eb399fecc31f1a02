"""Cluster mode in a server (a *front*): its home (:mod:`.home`), a field's view
(:mod:`.remote`), placement (:mod:`.placement`), transport (:mod:`.transport`),
failover (:mod:`.failover`) and health (:mod:`.health`). Nothing here runs in an actor.
"""
