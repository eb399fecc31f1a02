"""Cluster mode in Ray actors: the shard worker (:mod:`.shard`) and its actor
(:mod:`.actor`), a chart's tiles in actors of their own (:mod:`.tiles`,
:mod:`.tile_actor`). Nothing here runs in a server.
"""
