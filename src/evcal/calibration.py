"""The result every estimator returns: per-pixel contrast and bias maps with validity.

Defaults: a pixel the estimator cannot trust keeps ``c = 0.1``, ``b = 0`` (the DI values), has
``valid = False`` and a :class:`Reason` code saying why; its standard errors are ``inf``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from enum import IntEnum
from types import MappingProxyType
from typing import Any, ClassVar, cast

import numpy as np

from .errors import ErrorReason, EvcalError
from .jsonable import to_jsonable

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
    FEW_NEIGHBOURS = 7  # OffE: too few neighbours with enough events to compare it with


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


class CalibrationDataError(EvcalError):
    """Maps that do not form a calibration (shapes, dtypes, codes, non-finite values)."""


# ----------------------------------------------------------------------------------------
# the one schema of the maps: files (evcal.io.calibfile), the wire (evcal.io.wire) and the
# service (queries, snapshots) all go through this table


@dataclass(frozen=True)
class MapSpec:
    """One per-pixel map of a calibration: its name, dtypes and meaning.

    ``dtype`` is the dtype in memory and in ``.npz`` files; ``wire`` the little-endian dtype of
    network messages (``bool`` travels as ``u1``); ``kinds`` the dtype kinds a reader accepts
    and casts to ``dtype``.
    """

    name: str
    dtype: np.dtype[Any]
    wire: np.dtype[Any]
    kinds: str
    doc: str


CALIBRATION_MAPS: tuple[MapSpec, ...] = (
    MapSpec("contrast", np.dtype(np.float32), np.dtype("<f4"), "f", "contrast threshold c"),
    MapSpec("bias", np.dtype(np.float32), np.dtype("<f4"), "f", "bias b"),
    MapSpec("valid", np.dtype(bool), np.dtype("u1"), "bu", "pixel trusted (else defaults)"),
    MapSpec("reason", np.dtype(np.uint8), np.dtype("u1"), "ui", "Reason code"),
    MapSpec("stderr_contrast", np.dtype(np.float32), np.dtype("<f4"), "f", "standard error of c"),
    MapSpec("stderr_bias", np.dtype(np.float32), np.dtype("<f4"), "f", "standard error of b"),
    MapSpec("special", np.dtype(np.uint8), np.dtype("u1"), "ui", "Special class"),
    MapSpec("n_events", np.dtype(np.int64), np.dtype("<i8"), "ui", "events used"),
)
MAP_SPECS: Mapping[str, MapSpec] = MappingProxyType({s.name: s for s in CALIBRATION_MAPS})
MAP_NAMES: tuple[str, ...] = tuple(MAP_SPECS)
_CODE_ENUMS: dict[str, type[IntEnum]] = {"reason": Reason, "special": Special}


def check_map_names(names: Any) -> list[str]:
    """``names`` as a list, or :class:`CalibrationDataError` naming the unknown ones."""
    out = [str(n) for n in names]
    unknown = sorted(set(out) - set(MAP_NAMES))
    if unknown:
        raise CalibrationDataError(f"unknown field(s) {unknown}; known: {sorted(MAP_NAMES)}",
                                   ErrorReason.BAD_QUERY)
    return out


def check_map(name: str, values: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """One map checked against the schema and cast to its dtype (no copy when it has it)."""
    spec = MAP_SPECS[name]
    a = np.asarray(values)
    if a.ndim != 2:
        raise CalibrationDataError(f"{name} map has shape {a.shape}, expected (H, W)")
    if shape is not None and a.shape != shape:
        raise CalibrationDataError(f"{name} map has shape {a.shape}, contrast has {shape}")
    if a.dtype.kind not in spec.kinds:
        raise CalibrationDataError(f"{name} map has dtype {a.dtype}, expected {spec.dtype}")
    a = a.astype(spec.dtype, copy=False)
    enum = _CODE_ENUMS.get(name)
    if enum is not None and a.size:
        top = max(int(v) for v in enum)
        if int(a.max()) > top:
            raise CalibrationDataError(f"{name} map holds code {int(a.max())}, the largest "
                                       f"{enum.__name__} code is {top}", ErrorReason.OUT_OF_RANGE)
    if name in ("contrast", "bias") and not np.isfinite(a).all():
        raise CalibrationDataError(f"{name} map contains NaN or infinite values",
                                   ErrorReason.BAD_VALUES)
    return a


# ----------------------------------------------------------------------------------------
# what each estimator reports beside its maps


_DIAGNOSTICS: dict[str, type[Diagnostics]] = {}


@dataclass(frozen=True, kw_only=True)
class Diagnostics:
    """Figures an estimator reports beside its maps, and warnings for the user.

    Each estimator has a subclass with typed fields (``OffEIDiagnostics.residual_lambda``...).
    Files and messages carry them as the JSON object ``params_json``; :meth:`from_dict` reads
    it back into the method's class, keeping figures it has no field for in ``extra`` (files of
    other versions). Fields named in ``_not_saved`` (large in-memory results such as OnEI's
    history) are not written.
    """

    method: ClassVar[str] = ""
    _not_saved: ClassVar[frozenset[str]] = frozenset()
    warnings: tuple[str, ...] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.method:
            _DIAGNOSTICS[cls.method] = cls

    def to_dict(self) -> dict[str, Any]:
        """The JSON-able figures (``extra`` merged in, ``warnings`` as a list)."""
        out: dict[str, Any] = dict(self.extra)
        for f in fields(self):
            if f.name in ("extra",) or f.name in self._not_saved:
                continue
            out[f.name] = getattr(self, f.name)
        if not self.warnings:
            out.pop("warnings", None)
        # to_jsonable of a mapping is a dict with str keys
        return cast("dict[str, Any]", to_jsonable(out))

    @staticmethod
    def from_dict(method: str, values: Mapping[str, Any]) -> Diagnostics:
        """The diagnostics of ``method`` from their JSON object (any unknown key in ``extra``)."""
        cls = _DIAGNOSTICS.get(method, Diagnostics)
        names = {f.name for f in fields(cls)} - {"extra"} - set(cls._not_saved)
        kwargs: dict[str, Any] = {k: v for k, v in values.items() if k in names}
        for f in fields(cls):  # JSON carries non-finite floats as text ("nan")
            v = kwargs.get(f.name)
            if isinstance(v, str) and "float" in str(f.type) and v in ("nan", "inf", "-inf"):
                kwargs[f.name] = float(v)
        if "warnings" in kwargs:
            kwargs["warnings"] = tuple(str(w) for w in kwargs["warnings"])
        extra = {k: v for k, v in values.items() if k not in names}
        try:
            return cls(extra=extra, **kwargs)
        except (TypeError, ValueError):  # a field of the wrong type: keep everything as extra
            return Diagnostics(extra=dict(values))

    def with_warning(self, text: str) -> Diagnostics:
        return replace(self, warnings=(*self.warnings, text))

    def updated(self, **changes: Any) -> Diagnostics:
        """The same diagnostics with some fields changed (the method's own fields)."""
        return replace(self, **changes)


@dataclass(frozen=True, kw_only=True)
class UniformDiagnostics(Diagnostics):
    """DI: the same ``c``, ``b`` everywhere."""

    method: ClassVar[str] = "di"
    contrast: float = DEFAULT_CONTRAST
    bias: float = DEFAULT_BIAS
    log_offset_estimation: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class OffEIDiagnostics(Diagnostics):
    """OffEI (:func:`evcal.offei.offei`)."""

    method: ClassVar[str] = "offei"
    _not_saved: ClassVar[frozenset[str]] = frozenset({"error_correlation"})
    residual_lambda: float = 0.0  # the residual-correction factor used
    window_frames: int = 0  # d: frame intervals per equation
    residual_correction: str | float = "auto"
    log_offset_estimation: Mapping[str, Any] = field(default_factory=dict)
    n_frames: int = 0
    # the standard errors' noise model (evcal.solver.overlap_standard_errors): how many
    # windows' worth of noise overlapping windows share, and the spread of the pixels' own
    # residual-correction factors about residual_lambda
    noise_overlap: float = 0.0
    lambda_spread: float = 0.0
    # evcal.gap.correct: the effects whose bias was removed and the gains/offsets applied
    model_correction: Mapping[str, Any] = field(default_factory=dict)
    # [H, W] float32: the correlation of each pixel's errors of c and b (NaN where not
    # valid); with stderr_contrast and stderr_bias their covariance. In memory only
    error_correlation: np.ndarray | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True, kw_only=True)
