"""The library of non-ideal sensor effects: one frozen parameter object per effect.

Each effect is a documented, composable piece with its parameters and units; the simulator
(:func:`evcal.sim.nonideal.simulate`) applies any combination. The names are stable: they are
what ``evcal gap`` reports.

========================  =========================================================  ==========
name                      what the sensor does                                       main param
========================  =========================================================  ==========
``refractory``            dead time ``period_us`` after every event; crossings in it   period_us
                          are lost (``mode="drop"``: the reference is re-latched to
                          the log intensity at the end of the dead time) or delayed
                          (``mode="delay"``: they fire at the end of the dead time and
                          the reference moves by the threshold as usual)
``leak``                  the reference drifts down by ``rate * th_on`` per second:    rate_hz
                          ON events at a per-pixel rate, log-normal across pixels
                          (mean ``rate_hz``, ``spread_log`` = sigma of ln rate),
                          optionally growing with light as ``(I / ref_dn)**light_exponent``
``shot_noise``            random ON and OFF events (50/50) at                           rate_hz
                          ``rate_hz (ref_dn / I)**light_exponent`` per pixel (``I``
                          floored at ``min_dn``): more in the dark; each one resets the
                          reference to the present log intensity
``bandwidth``             first-order low-pass of log intensity before the comparator;   cutoff_hz
                          cutoff ``cutoff_hz * (I + dark) / ref_dn`` (photocurrent-
                          limited: slower in low light)
``threshold_noise``       both thresholds re-drawn at every event as                    sigma
                          ``th * max(0.2, 1 + sigma * N(0, 1))`` (per event, not fixed
                          pattern; ``sigma`` is a fraction of the pixel's threshold)
``hot_pixels``            a ``fraction`` of pixels fire Poisson events at ``rate_hz``    rate_hz
                          regardless of light (ON with probability ``on_fraction``)
``log_offset``            the sensor sees ``log(I + dark_dn)`` instead of the nominal    dark_dn
                          ``log(I + SimConfig.log_offset)``; ``dark_dn`` in frame DN
``timestamp_jitter``      Gaussian timestamp noise ``sigma_us``, then quantisation to    sigma_us
                          multiples of ``quantum_us`` (events re-sorted)
``threshold_light``       contrast thresholds that grow in the dark:                    exponent
                          ``th(I) = th * ((I + dark) / ref_dn)**(-exponent)`` (both
                          polarities; ``dark`` the log offset the sensor sees): events
                          fire when the integral of ``dL / th(I)`` crosses one threshold
``row_noise``             correlated bursts along a readout line (``axis`` row or       rate_hz
                          column): each line bursts at ``rate_hz``, a ``fraction`` of
                          its pixels firing (ON or OFF) within ``spread_us``
``aps_fpn``               APS frames only: a constant dark offset ``o[y, x]`` (DN) per   sigma_dn
                          pixel added to the frame value (dark signal non-uniformity,
                          spread ``sigma_dn``, mean ``mean_dn``); the DVS part of the
                          pixel does not see it. A given ``offset_dn`` map, else drawn
                          from ``seed``
``exposure``              APS frames only: a frame averages the intensity over           lag_us
                          ``exposure_us``, its exposure's centre ``lag_us`` after the
                          frame's timestamp (``exposure_us / 2``: stamped at the start
                          of exposure, dv-processing; 0: at its middle, libcaer)
========================  =========================================================  ==========

APS frames (exposure, motion blur, read noise, 8-bit quantisation) are described by
:class:`ApsConfig`. ``aps_fpn`` and ``exposure`` act on them only (:meth:`ApsConfig.
with_effects` puts them into the frame model); in the gap workflow they say how the measured
frames that drive the simulation must be corrected (:func:`evcal.gap.frames.model_frames`).

Intensities ``I`` are in frame units (DN, 0..255 is the 8-bit range); rates in events per
second per pixel (Hz); times in microseconds.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from functools import lru_cache
from typing import Any, ClassVar

import numpy as np

from ..errors import ConfigError
from .kernel import step_events
from .labels import LABEL_HOT_PIXEL as LABEL_HOT_PIXEL
from .labels import LABEL_LEAK as LABEL_LEAK
from .labels import LABEL_LEGEND as LABEL_LEGEND
from .labels import LABEL_ROW_NOISE as LABEL_ROW_NOISE
from .labels import LABEL_SHOT_NOISE as LABEL_SHOT_NOISE
from .labels import LABEL_SIGNAL as LABEL_SIGNAL


class EffectError(ConfigError):
    """An effect with out-of-range parameters or an unknown name."""


def _check(name: str, ok: bool, what: str, value: Any) -> None:
    if not ok:
        raise EffectError(f"{name}: {what} (got {value!r})")


@dataclass(frozen=True, kw_only=True)
class Effect:
    """Base of the effect parameter objects (frozen, keyword-only, validated)."""

    name: ClassVar[str] = ""
    primary: ClassVar[str] = ""  # the parameter the gap workflow's tolerance refers to
    n_fitted: ClassVar[int] = 1  # parameters the gap workflow fits (complexity penalty)

    def parameters(self) -> dict[str, Any]:
        return asdict(self)

    def with_params(self, **changes: Any) -> Effect:
        values = self.parameters()
        values.update(changes)
        return type(self)(**values)

    def on_rows(self, rows: slice) -> Effect:
        """The effect on the sensor rows ``rows`` only (a band simulated on its own): its
        per-pixel maps of the events' side cut to them. Effects without one, and those
        acting on the frames before they are cut, are the same on any rows."""
        return self


@dataclass(frozen=True, kw_only=True)
class Refractory(Effect):
    name: ClassVar[str] = "refractory"
    primary: ClassVar[str] = "period_us"
    period_us: float = 1000.0
    mode: str = "drop"

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.period_us) and self.period_us >= 0,
               "period_us must be finite and >= 0", self.period_us)
        _check(self.name, self.mode in ("drop", "delay"), "mode must be 'drop' or 'delay'",
               self.mode)


@dataclass(frozen=True, kw_only=True)
class Leak(Effect):
    name: ClassVar[str] = "leak"
    primary: ClassVar[str] = "rate_hz"
    rate_hz: float = 0.5
    spread_log: float = 0.5
    light_exponent: float = 0.0
    ref_dn: float = 128.0

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.rate_hz) and self.rate_hz >= 0,
               "rate_hz must be finite and >= 0", self.rate_hz)
        _check(self.name, 0 <= self.spread_log <= 3, "spread_log must be in [0, 3]",
               self.spread_log)
        _check(self.name, -2 <= self.light_exponent <= 2, "light_exponent must be in [-2, 2]",
               self.light_exponent)
        _check(self.name, self.ref_dn > 0, "ref_dn must be > 0", self.ref_dn)

    def pixel_rates_hz(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Per-pixel leak rates: log-normal with mean ``rate_hz`` (Hz)."""
        s = float(self.spread_log)
        return self.rate_hz * np.exp(rng.normal(-0.5 * s * s, s, n))


