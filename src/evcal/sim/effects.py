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
========================  =========================================================  ==========

APS frames (exposure, motion blur, read noise, 8-bit quantisation) are described by
:class:`ApsConfig`; they are the simulator's frame model, not a candidate of the gap workflow
(which takes the measured frames as its input).

Intensities ``I`` are in frame units (DN, 0..255 is the 8-bit range); rates in events per
second per pixel (Hz); times in microseconds.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any, ClassVar

import numpy as np

from ..errors import ConfigError


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
    from .kernel import step_events  # noqa: PLC0415 - the kernel imports this module

    refr_us = float(refractory.period_us) if refractory is not None else 0.0
    drop = bool(refractory is not None and refractory.mode == "drop")
    end = float(t[-1]) if t_end_us is None else float(t_end_us)
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] = step_events(
        t, np.ascontiguousarray(pix, np.int32), np.ascontiguousarray(pol, np.int8),
        np.ascontiguousarray(lab, np.uint8), int(n_pix), origin, step, end, refr_us, drop)
    return out


@dataclass(frozen=True, kw_only=True)
class ApsConfig:
    """APS frame model: exposure (motion blur), read noise, 8-bit quantisation.

    A frame at time ``t`` is the mean of the intensity over ``[t - exposure/2, t +
    exposure/2]`` (``blur_samples`` renders; one render when ``exposure_us`` is 0), plus
    Gaussian read noise of ``read_noise_dn`` (DN), rounded and clipped to 0..255 when
    ``quantise``. Frame times are the middle of the exposure.
    """

    exposure_us: int = 0
    read_noise_dn: float = 0.0
    quantise: bool = True
    blur_samples: int = 5

    def __post_init__(self) -> None:
        _check("aps", int(self.exposure_us) >= 0, "exposure_us must be >= 0", self.exposure_us)
        _check("aps", self.read_noise_dn >= 0, "read_noise_dn must be >= 0",
               self.read_noise_dn)
        _check("aps", int(self.blur_samples) >= 1, "blur_samples must be >= 1",
               self.blur_samples)


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (Refractory, Leak, ShotNoise, Bandwidth, ThresholdNoise, HotPixels, LogOffset,
                TimestampJitter, TimestampQuantisation)
}
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECTS)

# Labels of simulated events (``truth["labels"]``, uint8, one per event).
LABEL_SIGNAL = 0
LABEL_LEAK = 1
LABEL_SHOT_NOISE = 2
LABEL_HOT_PIXEL = 3
LABEL_LEGEND = {LABEL_SIGNAL: "signal", LABEL_LEAK: "leak", LABEL_SHOT_NOISE: "shot_noise",
                LABEL_HOT_PIXEL: "hot_pixels"}


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
