"""The cluster mode's side in Ray actors: the shard workers and their tiles' actors.

A shard worker (:mod:`.shard`) is the server's log engine on some charts of one
field, run by a shard actor (:mod:`.actor`); a chart held in tiles keeps each tile
in an actor of its own (:mod:`.tiles`). Nothing here runs in a server; what does is
:mod:`flatserve.service.cluster.front`.
"""