@dataclass(frozen=True, kw_only=True)
class ShotNoise(Effect):
    name: ClassVar[str] = "shot_noise"
    primary: ClassVar[str] = "rate_hz"
    n_fitted: ClassVar[int] = 2
    rate_hz: float = 1.0
    ref_dn: float = 16.0
    # rate ~ (ref / I)**light_exponent: 1 is photon shot noise's 1/I; sensors and simulators
    # differ (v2e's falls only 4x from black to white: about 0.6)
    light_exponent: float = 1.0
    min_dn: float = 1.6  # the law's intensity floor (DN): the rate stops growing below it

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.rate_hz) and self.rate_hz >= 0,
               "rate_hz must be finite and >= 0", self.rate_hz)
        _check(self.name, self.ref_dn > 0, "ref_dn must be > 0", self.ref_dn)
        _check(self.name, 0 <= self.light_exponent <= 2, "light_exponent must be in [0, 2]",
               self.light_exponent)
        _check(self.name, np.isfinite(self.min_dn) and self.min_dn > 0,
               "min_dn must be finite and > 0", self.min_dn)

    def rate_at(self, intensity_dn: np.ndarray) -> np.ndarray:
        """Noise-event rate (Hz, ON and OFF together) at intensity ``I`` (DN)."""
        i = np.maximum(np.asarray(intensity_dn, np.float64), self.min_dn)
        return np.asarray(self.rate_hz * (self.ref_dn / i) ** self.light_exponent)

    def kernel_law(self) -> tuple[float, float, float]:
        """``(rate, ref, exponent)`` of the same law with ``ref = 10 min_dn`` (the simulator
        kernel floors the intensity at a tenth of its reference)."""
        ref = 10.0 * float(self.min_dn)
        rate = float(self.rate_hz) * (float(self.ref_dn) / ref) ** float(self.light_exponent)
        return rate, ref, float(self.light_exponent)


