"""orjson-rendered JSON response (NumPy arrays allowed; NaN becomes null)."""
from __future__ import annotations

from typing import Any

import numpy as np
import orjson
from fastapi import Response
from pydantic import BaseModel

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


def model_body(model: type[BaseModel], status_code: int = 200, headers=None,
               **members) -> JSONBytes:
    """The response of ``model`` with these members (NumPy arrays as they are: not
    validated, written by orjson), in the model's order: for answers as large as
    their questions, which the model documents and names but need not copy."""
    out = model.model_construct(**members)
    return JSONBytes({k: v for k, v in out.__dict__.items() if k in out.model_fields_set},
                     status_code=status_code, headers=headers)
