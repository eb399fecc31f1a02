"""Cluster mode (``serve --ray``): a field's shards in Ray actors, the servers stateless fronts.

What runs in a server is :mod:`.front`; what runs in Ray actors, :mod:`.worker`; the
calls between them, :mod:`.wire`; Ray itself is imported by :mod:`.ray_env` alone, on
first use. The log stays the one truth: the shard workers follow it. The process
map and its rules: docs/design.md, "Cluster mode".
"""
