"""The result every estimator returns: per-pixel contrast and bias maps with validity.

Defaults: a pixel the estimator cannot trust keeps ``c = 0.1``, ``b = 0`` (the DI values), has
``valid = False`` and a :class:`Reason` code saying why; its standard errors are ``inf``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np

DEFAULT_CONTRAST = 0.1
DEFAULT_BIAS = 0.0


class Reason(IntEnum):
    """Why a pixel is invalid (``reason`` map, uint8)."""

    VALID = 0
    NO_EVENTS = 1  # unobserved: not one event
    TOO_FEW_EVENTS = 2  # fewer events or equations than the estimator needs
    RANK_DEFICIENT = 3  # [sum P, sum E] columns (nearly) collinear: c and b not separable
    SATURATED = 4  # the frames at this pixel are clipped at 0 or full scale
    CONSTANT = 5  # the frames never change at this pixel
    OUT_OF_RANGE = 6  # the solution is not physical (c <= 0 or |b| >= c or c too large)


class Special(IntEnum):
    """Special-pixel classes (``special`` map, uint8).

    hot: contrast significantly below the population (fires too often); cold: significantly
    above (fires too rarely); warm: bias significantly below the population (the ON threshold
    ``c + b`` is low: ON-prone); cool: bias significantly above (OFF-prone).
    """

    UNOBSERVED = 0
    NORMAL = 1
    HOT = 2
    COLD = 3
    WARM = 4
    COOL = 5


SPECIAL_LEGEND = {int(s): s.name.lower() for s in Special}
REASON_LEGEND = {int(r): r.name.lower() for r in Reason}


@dataclass(frozen=True)
class Calibration:
    """Per-pixel calibration of one sensor; every map is ``[H, W]``."""

    contrast: np.ndarray
    bias: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    stderr_contrast: np.ndarray
    stderr_bias: np.ndarray
    special: np.ndarray
    log_offset: float
    method: str
    n_events: np.ndarray  # events used per pixel (int64)
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        shape = np.shape(self.contrast)
        if len(shape) != 2:
            raise ValueError(f"contrast map has shape {shape}, expected (H, W)")
        for name in ("bias", "valid", "reason", "stderr_contrast", "stderr_bias", "special",
                     "n_events"):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(
                    f"{name} map has shape {np.shape(getattr(self, name))}, contrast has {shape}"
                )
        object.__setattr__(self, "contrast", np.asarray(self.contrast, np.float32))
        object.__setattr__(self, "bias", np.asarray(self.bias, np.float32))
        object.__setattr__(self, "valid", np.asarray(self.valid, bool))
        object.__setattr__(self, "reason", np.asarray(self.reason, np.uint8))
        object.__setattr__(self, "stderr_contrast", np.asarray(self.stderr_contrast, np.float32))
        object.__setattr__(self, "stderr_bias", np.asarray(self.stderr_bias, np.float32))
        object.__setattr__(self, "special", np.asarray(self.special, np.uint8))
        object.__setattr__(self, "n_events", np.asarray(self.n_events, np.int64))
        for name in ("contrast", "bias"):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"{name} map contains NaN or infinite values")

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.contrast.shape)  # type: ignore[return-value]

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean()) if self.valid.size else 0.0

    @classmethod
    def uniform(
        cls,
        shape: tuple[int, int],
        contrast: float = DEFAULT_CONTRAST,
        bias: float = DEFAULT_BIAS,
        *,
        method: str = "di",
        log_offset: float = 0.0,
    ) -> Calibration:
        """The same ``c``, ``b`` everywhere (direct integration, DI)."""
        return cls(
            contrast=np.full(shape, contrast, np.float32),
            bias=np.full(shape, bias, np.float32),
            valid=np.ones(shape, bool),
            reason=np.zeros(shape, np.uint8),
            stderr_contrast=np.zeros(shape, np.float32),
            stderr_bias=np.zeros(shape, np.float32),
            special=np.full(shape, Special.NORMAL, np.uint8),
            log_offset=float(log_offset),
            method=method,
            n_events=np.zeros(shape, np.int64),
            params={"contrast": contrast, "bias": bias},
        )

    def replace(self, **changes: Any) -> Calibration:
        values = {k: getattr(self, k) for k in self.__dataclass_fields__}
        values.update(changes)
        return Calibration(**values)

    def summary(self) -> dict[str, Any]:
        """Population figures of the valid pixels (for tables and logs)."""
        v = self.valid
        out: dict[str, Any] = {
            "method": self.method,
            "valid_fraction": self.valid_fraction,
            "log_offset": self.log_offset,
        }
        if v.any():
            c, b = self.contrast[v], self.bias[v]
            out.update(
                contrast_median=float(np.median(c)),
                contrast_p05=float(np.percentile(c, 5)),
                contrast_p95=float(np.percentile(c, 95)),
                bias_median=float(np.median(b)),
                bias_p05=float(np.percentile(b, 5)),
                bias_p95=float(np.percentile(b, 95)),
            )
        counts = np.bincount(self.special.ravel(), minlength=len(Special))
        out["special_counts"] = {SPECIAL_LEGEND[i]: int(counts[i]) for i in range(len(Special))}
        return out
