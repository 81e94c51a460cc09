"""Calibration files: an ``.npz`` of every map, and the CSV pair of the reference MATLAB code.

The ``.npz`` holds exactly these arrays (maps are ``[H, W]``)::

    contrast, bias, stderr_contrast, stderr_bias   float32
    valid                                          bool
    reason, special                                uint8 (Reason, Special codes)
    n_events                                       int64
    log_offset                                     float64, 0-d
    method, params_json                            str, 0-d (params as JSON)
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import Calibration, Reason, Special
from ._util import load_npz_arrays, to_jsonable

MAP_DTYPES: dict[str, np.dtype] = {
    "contrast": np.dtype(np.float32),
    "bias": np.dtype(np.float32),
    "valid": np.dtype(bool),
    "reason": np.dtype(np.uint8),
    "stderr_contrast": np.dtype(np.float32),
    "stderr_bias": np.dtype(np.float32),
    "special": np.dtype(np.uint8),
    "n_events": np.dtype(np.int64),
}
CALIBRATION_KEYS = frozenset(MAP_DTYPES) | {"log_offset", "method", "params_json"}
# dtype kinds accepted on load (cast to MAP_DTYPES): f float, b bool, u/i integers
_KINDS = {"contrast": "f", "bias": "f", "stderr_contrast": "f", "stderr_bias": "f",
          "valid": "b", "reason": "ui", "special": "ui", "n_events": "ui"}


class CalibrationFileError(ValueError):
    """A calibration file that is missing, damaged or does not hold a valid calibration."""


def save_calibration(cal: Calibration, path: str | os.PathLike[str]) -> Path:
    """Write ``cal`` as a compressed ``.npz`` with exactly :data:`CALIBRATION_KEYS`.

    The path is used as given (no ``.npz`` is appended). Returns the path.
    """
    path = Path(path)
    arrays: dict[str, Any] = {k: np.asarray(getattr(cal, k), dt) for k, dt in MAP_DTYPES.items()}
    arrays["log_offset"] = np.float64(cal.log_offset)
    arrays["method"] = np.array(str(cal.method))
    arrays["params_json"] = np.array(json.dumps(to_jsonable(cal.params), default=repr,
                                                sort_keys=True))
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


def _scalar_str(data: dict[str, np.ndarray], key: str, path: Path) -> str:
    a = data[key]
    if a.shape != () or a.dtype.kind != "U":
        raise CalibrationFileError(f"{path}: {key} is {a.dtype} {a.shape}, expected a 0-d string")
    return str(a)


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration written by :func:`save_calibration`, checking keys, dtypes, shapes.

    Raises
    ------
    CalibrationFileError
        Naming the missing key, the map of the wrong shape or dtype, or the bad value.
    """
    path = Path(path)
    data = load_npz_arrays(path, CalibrationFileError)
    missing = sorted(CALIBRATION_KEYS - set(data))
    if missing:
        hint = " (this looks like a recording, not a calibration)" if "events" in data else ""
        raise CalibrationFileError(f"{path}: missing array(s) {missing}{hint}")
    shape = data["contrast"].shape
    if len(shape) != 2:
        raise CalibrationFileError(f"{path}: contrast has shape {shape}, expected (H, W)")
    maps: dict[str, np.ndarray] = {}
    for key, dt in MAP_DTYPES.items():
        a = data[key]
        if a.shape != shape:
            raise CalibrationFileError(f"{path}: {key} has shape {a.shape}, contrast has {shape}")
        if a.dtype.kind not in _KINDS[key]:
            raise CalibrationFileError(f"{path}: {key} has dtype {a.dtype}, expected {dt}")
        maps[key] = a.astype(dt, copy=False)
    for key, enum in (("reason", Reason), ("special", Special)):
        top = max(int(v) for v in enum)
        if maps[key].size and int(maps[key].max()) > top:
            raise CalibrationFileError(f"{path}: {key} holds code {int(maps[key].max())}, "
                                       f"the largest {enum.__name__} code is {top}")
    lo = data["log_offset"]
    if lo.shape != () or lo.dtype.kind not in "fiu" or not math.isfinite(float(lo)):
        raise CalibrationFileError(f"{path}: log_offset is {lo.dtype} {lo.shape} = {lo!r}, "
                                   "expected a finite 0-d float")
    method = _scalar_str(data, "method", path)
    try:
        params = json.loads(_scalar_str(data, "params_json", path))
    except ValueError as exc:
        raise CalibrationFileError(f"{path}: params_json is not valid JSON ({exc})") from None
    if not isinstance(params, dict):
        raise CalibrationFileError(f"{path}: params_json is a {type(params).__name__}, "
                                   "expected an object")
    try:
        return Calibration(log_offset=float(lo), method=method, params=params, **maps)
    except ValueError as exc:
        raise CalibrationFileError(f"{path}: {exc}") from None


def write_csv(cal: Calibration, folder: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``scale.csv`` (contrast) and ``bias.csv`` as the reference MATLAB code does.

    Plain comma-separated matrices, H rows of W values, ``%.6f``, no header. The folder is
    created if needed. Returns the two paths.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = (folder / "scale.csv", folder / "bias.csv")
    for file, values in zip(out, (cal.contrast, cal.bias)):
        np.savetxt(file, values, fmt="%.6f", delimiter=",")
    return out
