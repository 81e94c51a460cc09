"""OffE: events-only calibration (no frames).

Over a long recording the log intensity at a pixel stays bounded while events pile up, so
``c * P(t) + b * E(t) ≈ L(t) - L(0)`` stays small: cumulative polarity ``P`` regressed on
cumulative count ``E`` (with intercept) at regular time steps has slope ``m ≈ -b / c``, and
its residual RMS ``r`` is the log-intensity excursion measured in events, ``≈ σ_L / c``. With a
population scale ``c0`` (the median contrast, by default the DI value 0.1, and the value of
the pixels left uncalibrated)::

    c ∝ ref / r  (median c0),     b = -c * m

The paper's ``ref`` is one for all pixels (``neighbourhood_px=0``): every pixel is assumed to
see the same light excursion ``σ_L``. A moving scene gives each pixel its own (a pixel that
stays on sky sees less than one crossing texture), and that spread, not the thresholds, is
most of what the paper's ratio measures. Neighbouring pixels see nearly the same light while
their thresholds are independent, so by default ``ref`` is the geometric mean of the ``r`` of
the pixel's neighbours (a ``neighbourhood_px`` square, the pixel left out): ``c`` is each
pixel's threshold against its neighbours'. The slope's error is mostly the light's drift
against the count over the recording, which neighbours share too: each pixel's ``m`` is
taken less its neighbours' mean, the population's median added back. What this cannot see is
a threshold or bias structure smoother than the neighbourhood (a gradient across the
sensor): it is flattened, where the paper's ratio could not tell it from the light either.

Stated errors: the recording's two halves in time (:func:`offe`; a live
:class:`StreamingOffE` its run before and after a mark) are fitted apart, and their
differences, read per bin of the pixels' event counts ``n``, give the whole run's variance as
a sum of terms in ``1 / n`` (:data:`LOG_C_TERMS`, :data:`SLOPE_TERMS`: what each term is and
how it scales from a part to the whole); ``se_c = c`` times ``log c``'s root, ``b``'s
combines ``c``'s and ``m``'s. What the parts cannot see is an error both share: a motion
that repeats within the recording shows each pixel the same light in both, and the errors
come out too small (tests/test_recovery.py measures both cases).

Pixels with too few events, no spread in ``E`` or an unrealistic result keep the defaults.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numba
import numpy as np

from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, Calibration, OffEDiagnostics, Reason
from .errors import CalibrationError, ConfigError, StateError
from .events import SensorSize
from .recording import Recording
from .special import classify, robust_spread
from .splithalf import MIN_PIXELS as MIN_HALF_PIXELS


@dataclass(frozen=True, kw_only=True)
class OffEConfig:
    """``step_us``: sampling period of the cumulative sums; ``c0``: population median
    contrast the relative scale is anchored to; ``neighbourhood_px``: the side of the square
    of neighbours each pixel is compared with (odd, at least 3), or 0 for the population (the
    paper's OffE); ``min_neighbours``: a pixel with fewer neighbours that have enough events
    is not calibrated (``FEW_NEIGHBOURS``: too few around it to compare it with)."""

    step_us: int = 10_000
    c0: float = DEFAULT_CONTRAST
    min_events: int = 20
    min_steps: int = 10
    max_ratio: float = 5.0  # c outside [median/ratio, median*ratio] is unrealistic
    neighbourhood_px: int = 5
    min_neighbours: int = 8

    def __post_init__(self) -> None:
        if self.step_us <= 0:
            raise ConfigError(f"step_us={self.step_us} must be > 0")
        if not self.c0 > 0:
            raise ConfigError(f"c0={self.c0} must be > 0")
        k = self.neighbourhood_px
        if k != 0 and (k < 3 or k % 2 == 0):
            raise ConfigError(f"neighbourhood_px={k} must be 0 or odd and >= 3")
        if k and not 1 <= self.min_neighbours <= k * k - 1:
            raise ConfigError(f"min_neighbours={self.min_neighbours} must be in "
                              f"1..{k * k - 1} for neighbourhood_px={k}")


_SUMS = ("e", "p", "ee", "ep", "pp")  # the sums, and the columns of StreamingOffE's


_Halves = tuple[tuple[dict[str, np.ndarray], int, np.ndarray], ...]


def offe(rec: Recording, config: OffEConfig | None = None) -> Calibration:
    """Events-only per-pixel ``c``, ``b`` (frames, if any, are not used), with stated
    errors from the recording's two halves in time (the module's docstring)."""
    cfg = config or OffEConfig()
    if rec.n_events == 0:
        raise CalibrationError("OffE needs events: the recording has none")
    whole, m, n_events, halves = _sums_by_events(rec, cfg)
    return offe_from_sums(whole, m, n_events, rec.sensor, cfg, halves=halves)


def _n_steps(rec: Recording, cfg: OffEConfig) -> int:
    """``M``: the steps ``t0 + k step_us``, ``k = 1..M``, the last at or after the last
    event."""
    t = rec.events["t_us"]
    return -(-(int(t[-1]) - int(t[0])) // cfg.step_us)


def _folded(events: np.ndarray, width: int, n: int, t0: int, step: int, m: int
            ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The sums over steps ``1..m`` after ``t0`` of ``events`` (all at or after ``t0``), by
    :class:`StreamingOffE`'s per-event fold; with each pixel's count and polarity sum over
    all of them (``E``, ``P`` at the end) and its events before step ``m``."""
    sums = np.zeros((n, len(_SUMS)))
    counts = np.zeros((n, 4), np.int64)
    counts[:, 2] = -1
    if events.size:
        _fold(events["t_us"], events["x"], events["y"], events["p"], width, t0, step, sums,
              counts)
    return _from_fold(sums, counts, m)


