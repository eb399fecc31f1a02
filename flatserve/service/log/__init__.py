"""The service's storage: the shared log of field operations and the snapshots.

The interface (:mod:`.backend`), its SQLite backend (:mod:`.storage`,
:mod:`.sqlitesnapshots`, :mod:`.sqlitemigrate`, the data directory :mod:`.datadir`)
and its PostgreSQL backend (:mod:`.pgstorage`, :mod:`.pgsession`, :mod:`.pgsnapshots`),
the rules and the schema both follow (:mod:`.sqlrules`, :mod:`.sqlschema`) and how a
batch's arrays are stored (:mod:`.blobs`). Storage only: what an entry means is the
rooms' (:mod:`flatserve.service.rooms`).
"""