@dataclass(frozen=True, kw_only=True)
class Bandwidth(Effect):
    name: ClassVar[str] = "bandwidth"
    primary: ClassVar[str] = "cutoff_hz"
    cutoff_hz: float = 100.0
    ref_dn: float = 128.0
    min_cutoff_hz: float = 0.5

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.cutoff_hz) and self.cutoff_hz > 0,
               "cutoff_hz must be finite and > 0", self.cutoff_hz)
        _check(self.name, self.ref_dn > 0, "ref_dn must be > 0", self.ref_dn)
        _check(self.name, self.min_cutoff_hz > 0, "min_cutoff_hz must be > 0",
               self.min_cutoff_hz)


@dataclass(frozen=True, kw_only=True)
class ThresholdNoise(Effect):
    name: ClassVar[str] = "threshold_noise"
    primary: ClassVar[str] = "sigma"
    sigma: float = 0.1

    def __post_init__(self) -> None:
        _check(self.name, 0 <= self.sigma <= 1, "sigma (a fraction of the threshold) must be "
               "in [0, 1]", self.sigma)


@dataclass(frozen=True, kw_only=True)
class HotPixels(Effect):
    name: ClassVar[str] = "hot_pixels"
    primary: ClassVar[str] = "rate_hz"
    n_fitted: ClassVar[int] = 2
    fraction: float = 0.002
    rate_hz: float = 50.0
    on_fraction: float = 0.5

    def __post_init__(self) -> None:
        _check(self.name, 0 <= self.fraction <= 1, "fraction must be in [0, 1]", self.fraction)
        _check(self.name, np.isfinite(self.rate_hz) and self.rate_hz >= 0,
               "rate_hz must be finite and >= 0", self.rate_hz)
        _check(self.name, 0 <= self.on_fraction <= 1, "on_fraction must be in [0, 1]",
               self.on_fraction)


@dataclass(frozen=True, kw_only=True)
class LogOffset(Effect):
    name: ClassVar[str] = "log_offset"
    primary: ClassVar[str] = "dark_dn"
    dark_dn: float = 20.0

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.dark_dn) and self.dark_dn >= 0,
               "dark_dn must be finite and >= 0", self.dark_dn)


@dataclass(frozen=True, kw_only=True)
class TimestampJitter(Effect):
    name: ClassVar[str] = "timestamp_jitter"
    primary: ClassVar[str] = "sigma_us"
    sigma_us: float = 100.0
    quantum_us: int = 1

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.sigma_us) and self.sigma_us >= 0,
               "sigma_us must be finite and >= 0", self.sigma_us)
        _check(self.name, int(self.quantum_us) >= 1 and int(self.quantum_us) == self.quantum_us,
               "quantum_us must be an integer >= 1", self.quantum_us)


