"""The one JSON cleaner of evcal: numpy values, paths and sensor sizes to plain JSON."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np


def to_jsonable(value: Any, *, nonfinite: str = "text") -> Any:
    """``value`` with numpy scalars and arrays, mappings, tuples, paths and enums turned into
    plain Python that :func:`json.dumps` takes; non-finite floats become strings
    (``nonfinite="text"``: the files evcal writes read them back) or ``None``
    (``"null"``: the documents other programs parse, see :func:`strict_dumps`); anything
    else unknown its ``str``."""
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v, nonfinite=nonfinite) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [to_jsonable(v, nonfinite=nonfinite) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist(), nonfinite=nonfinite)
    if isinstance(value, np.generic):
        return to_jsonable(value.item(), nonfinite=nonfinite)
    if isinstance(value, Enum):
        return to_jsonable(value.value, nonfinite=nonfinite)
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        return None if nonfinite == "null" else str(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, Path):
        return str(value)
    return str(value)  # SensorSize prints as WxH; anything else as its text


def dumps(value: Any, **kwargs: Any) -> str:
    """``json.dumps(to_jsonable(value))`` with sorted keys (stable files and messages)."""
    kwargs.setdefault("sort_keys", True)
    return json.dumps(to_jsonable(value), **kwargs)


def strict_dumps(value: Any, **kwargs: Any) -> str:
    """Strict JSON of ``value`` (NaN and infinities as ``null``; ``json.dumps`` would write
    ``NaN``, which JavaScript, Go and jq refuse): every document the service and the
    clients emit (status, cameras, errors, replies)."""
    return json.dumps(to_jsonable(value, nonfinite="null"), allow_nan=False, **kwargs)
