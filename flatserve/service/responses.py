"""orjson-rendered JSON response (NumPy arrays allowed; NaN becomes null)."""
from __future__ import annotations

from typing import Any

import numpy as np
import orjson
from fastapi import Response

_OPTS = orjson.OPT_SERIALIZE_NUMPY


def _default(obj):
    if isinstance(obj, np.ndarray):  # non-contiguous or of a dtype orjson does not take
        if obj.dtype.kind in "fiub":
            return np.ascontiguousarray(obj)
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


class JSONBytes(Response):
    media_type = "application/json"

    def render(self, content: Any) -> bytes:
        return orjson.dumps(content, option=_OPTS, default=_default)