@dataclass(frozen=True, kw_only=True)
class TimestampQuantisation(Effect):
    """Events decided per simulation step rather than at the crossing (a property of
    frame-driven simulators, not of a sensor): steps of ``step_us`` from the recording's
    first time; ``scheme="spread"``: a pixel with ``n`` pending crossings at a step's end
    fires at the first ``n`` of ``N`` slots ``start + step_us i / N`` (i = 1..N), ``N`` the
    most any pixel has pending in that step, and a dead time (``refractory``) is applied to
    those stamps (v2e's scheme, v2ecore/emulator.py ``generate_events``; see
    :func:`quantise_events`); ``scheme="end"``: every event of a step gets its end."""

    name: ClassVar[str] = "timestamp_quantisation"
    primary: ClassVar[str] = "step_us"
    step_us: float = 1000.0
    scheme: str = "spread"
    phase_us: float = 0.0  # step ends at t0 + phase_us + k step_us


    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.step_us) and self.step_us >= 1,
               "step_us must be finite and >= 1", self.step_us)
        _check(self.name, self.scheme in ("spread", "end"), "scheme must be 'spread' or 'end'",
               self.scheme)
        _check(self.name, np.isfinite(self.phase_us), "phase_us must be finite", self.phase_us)


@dataclass(frozen=True, kw_only=True)
class ThresholdLight(Effect):
    """Contrast thresholds that depend on the present photocurrent:
    ``th(I) = th * ((I + dark) / ref_dn)**(-exponent)`` for both polarities (``th`` the
    pixel's threshold at ``ref_dn``, ``dark`` the log offset the sensor sees).

    Events fire when the integral of ``dL / th(I)`` since the last event crosses one
    threshold, which is a fixed-threshold comparator on the response
    ``G(x) = ln(ref_dn) + ((x / ref_dn)**exponent - 1) / exponent`` of ``x = I + dark``
    (``ln x`` at exponent 0): the simulator runs its comparator on ``G``, while shot noise,
    leak and the bandwidth keep seeing the true intensity (their laws are in photocurrent).
    Scale-free where ``log_offset`` is not: the threshold ratio between two intensities
    depends on their ratio only, whereas a dark level desensitises only pixels near it.

    ``pixel_ref_dn`` (``[H, W]``, in units of ``I + dark``, not reported) is, when given, the
    reference of each pixel in place of ``ref_dn``: the intensity at which the threshold map
    holds. A map fitted with intensity-blind OffEI gives each pixel its threshold at the
    light it saw (the gap workflow's base model), so the fitter sets it to that light;
    otherwise the law would be applied twice, once by the fit and once by the simulator."""

    name: ClassVar[str] = "threshold_light"
    primary: ClassVar[str] = "exponent"
    exponent: float = 0.2
    ref_dn: float = 128.0
    pixel_ref_dn: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.exponent) and 0 <= self.exponent <= 1,
               "exponent must be in [0, 1]", self.exponent)
        _check(self.name, np.isfinite(self.ref_dn) and self.ref_dn > 0, "ref_dn must be > 0",
               self.ref_dn)
        if self.pixel_ref_dn is not None:
            m = np.asarray(self.pixel_ref_dn)
            _check(self.name, m.ndim == 2 and bool(np.isfinite(m).all()) and bool(
                (m > 0).all()), "pixel_ref_dn must be a finite positive 2-D map", m.shape)

    def parameters(self) -> dict[str, Any]:
        return {"exponent": self.exponent, "ref_dn": self.ref_dn}

    def with_params(self, **changes: Any) -> Effect:
        values: dict[str, Any] = {**self.parameters(), "pixel_ref_dn": self.pixel_ref_dn,
                                  **changes}
        return type(self)(**values)

    def on_rows(self, rows: slice) -> Effect:
        if self.pixel_ref_dn is None:
            return self
        return replace(self, pixel_ref_dn=np.asarray(self.pixel_ref_dn)[rows])

    def references(self, shape: tuple[int, int]) -> np.ndarray:
        """Per-pixel reference (``[H, W]`` float64, units of ``I + dark``)."""
        if self.pixel_ref_dn is None:
            return np.full(shape, float(self.ref_dn))
        m = np.asarray(self.pixel_ref_dn, np.float64)
        if m.shape != tuple(shape):
            raise EffectError(f"{self.name}: pixel_ref_dn has shape {m.shape}, the sensor "
                              f"{tuple(shape)}")
        return m

    def threshold_factor(self, intensity_dn: np.ndarray, dark_dn: float,
                         ref: np.ndarray | float | None = None) -> np.ndarray:
        """``th(I) / th`` at intensity ``I`` (DN) with the sensor's dark level ``dark_dn``
        (reference ``ref``, default ``ref_dn``)."""
        r = self.ref_dn if ref is None else ref
        x = np.maximum(np.asarray(intensity_dn, np.float64) + dark_dn, 1e-3)
        return np.asarray((x / r) ** (-self.exponent))

    def response(self, intensity_dn: np.ndarray, dark_dn: float,
                 ref: np.ndarray | float | None = None) -> np.ndarray:
        """``G(I + dark)``: the log intensity a fixed-threshold comparator must see to fire
        as the sensor does (the integral of ``d ln x / th-factor``; reference ``ref``,
        default ``ref_dn``)."""
        r = np.asarray(self.ref_dn if ref is None else ref, np.float64)
        x = np.maximum(np.asarray(intensity_dn, np.float64) + dark_dn, 1e-3)
        if self.exponent == 0:
            return np.log(x)
        e = float(self.exponent)
        return np.asarray(np.log(r) + ((x / r) ** e - 1.0) / e)


