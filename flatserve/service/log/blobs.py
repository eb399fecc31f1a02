"""How a batch's arrays are stored: one blob, and one content hash for idempotency.

The blob is written once, read at every restore; its layout is independent of
the transport the batch came by (JSON, ``.npy``, ``.npz``).
"""
from __future__ import annotations

import hashlib
import json
import math

import numpy as np

from ..status import StorageError


#: blob layout of stored arrays: this magic, uint32 little-endian length of a JSON
#: header ``[[name, dtype descr, shape], ...]``, the header, then each array's raw
#: C-order bytes (8-byte aligned offsets).
BLOB_MAGIC = b"FSARRAY1"


def pack_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    """Arrays as one blob (a single copy of the data; see :data:`BLOB_MAGIC`)."""
    arrs = [(name, np.ascontiguousarray(a)) for name, a in arrays.items()]
    head = json.dumps([[name, np.lib.format.dtype_to_descr(a.dtype), list(a.shape)]
                       for name, a in arrs]).encode()
    start = len(BLOB_MAGIC) + 4 + len(head)
    parts = [BLOB_MAGIC, len(head).to_bytes(4, "little"), head, b"\0" * (-start % 8)]
    for _, a in arrs:
        b = a.data.cast("B") if a.size else b""
        parts += [b, b"\0" * (-len(b) % 8)]
    return b"".join(parts)


def unpack_arrays(blob: bytes) -> dict[str, np.ndarray]:
    if blob[:len(BLOB_MAGIC)] != BLOB_MAGIC:
        raise StorageError("stored batch: unknown blob format (bad magic)")
    p = len(BLOB_MAGIC)
    n = int.from_bytes(blob[p:p + 4], "little")
    head = json.loads(blob[p + 4:p + 4 + n])
    off = p + 4 + n
    off += -off % 8
    out = {}
    for name, descr, shape in head:
        dt = np.dtype(np.lib.format.descr_to_dtype(descr))
        count = math.prod(shape)
        out[name] = np.frombuffer(blob, dt, count, off).reshape(shape)
        off += count * dt.itemsize
        off += -off % 8
    return out


def content_hash(form: str, arrays: dict[str, np.ndarray]) -> str:
    """Hash of a batch's content, independent of its transport encoding."""
    h = hashlib.sha256(form.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name], dtype=np.float64)
        h.update(f"|{name}{a.shape}|".encode())
        h.update(a.data)
    return h.hexdigest()


#: The array that a batch of a field whose unit of length is chosen from the data
#: carries beside its flats and ``values``: shape (1,), the unit its rows were
#: charted in (:func:`flatserve.atlas_field.choose_unit` of the batch). A replica or
#: front stores it with every batch it charts while the field has no unit there
#: yet, so the first stored batch records the unit for every replica, restart
#: and shard (:func:`split_batch`, :func:`flatserve.service.rooms.units.adopt_unit`);
#: a later batch's is ignored. It is not part of the batch's content hash (what
#: the client sent).
UNIT_ARRAY = "unit"


def split_batch(arrays: dict[str, np.ndarray]) -> tuple[dict, np.ndarray, float | None]:
    """A stored batch's arrays (:func:`unpack_arrays`) split into its flats' arrays
    (by name), its ``values`` and the unit recorded with it (None: none recorded)."""
    arrays = dict(arrays)
    values = arrays.pop("values")
    unit = arrays.pop(UNIT_ARRAY, None)
    return arrays, values, None if unit is None else float(np.asarray(unit).reshape(-1)[0])
