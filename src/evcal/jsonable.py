"""The one JSON cleaner of evcal: numpy values, paths and sensor sizes to plain JSON."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np


def to_jsonable(value: Any) -> Any:
    """``value`` with numpy scalars and arrays, mappings, tuples, paths and enums turned into
    plain Python that :func:`json.dumps` takes; non-finite floats become strings (JSON has no
    NaN or infinity) and anything else unknown its ``str``."""
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, Enum):
        return to_jsonable(value.value)
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, Path):
        return str(value)
    return str(value)  # SensorSize prints as WxH; anything else as its text


def dumps(value: Any, **kwargs: Any) -> str:
    """``json.dumps(to_jsonable(value))`` with sorted keys (stable files and messages)."""
    kwargs.setdefault("sort_keys", True)
    return json.dumps(to_jsonable(value), **kwargs)
