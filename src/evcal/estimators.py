"""The registry of calibration methods: one entry per estimator, used by the CLI and the API.

:func:`calibrate` runs any of them on a :class:`~evcal.recording.Recording` with the common
options (log offset, window, OnEI buffer sizes); :data:`ESTIMATORS` says what each needs and
does (``evcal calibrate --method`` takes its keys).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any

from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, Calibration
from .errors import ConfigError
from .recording import Recording

FALLBACK_LOG_OFFSET = 30.0  # DN: where the offset cannot be estimated (no frames)
ERROR_SCALES = ("auto", "split-half", "none")


@dataclass(frozen=True, kw_only=True)
class CalibrateOptions:
    """The options :func:`calibrate` passes on to an estimator (``None``: its default)."""

    log_offset: float | str = "auto"  # DN, or "auto" (estimated from the frames)
    window_frames: int | None = None  # OffEI's d
    n_small: int | None = None  # OnEI's small buffer (events)
    n_large: int | None = None  # OnEI's large buffer (events)
    smoothing: float | None = None  # OnEI's low-pass factor
    c0: float | None = None  # OffE's scale: the population's median contrast
    # the stated errors checked on the recording's two halves (evcal.splithalf):
    # "split-half", "none", or "auto" (split-half for OnEI, whose error model the frames'
    # noise decides; OffEI's errors come from its own residuals and stay as they are)
    error_scale: str = "auto"

    def __post_init__(self) -> None:
        if self.error_scale not in ERROR_SCALES:
            raise ConfigError(f"error_scale={self.error_scale!r} must be one of "
                              f"{', '.join(ERROR_SCALES)}")
        lo = self.log_offset
        if not (lo == "auto" or (isinstance(lo, (int, float)) and not isinstance(lo, bool)
                                 and lo >= 0)):
            raise ConfigError(f"log_offset={lo!r} must be 'auto' or a number >= 0")


@dataclass(frozen=True)
class Estimator:
    """One calibration method: its name, what it needs and the function that runs it."""

    name: str
    needs_frames: bool
    summary: str
    run: Callable[[Recording, CalibrateOptions], Calibration]


def _log_offset(rec: Recording, opts: CalibrateOptions) -> tuple[float, dict[str, Any]]:
    """The offset to use and how it was found: given, estimated (OffEI's criterion), or the
    fallback when the recording has too little to estimate it from."""
    from .offline import OffEIConfig, estimate_log_offset  # noqa: PLC0415

    if opts.log_offset != "auto":
        return float(opts.log_offset), {"method": "given"}
    if len(rec.frames) < 3 or rec.n_events == 0:
        return FALLBACK_LOG_OFFSET, {"method": "default (no frames to estimate from)"}
    wf = min(opts.window_frames or OffEIConfig().window_frames, len(rec.frames) - 1)
    return estimate_log_offset(rec, OffEIConfig(window_frames=wf))


def _run_offei(rec: Recording, opts: CalibrateOptions) -> Calibration:
    from .offline import OffEIConfig, offei  # noqa: PLC0415

    kw: dict[str, Any] = {} if opts.window_frames is None else {
        "window_frames": opts.window_frames}
    return offei(rec, OffEIConfig(log_offset=opts.log_offset, **kw))


def _run_onei(rec: Recording, opts: CalibrateOptions) -> Calibration:
    from .online import OnEIConfig, onei  # noqa: PLC0415

    off, info = _log_offset(rec, opts)
    kw: dict[str, Any] = {k: v for k, v in (("n_small", opts.n_small),
                                            ("n_large", opts.n_large),
                                            ("smoothing", opts.smoothing)) if v is not None}
    cal = onei(rec, OnEIConfig(log_offset=off, **kw))
    return cal.replace(diagnostics=cal.diagnostics.updated(log_offset_estimation=info))


def _run_offe(rec: Recording, opts: CalibrateOptions) -> Calibration:
    from .offe import OffEConfig, offe  # noqa: PLC0415

    return offe(rec, OffEConfig() if opts.c0 is None else OffEConfig(c0=opts.c0))


def _run_brandli(rec: Recording, opts: CalibrateOptions) -> Calibration:
    from .brandli import BrandliConfig, brandli  # noqa: PLC0415

    off, info = _log_offset(rec, opts)
    cal = brandli(rec, BrandliConfig(log_offset=off))
    return cal.replace(diagnostics=cal.diagnostics.updated(log_offset_estimation=info))


def _run_di(rec: Recording, opts: CalibrateOptions) -> Calibration:
    off, info = _log_offset(rec, opts)
    cal = Calibration.uniform(rec.sensor.shape, DEFAULT_CONTRAST, DEFAULT_BIAS, method="di",
                              log_offset=off)
    return cal.replace(diagnostics=cal.diagnostics.updated(log_offset_estimation=info))


ESTIMATORS: Mapping[str, Estimator] = MappingProxyType({e.name: e for e in (
    Estimator("offei", True, "per-pixel least squares of event sums against the frames' "
              "log-intensity change, overlapping windows, residual correction", _run_offei),
    Estimator("onei", True, "OffEI streamed: event-count-driven large buffer split into "
              "overlapping small ones, low-pass updated (what the service runs)", _run_onei),
    Estimator("offe", False, "events only: cumulative polarity regressed on cumulative count, "
              "each pixel against its neighbours",
              _run_offe),
    Estimator("brandli", True, "baseline of Brandli et al. 2014: ON/OFF gains corrected by "
              "the integration error at each frame", _run_brandli),
    Estimator("di", False, "baseline: c = 0.1, b = 0 everywhere (direct integration)",
              _run_di),
)})


def calibrate(rec: Recording, method: str = "offei", **options: Any) -> Calibration:
    """Calibrate ``rec`` with ``method`` (a key of :data:`ESTIMATORS`).

    ``options`` are the fields of :class:`CalibrateOptions`: ``log_offset`` (DN or ``"auto"``),
    ``window_frames`` (OffEI), ``n_small``, ``n_large``, ``smoothing`` (OnEI), ``c0`` (OffE's
    scale), ``error_scale``
    (the stated errors checked on the recording's two halves: :mod:`evcal.splithalf`; by
    default for OnEI, at about twice its cost).

    Examples
    --------
    >>> from evcal.sim.ideal import SimConfig, simulate_ideal
    >>> rec = simulate_ideal(SimConfig(height=24, width=32, duration_s=0.5, seed=1)).recording
    >>> cal = calibrate(rec, "offei", window_frames=2)
    >>> cal.method, cal.shape, bool(cal.valid.any())
    ('offei', (24, 32), True)
    """
    est = ESTIMATORS.get(method)
    if est is None:
        raise ConfigError(f"unknown method {method!r}; choose one of {', '.join(ESTIMATORS)}")
    opts = CalibrateOptions(**options)
    cal = est.run(rec, opts)
    mode = opts.error_scale
    if mode == "auto":
        mode = "split-half" if method == "onei" else "none"
    if mode == "none":
        return cal
    from . import splithalf  # noqa: PLC0415

    def run_half(half: Recording, log_offset: float) -> Calibration:
        return est.run(half, replace(opts, log_offset=log_offset, error_scale="none"))

    return splithalf.with_scale(cal, splithalf.split_half_scale(rec, cal, run_half))