@dataclass(frozen=True, kw_only=True)
class RowNoise(Effect):
    """Bursts of events along one readout line: every row (``axis="row"``) or column
    (``"column"``) bursts as a Poisson process of ``rate_hz``; in a burst each pixel of the
    line fires with probability ``fraction``, ON with probability ``on_fraction`` (a glitch
    on a shared line is a short pulse that goes both ways; which threshold a pixel crosses
    depends on where its own reference sits), at the burst time plus a half-normal delay of
    ``spread_us`` (the arbiter serialises the burst). Independent of light and of the
    pixel's state otherwise."""

    name: ClassVar[str] = "row_noise"
    primary: ClassVar[str] = "rate_hz"
    n_fitted: ClassVar[int] = 2
    rate_hz: float = 0.5
    fraction: float = 0.3
    axis: str = "row"
    spread_us: float = 5.0
    on_fraction: float = 0.5

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.rate_hz) and self.rate_hz >= 0,
               "rate_hz must be finite and >= 0", self.rate_hz)
        _check(self.name, 0 < self.fraction <= 1, "fraction must be in (0, 1]", self.fraction)
        _check(self.name, self.axis in ("row", "column"), "axis must be 'row' or 'column'",
               self.axis)
        _check(self.name, np.isfinite(self.spread_us) and self.spread_us >= 0,
               "spread_us must be finite and >= 0", self.spread_us)
        _check(self.name, 0 <= self.on_fraction <= 1, "on_fraction must be in [0, 1]",
               self.on_fraction)

    def events(self, shape: tuple[int, int], t_lo_us: int, t_hi_us: int,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t_us, pixel, polarity)`` of the bursts in ``[t_lo_us, t_hi_us]`` on a sensor of
        ``shape`` (H, W), pixel index ``y W + x``, sorted by time."""
        h, w = shape
        n_lines, length = (h, w) if self.axis == "row" else (w, h)
        dur_s = max(t_hi_us - t_lo_us, 0) * 1e-6
        n_b = rng.poisson(self.rate_hz * dur_s, n_lines)
        line = np.repeat(np.arange(n_lines), n_b)
        t_b = rng.integers(t_lo_us, t_hi_us + 1, line.size)
        # one row of member draws per burst: bursts x line length, small (rate x time x lines)
        member = rng.random((line.size, length)) < self.fraction
        b_idx, pos = np.nonzero(member)
        delay = np.rint(np.abs(rng.normal(0.0, self.spread_us, b_idx.size))).astype(np.int64)
        pol = np.where(rng.random(b_idx.size) < self.on_fraction, 1, -1).astype(np.int8)
        t = np.minimum(t_b[b_idx] + delay, t_hi_us)
        ln = line[b_idx]
        pix = (ln * w + pos) if self.axis == "row" else (pos * w + ln)
        order = np.argsort(t, kind="stable")
        return t[order].astype(np.int64), pix[order].astype(np.int32), pol[order]


@dataclass(frozen=True, kw_only=True)
class ApsFpn(Effect):
    """Dark signal non-uniformity of the APS frames (fixed-pattern offset): each pixel's frame
    value carries its own constant dark level ``o[y, x]`` (DN) on top of the light; the DVS
    part of the pixel (its own photoreceptor and comparators) does not see it.

    ``offset_dn`` is the per-pixel map when it is known (the gap workflow's estimate,
    :func:`evcal.gap.frames.fit_aps_fpn`); otherwise :meth:`offsets_dn` draws it as
    ``N(mean_dn, sigma_dn)`` from ``seed``. The map is not one of the :meth:`parameters`
    (reports stay small); :meth:`with_params` keeps it, scaled about its mean by the ratio of
    a new ``sigma_dn`` to the old.
    """

    name: ClassVar[str] = "aps_fpn"
    primary: ClassVar[str] = "sigma_dn"
    sigma_dn: float = 3.0
    mean_dn: float = 0.0
    seed: int = 0
    offset_dn: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.sigma_dn) and self.sigma_dn >= 0,
               "sigma_dn must be finite and >= 0", self.sigma_dn)
        _check(self.name, np.isfinite(self.mean_dn), "mean_dn must be finite", self.mean_dn)
        _check(self.name, int(self.seed) == self.seed and self.seed >= 0,
               "seed must be an integer >= 0", self.seed)
        if self.offset_dn is not None:
            m = np.asarray(self.offset_dn)
            _check(self.name, m.ndim == 2 and bool(np.isfinite(m).all()),
                   "offset_dn must be a finite 2-D map", m.shape)

    def parameters(self) -> dict[str, Any]:
        return {"sigma_dn": self.sigma_dn, "mean_dn": self.mean_dn, "seed": self.seed}

    def with_params(self, **changes: Any) -> Effect:
        # a new sigma_dn scales the map about its mean: the map is what the gap workflow
        # simulates, so its bias correction and search of sigma_dn must move the map (a
        # parameter that moved nothing would drift freely under the bias correction)
        values: dict[str, Any] = {**self.parameters(), "offset_dn": self.offset_dn, **changes}
        m = values["offset_dn"]
        if m is not None and "offset_dn" not in changes and self.sigma_dn > 0:
            m = np.asarray(m, np.float64)
            mu = float(m.mean())
            values["offset_dn"] = mu + (m - mu) * (float(values["sigma_dn"]) / self.sigma_dn)
        return type(self)(**values)

    def offsets_dn(self, shape: tuple[int, int]) -> np.ndarray:
        """The per-pixel dark offsets (DN, float64 ``[H, W]``): the map when given (its
        shape must be ``shape``), else drawn (deterministic for ``seed`` and ``shape``)."""
        if self.offset_dn is not None:
            m = np.asarray(self.offset_dn, np.float64)
            if m.shape != tuple(shape):
                raise EffectError(f"{self.name}: offset_dn has shape {m.shape}, frames "
                                  f"{tuple(shape)}")
            return m
        drawn: np.ndarray = _dark_offsets(float(self.sigma_dn), float(self.mean_dn),
                                          int(self.seed), (int(shape[0]), int(shape[1])))
        out: np.ndarray = drawn.copy()  # the cached array must not be changed by a caller
        return out


@lru_cache(maxsize=8)
def _dark_offsets(sigma_dn: float, mean_dn: float, seed: int, shape: tuple[int, int]
                  ) -> np.ndarray:
    # its own generator (not the simulator's stream): adding DSNU changes no other draw, and
    # every frame of a recording gets the same pattern
    rng = np.random.default_rng([seed, 0xD5A0])
    out: np.ndarray = mean_dn + sigma_dn * rng.standard_normal(shape)
    return out


@dataclass(frozen=True, kw_only=True)
class Exposure(Effect):
    """Exposure integration and timestamp placement of the APS frames: a frame is the mean of
    the intensity over ``exposure_us``, centred ``lag_us`` after the frame's timestamp
    (``exposure_us / 2`` when the stamp is the start of exposure, as dv-processing's
    ``dv::Frame::timestamp``; 0 at its middle, as libcaer's frame timestamp; ``-exposure_us
    / 2`` at its end). Events are instants; only the frames are affected."""

    name: ClassVar[str] = "exposure"
    primary: ClassVar[str] = "lag_us"
    lag_us: float = 2500.0
    exposure_us: float = 5000.0

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.lag_us), "lag_us must be finite", self.lag_us)
        _check(self.name, np.isfinite(self.exposure_us) and self.exposure_us >= 0,
               "exposure_us must be finite and >= 0", self.exposure_us)


def quantise_events(t_us: np.ndarray, pix: np.ndarray, pol: np.ndarray, lab: np.ndarray,
                    q: TimestampQuantisation, t0_us: int, *, n_pix: int,
                    t_end_us: float | None = None, refractory: Refractory | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The events ``(t_us, pix, pol, lab)`` (sorted by time; crossings of pixels without a
    dead time) as a frame-driven simulator under ``q`` emits them, sorted by time (steps end
    at ``t0_us + q.phase_us + k q.step_us``, up to ``t_end_us``, default the last event).

    ``scheme="spread"`` (v2e, v2ecore/emulator.py ``generate_events``): per step, each
    pixel's signed count of pending crossings, slots at ``start + i step / N`` (``N`` the
    largest count of any pixel), a pixel's events at its first slots, and ``refractory``
    applied to these stamps (:func:`evcal.sim.kernel.step_events`): blocked crossings stay
    pending in ``delay`` mode (v2e's), are lost in ``drop`` mode. ``scheme="end"``: every
    event at its step's end (a dead time, if any, must have been applied to the crossings).
    """
    t = np.asarray(t_us, np.int64)
    if t.size == 0:
        return t.copy(), np.asarray(pix).copy(), np.asarray(pol).copy(), np.asarray(lab).copy()
    step = float(q.step_us)
    origin = t0_us + float(q.phase_us) % step - step  # a grid point at or before t0
    if q.scheme == "end":
        # a step is (start, end]: an event exactly at a step's end belongs to that step
        k = np.maximum(np.ceil((t - origin) / step).astype(np.int64) - 1, 0)
        ends: np.ndarray = np.rint(origin + (k + 1) * step).astype(np.int64)
        return ends, np.asarray(pix).copy(), np.asarray(pol).copy(), np.asarray(lab).copy()
    refr_us = float(refractory.period_us) if refractory is not None else 0.0
    drop = bool(refractory is not None and refractory.mode == "drop")
    end = float(t[-1]) if t_end_us is None else float(t_end_us)
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] = step_events(
        t, np.ascontiguousarray(pix, np.int32), np.ascontiguousarray(pol, np.int8),
        np.ascontiguousarray(lab, np.uint8), int(n_pix), origin, step, end, refr_us, drop)
    return out