class OnEIDiagnostics(Diagnostics):
    """OnEI (:class:`evcal.online.OnlineCalibrator`): the state of its buffers at the time."""

    method: ClassVar[str] = "onei"
    _not_saved: ClassVar[frozenset[str]] = frozenset({"history"})
    n_updates: int = 0
    n_events: int = 0
    n_frames: int = 0
    buffer_events: int = 0
    buffer_frames: int = 0
    buffer_equations: int = 0
    buffer_bytes: int = 0
    pending_events: int = 0
    folded_late_events: int = 0
    # frames that came before events counted ahead of them (their interval counted again)
    refolds: int = 0
    late_events: int = 0
    gaps: int = 0
    sessions: int = 0  # discontinuities of the stream's time base (buffers emptied)
    residual_lambda: float = 0.0
    n_small: int = 0
    n_large: int = 0
    last_frame_t_us: int | None = None
    log_offset: float = math.nan  # the offset the equations use (NaN: not estimated yet)
    log_offset_state: str = ""  # where the online estimate stands (waiting, running, ...)
    config: Mapping[str, Any] = field(default_factory=dict)
    log_offset_estimation: Mapping[str, Any] = field(default_factory=dict)
    # how the stated standard errors were calibrated (evcal.onei.stderr: the sandwich's
    # factors and what they were measured on, or why they were not)
    stderr_calibration: Mapping[str, Any] = field(default_factory=dict)
    # (t_us, contrast, bias, valid) after every n-th update (onei(history_every=n)); in memory
    history: tuple[tuple[int, np.ndarray, np.ndarray, np.ndarray], ...] = ()


