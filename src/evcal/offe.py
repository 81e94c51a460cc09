"""OffE: events-only calibration (no frames).

Over a long recording the log intensity at a pixel stays bounded while events pile up, so
``c * P(t) + b * E(t) ≈ L(t) - L(0)`` stays small: cumulative polarity ``P`` regressed on
cumulative count ``E`` (with intercept) at regular time steps has slope ``m ≈ -b / c``, and
its residual RMS ``r`` is the log-intensity excursion measured in events, ``≈ σ_L / c``. With a
population scale ``c0`` (the median contrast, by default the DI value 0.1)::

    c = median(c0 * r) / r,     b = -c * m

Pixels with too few events, no spread in ``E`` or an unrealistic result keep the defaults.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Any

import numba
import numpy as np

from .accumulate import Accumulator
from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, Calibration, OffEDiagnostics, Reason
from .errors import CalibrationError, ConfigError, StateError
from .events import SensorSize
from .recording import Recording
from .special import classify
from .stream import frame_cuts


@dataclass(frozen=True, kw_only=True)
class OffEConfig:
    """``step_us``: sampling period of the cumulative sums; ``c0``: population median
    contrast the relative scale is anchored to."""

    step_us: int = 10_000
    c0: float = DEFAULT_CONTRAST
    min_events: int = 20
    min_steps: int = 10
    max_ratio: float = 5.0  # c outside [median/ratio, median*ratio] is unrealistic

    def __post_init__(self) -> None:
        if self.step_us <= 0:
            raise ConfigError(f"step_us={self.step_us} must be > 0")
        if not self.c0 > 0:
            raise ConfigError(f"c0={self.c0} must be > 0")


def offe(rec: Recording, config: OffEConfig | None = None) -> Calibration:
    """Events-only per-pixel ``c``, ``b`` (frames, if any, are not used)."""
    cfg = config or OffEConfig()
    if rec.n_events == 0:
        raise CalibrationError("OffE needs events: the recording has none")
    # (the loop below is the definition; StreamingOffE computes the same sums per event)
    t = rec.events["t_us"]
    t0, t1 = int(t[0]), int(t[-1])
    steps = np.arange(t0 + cfg.step_us, t1 + cfg.step_us, cfg.step_us, dtype=np.int64)
    n = rec.sensor.n_pixels
    acc = Accumulator(rec.sensor)
    s = {k: np.zeros(n) for k in ("e", "p", "ee", "ep", "pp")}
    pos = 0
    cuts = frame_cuts(t, steps)  # steps cut the stream as frames do
    for cut in cuts:  # loop over time steps, vectorised over pixels
        if cut > pos:
            acc.add(rec.events[pos:cut])
            pos = int(cut)
        e = (acc.on + acc.off).astype(np.float64)
        p = (acc.on - acc.off).astype(np.float64)
        s["e"] += e
        s["p"] += p
        s["ee"] += e * e
        s["ep"] += e * p
        s["pp"] += p * p
    n_events = (acc.on + acc.off).astype(np.int64)
    return offe_from_sums(s, len(steps), n_events, rec.sensor, cfg)


def offe_from_sums(s: dict[str, np.ndarray], n_steps: int, n_events: np.ndarray,
                   sensor: SensorSize, cfg: OffEConfig, *,
                   extra: dict[str, Any] | None = None) -> Calibration:
    """The OffE maps from the per-pixel sums over the time steps of ``E`` (``e``), ``P``
    (``p``), ``E²`` (``ee``), ``E·P`` (``ep``) and ``P²`` (``pp``), flat float64 arrays of one
    value per pixel; raises :class:`~evcal.errors.CalibrationError` when no pixel has enough
    events."""
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
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = float(np.median(cfg.c0 * r[cand]))
        c = np.where(cand, scale / np.where(cand, r, 1.0), DEFAULT_CONTRAST)
        b = np.where(cand, -c * slope, DEFAULT_BIAS)
    med = float(np.median(c[cand]))
    bad = cand & ((c < med / cfg.max_ratio) | (c > med * cfg.max_ratio) | (np.abs(b) >= 0.95 * c))
    reason[bad] = Reason.OUT_OF_RANGE
    valid = reason == 0
    c = np.where(valid, c, DEFAULT_CONTRAST)
    b = np.where(valid, b, DEFAULT_BIAS)
    # No stated errors (inf): c's scale has none that is meaningful without frames (it is
    # the pixel's own light excursion against the typical pixel's, and c0), and b = -c m
    # carries it, so c times the slope's regression error would state far too little. The
    # slope itself (b / c) is measured: its error judges warm and cool pixels.
    with np.errstate(divide="ignore", invalid="ignore"):
        se_slope = np.sqrt(np.where(see > 0, rss / max(m_steps - 2, 1) / see, np.inf))
    se_ratio = np.where(valid, c * se_slope, np.inf)
    se_c = np.full(n, np.inf)
    se_b = np.full(n, np.inf)
    special = classify(c, b, np.where(valid, 0.0, np.inf), se_ratio, valid)
    shape = sensor.shape
    return Calibration(
        contrast=c.reshape(shape), bias=b.reshape(shape), valid=valid.reshape(shape),
        reason=reason.reshape(shape), stderr_contrast=se_c.reshape(shape),
        stderr_bias=se_b.reshape(shape), special=special.reshape(shape), log_offset=math.nan,
        method="offe", n_events=n_events.reshape(shape),
        diagnostics=OffEDiagnostics(step_us=cfg.step_us, c0=cfg.c0, scale=float(scale),
                                    n_steps=int(m_steps), extra=extra or {}),
    )


_SUMS = ("e", "p", "ee", "ep", "pp")  # the columns of StreamingOffE's sums
STREAMING_FORMAT = "evcal.offe.streaming.v1"


# (untyped decorator: evcal.offe is not yet in pyproject's list of numba modules)
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
    """

    def __init__(self, sensor: SensorSize, config: OffEConfig | None = None) -> None:
        self.sensor = sensor
        self.config = config or OffEConfig()
        n = sensor.n_pixels
        self._sums = np.zeros((n, len(_SUMS)))
        self._counts = np.zeros((n, 4), np.int64)  # n, q, latest step index, events at it
        self._counts[:, 2] = -1
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
        n, q = self._counts[:, 0].astype(np.float64), self._counts[:, 1].astype(np.float64)
        a = {"e": n, "p": q, "ee": n * n, "ep": n * q, "pp": q * q}
        s = {k: a[k] * m - self._sums[:, i] for i, k in enumerate(_SUMS)}
        n_events = self._counts[:, 0] - np.where(self._counts[:, 2] == m,
                                                 self._counts[:, 3], 0)
        span_s = max(self.last_t_us - self.t0_us, 1) / 1e6
        return offe_from_sums(s, m, n_events, self.sensor, self.config,
                              extra={"streaming": True, "t0_us": self.t0_us,
                                     "t_us": self.last_t_us,
                                     "event_rate_hz_median": float(np.median(n) / span_s)})

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
        ``(n_pixels, 4)`` int64 and a JSON ``scalars`` string."""
        scalars = {"format": STREAMING_FORMAT, "height": self.sensor.height,
                   "width": self.sensor.width, "config": asdict(self.config),
                   "t0_us": self.t0_us, "last_t_us": self.last_t_us,
                   "n_events": self.n_events}
        return {"sums": self._sums, "counts": self._counts,
                "scalars": np.array(json.dumps(scalars))}

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> StreamingOffE:
        """Resume from :meth:`state_dict` (:class:`~evcal.errors.StateError` if it is not
        one, or its arrays do not fit its sensor)."""
        try:
            sc = json.loads(str(state["scalars"]))
            if sc.get("format") != STREAMING_FORMAT:
                raise StateError(f"unknown streaming OffE state {sc.get('format')!r}")
            sensor = SensorSize(width=int(sc["width"]), height=int(sc["height"]))
            self = cls(sensor, OffEConfig(**sc["config"]))
            for name, arr0 in (("sums", self._sums), ("counts", self._counts)):
                arr = np.asarray(state[name])
                if arr.shape != arr0.shape or arr.dtype != arr0.dtype:
                    raise StateError(f"{name}: {arr.dtype}{arr.shape}, expected "
                                     f"{arr0.dtype}{arr0.shape}")
                arr0[...] = arr
            self.t0_us = None if sc["t0_us"] is None else int(sc["t0_us"])
            self.last_t_us = None if sc["last_t_us"] is None else int(sc["last_t_us"])
            self.n_events = int(sc["n_events"])
        except StateError:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever is wrong, it is not such a state
            raise StateError(f"not a streaming OffE state: {type(exc).__name__}: {exc}"
                             ) from None
        return self