APS_TIMESTAMPS = ("start", "middle", "end")


@dataclass(frozen=True, kw_only=True)
class ApsConfig:
    """APS frame model: exposure (motion blur), timestamp placement, dark offsets, read noise,
    8-bit quantisation.

    A frame stamped ``t`` is the mean of the intensity over ``[c - exposure/2, c +
    exposure/2]`` (``blur_samples`` renders; one render when ``exposure_us`` is 0), ``c = t +``
    :attr:`centre_lag_us`: the stamp marks the ``timestamp`` (start, middle or end) of the
    exposure, or the centre lies ``lag_us`` after it when that is given. Then each pixel's
    dark offset is added (DSNU: ``N(dsnu_mean_dn, dsnu_sigma_dn)`` per pixel, drawn once from
    ``dsnu_seed``, the same in every frame), Gaussian read noise of ``read_noise_dn`` (DN),
    and the value is rounded and clipped to 0..255 when ``quantise``.
    """

    exposure_us: int = 0
    read_noise_dn: float = 0.0
    quantise: bool = True
    blur_samples: int = 5
    timestamp: str = "middle"
    lag_us: float | None = None
    dsnu_sigma_dn: float = 0.0
    dsnu_mean_dn: float = 0.0
    dsnu_seed: int = 0

    def __post_init__(self) -> None:
        _check("aps", int(self.exposure_us) >= 0, "exposure_us must be >= 0", self.exposure_us)
        _check("aps", self.read_noise_dn >= 0, "read_noise_dn must be >= 0",
               self.read_noise_dn)
        _check("aps", int(self.blur_samples) >= 1, "blur_samples must be >= 1",
               self.blur_samples)
        _check("aps", self.timestamp in APS_TIMESTAMPS,
               f"timestamp must be one of {APS_TIMESTAMPS}", self.timestamp)
        _check("aps", self.lag_us is None or bool(np.isfinite(self.lag_us)),
               "lag_us must be finite or None", self.lag_us)
        _check("aps", np.isfinite(self.dsnu_sigma_dn) and self.dsnu_sigma_dn >= 0,
               "dsnu_sigma_dn must be finite and >= 0", self.dsnu_sigma_dn)
        _check("aps", bool(np.isfinite(self.dsnu_mean_dn)), "dsnu_mean_dn must be finite",
               self.dsnu_mean_dn)

    @property
    def centre_lag_us(self) -> float:
        """Where the exposure's centre lies after the frame's timestamp (us)."""
        if self.lag_us is not None:
            return float(self.lag_us)
        half = 0.5 * float(self.exposure_us)
        return {"start": half, "middle": 0.0, "end": -half}[self.timestamp]

    def dark_offsets_dn(self, shape: tuple[int, int]) -> np.ndarray | None:
        """Per-pixel dark offsets (DN, ``[H, W]``), ``None`` without DSNU."""
        if self.dsnu_sigma_dn == 0 and self.dsnu_mean_dn == 0:
            return None
        return _dark_offsets(float(self.dsnu_sigma_dn), float(self.dsnu_mean_dn),
                             int(self.dsnu_seed), (int(shape[0]), int(shape[1])))

    def with_effects(self, effects: Mapping[str, Effect]) -> ApsConfig:
        """This frame model with the frame-side effects of ``effects`` (``aps_fpn``:
        the DSNU; ``exposure``: exposure time and centre); unchanged without them."""
        out = self
        fpn = effects.get(ApsFpn.name)
        if isinstance(fpn, ApsFpn):
            out = replace(out, dsnu_sigma_dn=float(fpn.sigma_dn),
                          dsnu_mean_dn=float(fpn.mean_dn), dsnu_seed=int(fpn.seed))
        exp = effects.get(Exposure.name)
        if isinstance(exp, Exposure):
            out = replace(out, exposure_us=int(round(exp.exposure_us)),
                          lag_us=float(exp.lag_us))
        return out


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (Refractory, Leak, ShotNoise, Bandwidth, ThresholdNoise, HotPixels, LogOffset,
                TimestampJitter, TimestampQuantisation, ThresholdLight, RowNoise, ApsFpn,
                Exposure)
}
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECTS)


def make_effect(name: str, **params: Any) -> Effect:
    """The effect called ``name`` with ``params`` (others at their defaults)."""
    try:
        cls = EFFECTS[name]
    except KeyError:
        raise EffectError(f"unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}") from None
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise EffectError(f"{name}: unknown parameter(s) {unknown}; known: {sorted(known)}")
    return cls(**params)


def effect_set(effects: Iterable[Effect] | Mapping[str, Effect] | None) -> dict[str, Effect]:
    """Effects by name; at most one of each kind."""
    if effects is None:
        return {}
    items = list(effects.values()) if isinstance(effects, Mapping) else list(effects)
    out: dict[str, Effect] = {}
    for e in items:
        if not isinstance(e, Effect) or not e.name:
            raise EffectError(f"{e!r} is not an effect of {EFFECT_NAMES}")
        if e.name in out:
            raise EffectError(f"effect {e.name!r} given twice")
        out[e.name] = e
    return out


def describe(effects: Iterable[Effect] | Mapping[str, Effect] | None
             ) -> dict[str, dict[str, Any]]:
    """``{name: parameters}`` (JSON-ready)."""
    return {name: e.parameters() for name, e in effect_set(effects).items()}
