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

import io
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import MAP_NAMES, MAP_SPECS, Calibration
from ..errors import EvcalError
from ..jsonable import dumps
from ._util import load_npz_arrays

# the .npz holds the maps of the schema plus these scalars
SCALAR_KEYS = frozenset({"log_offset", "method", "params_json"})
CALIBRATION_KEYS = frozenset(MAP_NAMES) | SCALAR_KEYS


class CalibrationFileError(EvcalError):
    """A calibration file that is missing, damaged or does not hold a valid calibration."""


def calibration_npz_arrays(cal: Calibration, names: Any = None, *,
                           extra: Mapping[str, Any] | None = None) -> dict[str, np.ndarray]:
    """The arrays of the calibration ``.npz`` layout (maps in their schema dtypes).

    With ``names`` only those maps are included (such a file is not loadable by
    :func:`load_calibration`); ``extra`` figures are merged into ``params_json`` (the service
    adds the calibration's sensor time ``t_us``).
    """
    arrays: dict[str, np.ndarray] = {k: np.asarray(v, MAP_SPECS[k].dtype)
                                     for k, v in cal.maps(names).items()}
    arrays["log_offset"] = np.array(cal.log_offset, np.float64)
    arrays["method"] = np.array(str(cal.method))
    params = cal.diagnostics.to_dict() | dict(extra or {})
    arrays["params_json"] = np.array(dumps(params))
    return arrays


def calibration_npz_bytes(cal: Calibration, names: Any = None, *,
                          extra: Mapping[str, Any] | None = None,
                          arrays: Mapping[str, np.ndarray] | None = None) -> bytes:
    """:func:`calibration_npz_arrays` (plus ``arrays``, maps beside the calibration's: such a
    file is not loadable by :func:`load_calibration`) as the bytes of a compressed ``.npz``
    (in memory)."""
    buf = io.BytesIO()
    out: dict[str, Any] = calibration_npz_arrays(cal, names, extra=extra) | dict(arrays or {})
    np.savez_compressed(buf, **out)
    return buf.getvalue()


def save_calibration(cal: Calibration, path: str | os.PathLike[str]) -> Path:
    """Write ``cal`` as a compressed ``.npz`` with exactly :data:`CALIBRATION_KEYS`.

    The path is used as given (no ``.npz`` is appended). Returns the path.
    """
    path = Path(path)
    with open(path, "wb") as f:
        f.write(calibration_npz_bytes(cal))
    return path


def _scalar_str(data: Mapping[str, np.ndarray], key: str, where: str) -> str:
    a = data[key]
    if a.shape != () or a.dtype.kind != "U":
        raise CalibrationFileError(f"{where}: {key} is {a.dtype} {a.shape}, expected a 0-d "
                                   "string")
    return str(a)


def calibration_from_npz_arrays(data: Mapping[str, np.ndarray], where: str) -> Calibration:
    """A calibration from the arrays of its ``.npz`` layout, every key, dtype, shape and code
    checked (:class:`CalibrationFileError` naming ``where`` and the problem)."""
    missing = sorted(CALIBRATION_KEYS - set(data))
    if missing:
        hint = " (this looks like a recording, not a calibration)" if "events" in data else ""
        raise CalibrationFileError(f"{where}: missing array(s) {missing}{hint}")
    lo = data["log_offset"]
    if lo.shape != () or lo.dtype.kind not in "fiu" or math.isinf(float(lo)):
        raise CalibrationFileError(f"{where}: log_offset is {lo.dtype} {lo.shape} = {lo!r}, "
                                   "expected a 0-d float (NaN when unknown)")
    method = _scalar_str(data, "method", where)
    try:
        params = json.loads(_scalar_str(data, "params_json", where))
    except ValueError as exc:
        raise CalibrationFileError(f"{where}: params_json is not valid JSON ({exc})") from None
    if not isinstance(params, dict):
        raise CalibrationFileError(f"{where}: params_json is a {type(params).__name__}, "
                                   "expected an object")
    try:
        return Calibration.from_maps({k: data[k] for k in MAP_NAMES}, log_offset=float(lo),
                                     method=method, diagnostics=params)
    except EvcalError as exc:
        raise CalibrationFileError(f"{where}: {exc}", exc.reason) from None


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration written by :func:`save_calibration`, checking keys, dtypes, shapes.

    Raises
    ------
    CalibrationFileError
        Naming the missing key, the map of the wrong shape or dtype, or the bad value.
    """
    path = Path(path)
    return calibration_from_npz_arrays(load_npz_arrays(path, CalibrationFileError), str(path))


def write_csv(cal: Calibration, folder: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``scale.csv`` (contrast) and ``bias.csv`` as the reference MATLAB code does.

    Plain comma-separated matrices, H rows of W values, ``%.6f``, no header. The folder is
    created if needed. Returns the two paths.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = (folder / "scale.csv", folder / "bias.csv")
    for file, values in zip(out, (cal.contrast, cal.bias), strict=True):
        np.savetxt(file, values, fmt="%.6f", delimiter=",")
    return out