def _from_fold(sums: np.ndarray, counts: np.ndarray, m: int
               ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    # each sum is A M - B (StreamingOffE's docstring); events at step m are in no sum
    e, q = counts[:, 0].astype(np.float64), counts[:, 1].astype(np.float64)
    a = {"e": e, "p": q, "ee": e * e, "ep": e * q, "pp": q * q}
    s = {k: a[k] * m - sums[:, i] for i, k in enumerate(_SUMS)}
    before_m = counts[:, 0] - np.where(counts[:, 2] == m, counts[:, 3], 0)
    return s, counts[:, :2], before_m


def _sums_by_events(rec: Recording, cfg: OffEConfig
                    ) -> tuple[dict[str, np.ndarray], int, np.ndarray, _Halves]:
    """The sums over the steps of the whole run and of its two halves (split at the middle
    step) in one pass over the events: each half folded from its own start (within a half,
    the cumulative counts from the run's start differ from the half's own by a constant per
    pixel, which the regression's intercept absorbs), the whole's from the halves' (``E ->
    E + E0`` in the second half's sums). tests/test_service_events_only.py keeps the sums'
    definition, step by step over all pixels, to compare with."""
    t = rec.events["t_us"]
    t0 = int(t[0])
    step = cfg.step_us
    m = _n_steps(rec, cfg)
    half = m // 2
    cut = int(np.searchsorted(t, t0 + half * step, side="left"))
    n, w = rec.sensor.n_pixels, rec.sensor.width
    s1, end1, n1 = _folded(rec.events[:cut], w, n, t0, step, half)
    s2, _, n2 = _folded(rec.events[cut:], w, n, t0 + half * step, step, m - half)
    e0, p0 = (end1[:, i].astype(np.float64) for i in (0, 1))
    m2 = float(m - half)
    whole = {
        "e": s1["e"] + s2["e"] + m2 * e0,
        "p": s1["p"] + s2["p"] + m2 * p0,
        "ee": s1["ee"] + s2["ee"] + 2 * e0 * s2["e"] + m2 * e0 * e0,
        "ep": s1["ep"] + s2["ep"] + e0 * s2["p"] + p0 * s2["e"] + m2 * e0 * p0,
        "pp": s1["pp"] + s2["pp"] + 2 * p0 * s2["p"] + m2 * p0 * p0,
    }
    return whole, m, n1 + n2, ((s1, half, n1), (s2, m - half, n2))


# the halves' differences are read in up to this many bins of the pixels' event counts, each
# of at least MIN_BIN_PIXELS pixels
HALF_BINS = 8
MIN_BIN_PIXELS = 200

_Sums = dict[str, np.ndarray]


@dataclass(frozen=True)
class _Fit:
    c: np.ndarray
    b: np.ndarray
    slope: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    scale: float


def _fit(s: _Sums, n_steps: int, n_events: np.ndarray, sensor: SensorSize,
         cfg: OffEConfig) -> _Fit:
    n = sensor.n_pixels
    m_steps = float(n_steps)
    n_events = np.asarray(n_events, np.int64).reshape(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        see = s["ee"] - s["e"] ** 2 / m_steps
        sep = s["ep"] - s["e"] * s["p"] / m_steps
        spp = s["pp"] - s["p"] ** 2 / m_steps
        slope = np.where(see > 0, sep / np.where(see > 0, see, 1.0), 0.0)
        rss = np.maximum(spp - slope * sep, 0.0)
        r = np.sqrt(rss / m_steps)
    reason = np.zeros(n, np.uint8)
    reason[(n_events < cfg.min_events) | (m_steps < cfg.min_steps)] = Reason.TOO_FEW_EVENTS
    reason[(see <= 0) & (reason == 0)] = Reason.RANK_DEFICIENT
    reason[(r <= 0) & (reason == 0)] = Reason.RANK_DEFICIENT
    reason[n_events == 0] = Reason.NO_EVENTS
    cand = reason == 0
    if not cand.any():
        raise CalibrationError("OffE: no pixel has enough events for a regression")
    r_med = float(np.median(r[cand]))
    scale = cfg.c0 * r_med
    ref = np.full(n, r_med)
    if cfg.neighbourhood_px:
        ref, slope, enough = _against_neighbours(r, slope, cand, sensor, cfg)
        # too few neighbours to compare with: the population's reference gave such pixels
        # several times the errors of the population's median (they sit in quiet regions,
        # where a handful of events decide r)
        reason[cand & ~enough] = Reason.FEW_NEIGHBOURS
        cand &= enough
        if not cand.any():
            raise CalibrationError(f"OffE: no pixel has {cfg.min_neighbours} neighbours with "
                                   f"enough events to compare it with (neighbourhood_px=0 "
                                   f"compares with the whole population)")
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(cand, ref / np.where(cand, r, 1.0), cfg.c0)
    c = np.where(cand, c * (cfg.c0 / float(np.median(c[cand]))), c)  # median c0
    b = np.where(cand, -c * slope, DEFAULT_BIAS)
    bad = cand & ((c < cfg.c0 / cfg.max_ratio) | (c > cfg.c0 * cfg.max_ratio)
                  | (np.abs(b) >= 0.95 * c))
    reason[bad] = Reason.OUT_OF_RANGE
    valid = reason == 0
    # the pixels not calibrated take the population's median contrast: c0, not the DI value
    return _Fit(c=np.where(valid, c, cfg.c0), b=np.where(valid, b, DEFAULT_BIAS),
                slope=slope, valid=valid, reason=reason, scale=scale)


def _box_sum(x: np.ndarray, k: int) -> np.ndarray:
    """Sums of ``x`` over the ``k`` x ``k`` square about each pixel (zero beyond the
    edges), by cumulative sums: a few passes over the map whatever ``k``."""
    h, w = x.shape
    c = np.zeros((h + k, w + k))
    c[1:, 1:] = np.pad(x, k // 2).cumsum(0).cumsum(1)
    out: np.ndarray = c[k:, k:] - c[:h, k:] - c[k:, :w] + c[:h, :w]
    return out


def _against_neighbours(r: np.ndarray, slope: np.ndarray, cand: np.ndarray,
                        sensor: SensorSize, cfg: OffEConfig
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's reference ``r`` (the geometric mean of its candidate neighbours', itself
    left out) and its slope less its neighbours' mean, the population's median added back
    (the slope's error is mostly the light's drift against the count, which neighbours
    share), and whether the pixel has at least ``min_neighbours`` such neighbours (where not,
    the reference is the population's and the slope the pixel's own: such pixels are not
    calibrated). Neighbours' values are clipped to the population's
    central band first (a hot pixel beside a normal one must not move it). A mean,
    not a median: the reference's own noise is the error's larger part, and a mean of about
    24 values has two thirds of a median's variance."""
    k = cfg.neighbourhood_px
    shape = sensor.shape
    ok = cand.reshape(shape)
    w = ok.astype(np.float64)
    count = _box_sum(w, k) - w
    out = []
    for x in (np.log(np.where(cand, r, 1.0)), slope):
        med, spread = robust_spread(x[cand])
        xc = np.where(cand, np.clip(x, med - 3 * spread, med + 3 * spread), 0.0).reshape(shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            mean = (_box_sum(xc, k) - xc) / count
        out.append((mean.ravel(), med))
    enough = (count >= cfg.min_neighbours).ravel()
    (log_ref, log_med), (m_ref, m_med) = out
    ref = np.exp(np.where(enough, log_ref, log_med))
    return ref, np.where(enough, slope - m_ref + m_med, slope), enough


def _spread(d: np.ndarray) -> float:
    """The standard deviation of ``d`` without its outliers (beyond five robust spreads:
    a special pixel's halves, one of them fitted on a handful of events)."""
    med, rsd = robust_spread(d)
    keep = np.abs(d - med) <= 5.0 * rsd if rsd > 0 else np.ones(d.size, bool)
    return float(np.std(d[keep]))


# The variance models of the whole run's estimates of a pixel of n events over a span of T,
# each term ``w / (n^pn T^pt)`` given as ``(pn, pt)``. log c: the light's sampling by the
# pixel's path (a constant in n, falling as 1/T: independent parts average it) and the
# counting (1/n). The slope: the counting (1/n) and the light's bounded excursion against the
# count (1/n^2: a drift estimated over n events). A part of a fraction f of the span (and so
# of the events) has each term f^-(pn + pt) times larger; the parts' difference the sum of
# both parts' (at f = 1/2: four times for 1/n and 1/T, eight for 1/n^2).
LOG_C_TERMS = ((0, 1), (1, 0))
SLOPE_TERMS = ((1, 0), (2, 0))


@dataclass(frozen=True)
class ErrorModel:
    """The variance models of ``log c`` and of the slope (coefficients of
    :data:`LOG_C_TERMS` and :data:`SLOPE_TERMS`) read on a run of ``n_steps`` steps, and
    how (the parts' steps, the pixels valid in both)."""

    log_contrast: tuple[float, ...]
    slope: tuple[float, ...]
    n_steps: int
    parts: tuple[int, int]
    pixels: int

    def variances(self, n_events: np.ndarray, n_steps: int
                  ) -> tuple[np.ndarray, np.ndarray]:
        """The variances of ``log c`` and of the slope of pixels of ``n_events`` over a run
        of ``n_steps`` (the terms in 1/T scaled from the run they were read on)."""
        n = np.maximum(np.asarray(n_events, np.float64), 1.0)
        t = self.n_steps / max(n_steps, 1)
        return (_variance_at(self.log_contrast, LOG_C_TERMS, n, t),
                _variance_at(self.slope, SLOPE_TERMS, n, t))

    def to_dict(self) -> dict[str, Any]:
        return {"log_contrast": list(self.log_contrast), "slope": list(self.slope),
                "n_steps": self.n_steps, "parts": list(self.parts), "pixels": self.pixels}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ErrorModel:
        return cls(log_contrast=tuple(float(x) for x in d["log_contrast"]),
                   slope=tuple(float(x) for x in d["slope"]), n_steps=int(d["n_steps"]),
                   parts=(int(d["parts"][0]), int(d["parts"][1])), pixels=int(d["pixels"]))


def _variance(d: np.ndarray, n: np.ndarray, terms: tuple[tuple[int, int], ...], f: float
              ) -> tuple[float, ...]:
    """The coefficients ``w_k`` of the whole run's variance ``sum_k w_k / n^pn_k`` (``terms``,
    module comment) from the two parts' differences ``d`` of pixels with ``n`` events in
    all, the first part a fraction ``f`` of the run: ``d``'s variance read per bin of ``n``
    (at least :data:`MIN_BIN_PIXELS` each), fitted by least squares with every ``w_k >= 0``
    (the best of the terms' subsets; with one bin every one-term model fits it exactly and
    the first term is kept)."""
    order = np.argsort(n, kind="stable")
    bins = np.array_split(order, max(1, min(HALF_BINS, n.size // MIN_BIN_PIXELS)))
    var = np.array([_spread(d[i]) ** 2 for i in bins])
    inv_n = np.array([1.0 / float(np.median(n[i])) for i in bins])
    factor = [f ** -(pn + pt) + (1 - f) ** -(pn + pt) for pn, pt in terms]
    cols = np.column_stack([g * inv_n ** pn for g, (pn, _) in zip(factor, terms, strict=True)])
    best: tuple[float, np.ndarray] = (math.inf, np.zeros(len(terms)))
    for mask in range(1, 2 ** len(terms)):
        use = [k for k in range(len(terms)) if mask >> k & 1]
        if len(use) > len(bins):
            continue
        w_use = np.linalg.lstsq(cols[:, use], var, rcond=None)[0]
        if (w_use < 0).any():
            continue
        cost = float(np.sum((cols[:, use] @ w_use - var) ** 2))
        if cost < best[0]:
            w = np.zeros(len(terms))
            w[use] = w_use
            best = (cost, w)
    return tuple(float(x) for x in best[1])


def _variance_at(w: tuple[float, ...], terms: tuple[tuple[int, int], ...], n: np.ndarray,
                 t_ratio: float = 1.0) -> np.ndarray:
    # t_ratio: the span the model was read on over this one's (terms in 1/T scale by it)
    out: np.ndarray = sum((wk * n ** -float(pn) * t_ratio ** pt
                           for wk, (pn, pt) in zip(w, terms, strict=True)),
                          start=np.zeros(n.shape))
    return out


def _part_errors(parts: _Halves, sensor: SensorSize, cfg: OffEConfig
                 ) -> tuple[ErrorModel | None, str]:
    """The whole run's :class:`ErrorModel`, read on its two parts in time (module
    docstring), or None and why it cannot be."""
    (_, m1, _), (_, m2, _) = parts
    m = m1 + m2
    if m1 <= 0 or m2 <= 0:
        return None, f"parts of {m1} and {m2} steps"
    f = m1 / m
    # a part has a share of the events and steps: the whole run's pixels of min_events have
    # fewer in each (the variance model carries the counts)
    short = min(f, 1 - f)
    part_cfg = replace(cfg, min_events=max(int(cfg.min_events * short), 2),
                       min_steps=max(int(cfg.min_steps * short), 3))
    try:
        a, b = (_fit(s, ms, n, sensor, part_cfg) for s, ms, n in parts)
    except CalibrationError as e:
        return None, f"a part ({m1}, {m2} steps) has no pixel to fit: {e}"
    both = a.valid & b.valid
    k = int(both.sum())
    if k < MIN_HALF_PIXELS:
        return None, f"{k} pixels valid in both parts (fewer than {MIN_HALF_PIXELS})"
    n_all = (np.asarray(parts[0][2]) + np.asarray(parts[1][2]))[both].astype(np.float64)
    return ErrorModel(
        log_contrast=_variance(np.log(a.c[both] / b.c[both]), n_all, LOG_C_TERMS, f),
        slope=_variance(a.slope[both] - b.slope[both], n_all, SLOPE_TERMS, f),
        n_steps=m, parts=(m1, m2), pixels=k), ""


def offe_from_sums(s: _Sums, n_steps: int, n_events: np.ndarray,
                   sensor: SensorSize, cfg: OffEConfig, *,
                   extra: dict[str, Any] | None = None,
                   halves: _Halves | None = None,
                   error_model: ErrorModel | None = None) -> Calibration:
    """The OffE maps from the per-pixel sums over the time steps of ``E`` (``e``), ``P``
    (``p``), ``E²`` (``ee``), ``E·P`` (``ep``) and ``P²`` (``pp``), flat float64 arrays of one
    value per pixel; raises :class:`~evcal.errors.CalibrationError` when no pixel has enough
    events. ``halves``: the same sums, step count and events per pixel of the run's two
    parts in time (halves, or a first part of at least a third), from which the errors are
    stated; ``error_model``: the errors' model read earlier (:class:`StreamingOffE`), used
    when the parts cannot give one. Without either the errors are ``inf``."""
    n = sensor.n_pixels
    fit = _fit(s, n_steps, n_events, sensor, cfg)
    c, b, valid = fit.c, fit.b, fit.valid
    extra = dict(extra or {})
    se_c = np.full(n, np.inf)
    se_b = np.full(n, np.inf)
    model, why = None, "no parts: a live stream's first estimate states no errors"
    if halves is not None:
        model, why = _part_errors(halves, sensor, cfg)
    read_now = model is not None
    if model is None and error_model is not None:
        model = error_model
    extra["errors"] = {**({} if model is None else model.to_dict()),
                       "read_now": read_now, **({"reason": why} if why else {})}
    if model is not None:
        var_log_c, var_m = model.variances(np.asarray(n_events).reshape(n), n_steps)
        se_log_c = np.sqrt(var_log_c)
        se_c = np.where(valid, c * se_log_c, np.inf)
        # b = -c m: the errors of c and m, taken as independent
        se_b = np.where(valid, np.hypot(b * se_log_c, c * np.sqrt(var_m)), np.inf)
    special = classify(c, b, np.where(np.isfinite(se_c), se_c, 0.0),
                       np.where(np.isfinite(se_b), se_b, 0.0), valid)
    shape = sensor.shape
    return Calibration(
        contrast=c.reshape(shape), bias=b.reshape(shape), valid=valid.reshape(shape),
        reason=fit.reason.reshape(shape), stderr_contrast=se_c.reshape(shape),
        stderr_bias=se_b.reshape(shape), special=special.reshape(shape), log_offset=math.nan,
        method="offe", n_events=np.asarray(n_events, np.int64).reshape(shape),
        diagnostics=OffEDiagnostics(step_us=cfg.step_us, c0=cfg.c0, scale=float(fit.scale),
                                    n_steps=int(n_steps), extra=extra),
    )


STREAMING_FORMAT = "evcal.offe.streaming.v2"
# v1 (before the mark): read, with no mark and no error model
_STREAMING_FORMATS = (STREAMING_FORMAT, "evcal.offe.streaming.v1")
MARK_FIELDS = ("mark_sums", "mark_counts")  # the v2 state's arrays beyond v1's
# a live OffE reads its errors' model again once the run is this many times the one it was
# last read on
REREAD_GROWTH = 1.25


@numba.njit(cache=True, nogil=True)
def _fold(t: Any, x: Any, y: Any, p: Any, width: int, t0: int, step: int, sums: Any,
          counts: Any) -> None:  # pragma: no cover - compiled
    # one pass in time order: each event's weights need its pixel's count and polarity sum
    # just before it. A pixel's state is one row of each array (two cache lines per event:
    # with one array per sum, random pixels cost nine misses an event)
    for i in range(t.size):
        k = np.int64(y[i]) * width + x[i]
        j = (t[i] - t0) // step
        pi = np.int64(1) if p[i] > 0 else np.int64(-1)
        nn = counts[k, 0]
        qq = counts[k, 1]
        jf = float(j)
        sums[k, 0] += jf
        sums[k, 1] += pi * jf
        sums[k, 2] += (2 * nn + 1) * jf
        sums[k, 3] += (qq + pi + nn * pi) * jf
        sums[k, 4] += (2 * pi * qq + 1) * jf
        counts[k, 0] = nn + 1
        counts[k, 1] = qq + pi
        if counts[k, 2] == j:
            counts[k, 3] += 1
        else:
            counts[k, 2] = j
            counts[k, 3] = 1


class StreamingOffE:
    """OffE over a live stream: per-pixel sums, updated per chunk of events, that give the
    maps :func:`offe` gives on the same events.

    :func:`offe` sums, at each step ``t0 + k·step_us`` (``k = 1..M``), the cumulative count
    ``E`` and polarity ``P`` of each pixel (events before the step) and their products. An
    event ``i`` at step index ``j_i = (t_i - t0) // step_us`` is in the cumulative sums of
    the ``M - j_i`` steps from ``j_i`` on, so each sum is ``A·M - B`` with, per event (``n``,
    ``q`` the pixel's count and polarity sum before it)::

        w_e = 1, w_p = p, w_ee = 2n + 1, w_ep = q + p + n·p, w_pp = 2p·q + 1
        A += w,  B += w·j_i

    where the ``A`` telescope to ``n, q, n², n·q, q²`` of the pixel's totals. The state is,
    per pixel, the five ``B`` (``sums``, float64: integers, exact below 2^53) and ``n``,
    ``q``, the step index of the pixel's latest events and their number (``counts``, int64;
    events at step ``M`` are in no sum): 72 bytes a pixel, 63 MiB at 1280x720. A chunk is
    one compiled pass over its events in time order (per-pixel sequential: each event's
    weights need the count before it). ``M`` is fixed only when the maps are asked for
    (:meth:`calibration`, at the latest event seen).

    Stated errors, as :func:`offe` states them, need the run in two parts. The state keeps a
    copy of itself taken at a step ``K`` (the *mark*, at the latest event's step: every event
    before it is at or before ``K``): the sums over steps ``1..K`` are the mark's ``A·K -
    B``, those over ``K+1..M`` the whole's less them (their counts from the run's start
    differ from the part's own by a constant, which the regression's intercept absorbs).
    When the second part has grown as long as the first the mark moves to the latest event,
    so the first part is a third to all of the run; the errors' model read on the two parts
    (:class:`ErrorModel`) is kept, and used, its terms in ``1/T`` scaled, while the second
    part is still too short to read one and until the run has grown by
    :data:`REREAD_GROWTH`. The mark doubles the state: 144 bytes a pixel.
    """

    def __init__(self, sensor: SensorSize, config: OffEConfig | None = None) -> None:
        self.sensor = sensor
        self.config = config or OffEConfig()
        n = sensor.n_pixels
        self._sums = np.zeros((n, len(_SUMS)))
        self._counts = np.zeros((n, 4), np.int64)  # n, q, latest step index, events at it
        self._counts[:, 2] = -1
        self._mark_sums = np.zeros_like(self._sums)
        self._mark_counts = self._counts.copy()
        self._mark_k = 0  # no mark yet
        self._error_model: ErrorModel | None = None
        self.t0_us: int | None = None
        self.last_t_us: int | None = None
        self.n_events = 0

    def reset(self) -> None:
        """Forget everything (a new time base: the step grid starts again)."""
        self.__init__(self.sensor, self.config)  # type: ignore[misc]

    def feed_events(self, events: np.ndarray) -> None:
        """Add a chunk (time-ordered, after the previous chunk, inside the sensor: the caller
        checked it). An empty chunk changes nothing."""
        if events.size == 0:
            return
        t = events["t_us"]
        if self.t0_us is None:
            self.t0_us = int(t[0])
        _fold(t, events["x"], events["y"], events["p"], self.sensor.width, self.t0_us,
              self.config.step_us, self._sums, self._counts)
        self.last_t_us = int(t[-1])
        self.n_events += int(events.size)

    @property
    def n_steps(self) -> int:
        """``M``: the steps :func:`offe` would sum over for the events so far."""
        if self.t0_us is None or self.last_t_us is None:
            return 0
        return -(-(self.last_t_us - self.t0_us) // self.config.step_us)

    @property
    def counts(self) -> np.ndarray:
        """Events per pixel so far (int64, flat)."""
        return self._counts[:, 0]

    def calibration(self) -> Calibration:
        """The OffE maps of the events so far (:class:`~evcal.errors.CalibrationError` while
        no pixel has enough)."""
        if self.n_events == 0:
            raise CalibrationError("OffE needs events: none yet")
        assert self.t0_us is not None
        assert self.last_t_us is not None
        m = self.n_steps
        s, _, n_events = _from_fold(self._sums, self._counts, m)
        n = self._counts[:, 0]
        span_s = max(self.last_t_us - self.t0_us, 1) / 1e6
        parts = self._parts(s, m, n_events)
        cal = offe_from_sums(s, m, n_events, self.sensor, self.config,
                             extra={"streaming": True, "t0_us": self.t0_us,
                                    "t_us": self.last_t_us,
                                    "event_rate_hz_median": float(np.median(n) / span_s)},
                             halves=parts, error_model=self._error_model)
        errors = cal.diagnostics.extra["errors"]
        if errors["read_now"]:
            self._error_model = ErrorModel.from_dict(errors)
        if self._mark_k == 0 or m - self._mark_k >= self._mark_k:
            self._set_mark()
        return cal

    def _parts(self, whole: dict[str, np.ndarray], m: int, n_events: np.ndarray
               ) -> _Halves | None:
        """The sums of steps ``1..K`` (the mark's) and ``K+1..M`` (the whole's less them);
        None before a mark with steps after it, and while the errors' model read last is of
        a run not much shorter (reading it costs two more fits of the maps)."""
        k = self._mark_k
        if k <= 0 or m <= k:
            return None
        model = self._error_model
        if model is not None and m < REREAD_GROWTH * model.n_steps:
            return None  # the kept model, scaled, until the run has grown enough
        first, _, n_first = _from_fold(self._mark_sums, self._mark_counts, k)
        second = {key: whole[key] - first[key] for key in _SUMS}
        n_mark = self._mark_counts[:, 0]
        return ((first, k, n_first), (second, m - k, n_events - n_mark))

    def _set_mark(self) -> None:
        assert self.t0_us is not None
        assert self.last_t_us is not None
        np.copyto(self._mark_sums, self._sums)
        np.copyto(self._mark_counts, self._counts)
        self._mark_k = (self.last_t_us - self.t0_us) // self.config.step_us

    def event_rate_hz(self) -> np.ndarray:
        """Per-pixel event rate (events/s over the stream so far, ``[y, x]``): on a still
        scene the noise rate."""
        span_s = 0.0
        if self.t0_us is not None and self.last_t_us is not None:
            span_s = (self.last_t_us - self.t0_us) / 1e6
        n = self._counts[:, 0]
        rate = n / span_s if span_s > 0 else np.zeros(n.size)
        return rate.reshape(self.sensor.shape)

    # -- snapshots -----------------------------------------------------------------------------

    def state_dict(self) -> dict[str, np.ndarray]:
        """Everything to resume: ``sums`` ``(n_pixels, 5)`` float64, ``counts``
        ``(n_pixels, 4)`` int64, the mark's (``mark_sums``, ``mark_counts``) and a JSON
        ``scalars`` string (the mark's step, the errors' model)."""
        scalars = {"format": STREAMING_FORMAT, "height": self.sensor.height,
                   "width": self.sensor.width, "config": asdict(self.config),
                   "t0_us": self.t0_us, "last_t_us": self.last_t_us,
                   "n_events": self.n_events, "mark_k": self._mark_k,
                   "error_model": (None if self._error_model is None
                                   else self._error_model.to_dict())}
        return {"sums": self._sums, "counts": self._counts, "mark_sums": self._mark_sums,
                "mark_counts": self._mark_counts, "scalars": np.array(json.dumps(scalars))}

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> StreamingOffE:
        """Resume from :meth:`state_dict` (:class:`~evcal.errors.StateError` if it is not
        one, or its arrays do not fit its sensor); a v1 state (no mark) resumes without a
        mark, which the next maps set."""
        try:
            sc = json.loads(str(state["scalars"]))
            if sc.get("format") not in _STREAMING_FORMATS:
                raise StateError(f"unknown streaming OffE state {sc.get('format')!r}")
            v1 = sc["format"] != STREAMING_FORMAT
            sensor = SensorSize(width=int(sc["width"]), height=int(sc["height"]))
            self = cls(sensor, OffEConfig(**sc["config"]))
            fields = [("sums", self._sums), ("counts", self._counts)]
            if not v1:
                fields += [("mark_sums", self._mark_sums), ("mark_counts", self._mark_counts)]
            for name, arr0 in fields:
                arr = np.asarray(state[name])
                if arr.shape != arr0.shape or arr.dtype != arr0.dtype:
                    raise StateError(f"{name}: {arr.dtype}{arr.shape}, expected "
                                     f"{arr0.dtype}{arr0.shape}")
                arr0[...] = arr
            self.t0_us = None if sc["t0_us"] is None else int(sc["t0_us"])
            self.last_t_us = None if sc["last_t_us"] is None else int(sc["last_t_us"])
            self.n_events = int(sc["n_events"])
            if not v1:
                self._mark_k = int(sc["mark_k"])
                em = sc["error_model"]
                self._error_model = None if em is None else ErrorModel.from_dict(em)
        except StateError:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever is wrong, it is not such a state
            raise StateError(f"not a streaming OffE state: {type(exc).__name__}: {exc}"
                             ) from None
        return self