@dataclass(frozen=True, kw_only=True)
class OffEDiagnostics(Diagnostics):
    """OffE (:func:`evcal.offe.offe`). ``scale``: ``c0`` times the population's median
    residual ``r`` (the paper's ``c = scale / r``; with neighbours each pixel's own
    reference takes its place)."""

    method: ClassVar[str] = "offe"
    step_us: int = 0
    c0: float = DEFAULT_CONTRAST
    scale: float = 1.0
    n_steps: int = 0


@dataclass(frozen=True, kw_only=True)
class BrandliDiagnostics(Diagnostics):
    """Brandli et al. 2014 (:func:`evcal.brandli.brandli`)."""

    method: ClassVar[str] = "brandli"
    eta: float = 0.0
    min_step: float = 0.0
    max_step: float = 0.0
    log_offset_estimation: Mapping[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------
# the calibration


@dataclass(frozen=True)
class Calibration:
    """Per-pixel calibration of one sensor; every map is ``[H, W]`` (see :data:`CALIBRATION_MAPS`).

    Construction checks and casts every map against the schema: equal shapes, dtype kinds,
    ``reason`` and ``special`` codes in range, finite ``contrast`` and ``bias``
    (:class:`CalibrationDataError` otherwise).
    """

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
    diagnostics: Diagnostics = field(default_factory=Diagnostics)

    def __post_init__(self) -> None:
        shape = check_map("contrast", self.contrast).shape
        for spec in CALIBRATION_MAPS:
            object.__setattr__(self, spec.name, check_map(spec.name, getattr(self, spec.name),
                                                          shape))
        lo = self.log_offset
        if isinstance(lo, bool) or not isinstance(lo, (int, float, np.number)) or not (
                math.isnan(float(lo)) or (math.isfinite(float(lo)) and float(lo) >= 0)):
            raise CalibrationDataError(f"log_offset={lo!r} must be a number >= 0 (DN), or NaN "
                                       "when unknown", ErrorReason.BAD_VALUES)
        object.__setattr__(self, "log_offset", float(lo))
        if not isinstance(self.method, str):
            raise CalibrationDataError(f"method must be a string, got {self.method!r}")
        if not isinstance(self.diagnostics, Diagnostics):
            raise CalibrationDataError(f"diagnostics must be a Diagnostics, got "
                                       f"{type(self.diagnostics).__name__}")

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.contrast.shape
        return (int(h), int(w))

    @property
    def log_offset_known(self) -> bool:
        """False when the calibration does not say its offset (NaN)."""
        return not math.isnan(self.log_offset)

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean()) if self.valid.size else 0.0

    @property
    def warnings(self) -> tuple[str, ...]:
        return self.diagnostics.warnings

    def maps(self, names: Any = None) -> dict[str, np.ndarray]:
        """The maps by name (all, or the ``names`` given; unknown names raise)."""
        return {n: getattr(self, n) for n in (MAP_NAMES if names is None
                                              else check_map_names(names))}

    @classmethod
    def from_maps(cls, maps: Mapping[str, Any], *, log_offset: float, method: str,
                  diagnostics: Diagnostics | Mapping[str, Any] | None = None) -> Calibration:
        """A calibration from a full set of maps (a file, a message), checked."""
        missing = sorted(set(MAP_NAMES) - set(maps))
        if missing:
            raise CalibrationDataError(f"map(s) {missing} missing")
        if diagnostics is None or not isinstance(diagnostics, Diagnostics):
            diagnostics = Diagnostics.from_dict(method, diagnostics or {})
        return cls(**{n: maps[n] for n in MAP_NAMES}, log_offset=log_offset, method=method,
                   diagnostics=diagnostics)

    @classmethod
    def uniform(
        cls,
        shape: tuple[int, int],
        contrast: float = DEFAULT_CONTRAST,
        bias: float = DEFAULT_BIAS,
        *,
        method: str = "di",
        log_offset: float = math.nan,
    ) -> Calibration:
        """The same ``c``, ``b`` everywhere (direct integration, DI). Its ``log_offset`` is
        unknown (NaN) unless given: 0 is a legitimate offset (``log(DN)``), never a marker."""
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
            diagnostics=UniformDiagnostics(contrast=float(contrast), bias=float(bias)),
        )

    def replace(self, **changes: Any) -> Calibration:
        return replace(self, **changes)

    def with_invalid_filled(self) -> Calibration:
        """The same maps with each invalid pixel's ``c``, ``b`` (the defaults, a marker rather
        than an estimate) replaced by the median of the valid pixels: what to integrate events
        with where the calibration has no estimate. Unchanged when no pixel or every pixel is
        valid."""
        v = self.valid
        if not v.any() or v.all():
            return self
        return replace(
            self,
            contrast=np.where(v, self.contrast, np.median(self.contrast[v])).astype(
                self.contrast.dtype),
            bias=np.where(v, self.bias, np.median(self.bias[v])).astype(self.bias.dtype))

    def with_warning(self, text: str) -> Calibration:
        """The same calibration with one more warning in its diagnostics."""
        return replace(self, diagnostics=self.diagnostics.with_warning(text))

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
