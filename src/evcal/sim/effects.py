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
``flicker``               the scene's light (not the sensor) multiplied by               depth
                          ``1 + depth sin(2 pi freq_hz t + phase_rad)`` (``t`` in
                          seconds of the recording's time: mains lighting flickers at
                          twice the mains frequency); events and frames both see it
``start_reset``           every pixel's reference set to its log intensity at the       (none)
                          recording's first instant (a simulator that starts from its
                          first frame, v2e), not anywhere within a threshold of it
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

How an effect acts on a simulation
----------------------------------
Each effect is the one place of its parameters and of what it does: :class:`Effect` has one
hook per stage of :func:`~evcal.sim.nonideal.simulate`, each a no-op there, and an effect
overrides those of the stages it acts at (:meth:`Effect.hooks` lists them). The simulator
runs the stages in this sequence, and in each asks every effect in the fixed order of
:attr:`Effect.order` (ties by name; :func:`simulation_order`), never by its class:

0. ``on_light(t_s)``: the factor the scene's light is multiplied by at the output times
   ``t_s`` (seconds), applied to the source the events and the frames are made from;
1. ``on_aps(aps)``: the APS frame model (:meth:`ApsConfig.with_effects`);
2. ``log_offset(nominal)``: the dark level of the log response ``log(I + dark)``
   (:func:`~evcal.sim.nonideal.effective_log_offset`);
3. ``applies_dead_time()``, asked of every effect first (``True``: its stamps apply the
   pixels' dead time, so the kernel leaves it out: :attr:`SimContext.stamps_apply_dead_time`),
   then ``kernel_setup(kp, ctx)``: the kernel's per-pixel parameters (:class:`KernelParams`:
   thresholds, dead time, leak, shot noise, bandwidth, the comparator's response, from which
   the initial reference is set);
4. the kernel runs; ``after_kernel(events, ctx)``: the events (:class:`SimEvents`, times as
   the kernel's) with the effect's additions, each merged with its label;
5. ``t_origin_us`` is added; ``on_timestamps(events, ctx)``: the events re-stamped (sorted by
   time again).

Effects talk to each other through the :class:`SimContext` only (e.g. ``refractory`` leaves
its dead time in :attr:`SimContext.stamp_dead_time` when the stamps apply it, and
``timestamp_quantisation`` applies it there). Randomness comes from the context's generators,
one per stage (:attr:`~SimContext.rng_kernel`, :attr:`~SimContext.rng_maps`,
:attr:`~SimContext.rng_events`, :attr:`~SimContext.rng_timestamps`), drawn in the fixed order;
an effect added to a stage's stream moves the draws of the effects after it, so a new effect
takes a stream of its own from :meth:`SimContext.spawn_rng` (which moves none).

=========================  =====  ===========================================================
name                       order  hooks (what the fixed order keeps)
=========================  =====  ===========================================================
``log_offset``             10     ``log_offset``
``threshold_light``        20     ``kernel_setup`` (the comparator's response)
``refractory``             30     ``kernel_setup`` (the dead time, or its note for the stamps)
``threshold_noise``        40     ``kernel_setup`` (``rng_kernel``: before ``shot_noise``)
``shot_noise``             50     ``kernel_setup`` (``rng_kernel``)
``leak``                   60     ``kernel_setup`` (``rng_maps``)
``bandwidth``              70     ``kernel_setup``
``hot_pixels``             80     ``after_kernel`` (``rng_events``; merged first)
``row_noise``              90     ``after_kernel`` (a spawned stream; merged second)
``timestamp_quantisation`` 100    ``applies_dead_time``, ``on_timestamps`` (before jitter)
``timestamp_jitter``       110    ``on_timestamps`` (``rng_timestamps``)
``aps_fpn``                120    ``on_aps``
``exposure``               130    ``on_aps``
``flicker``                140    ``on_light``
``start_reset``            150    ``kernel_setup`` (a flag: the initial references)
=========================  =====  ===========================================================

To add an effect: subclass :class:`Effect` as a frozen, keyword-only dataclass with a unique
``name`` (and ``primary``, ``n_fitted`` for the gap workflow), its parameters as fields
validated in ``__post_init__``, an ``order`` (default 1000: after all of the above), and
override the hooks of the stages it acts at; add it to the registry :data:`EFFECTS` (below)
so that :func:`make_effect` and ``evcal gap`` know it by name. :func:`simulate` needs no
change: an effect given to it works unregistered too.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from functools import lru_cache
from typing import Any, ClassVar, NamedTuple

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
    order: ClassVar[int] = 1000  # its place in the simulation's fixed order (module doc)

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

    # the simulation hooks, one per stage (the module doc gives the stages and their order);
    # each does nothing here, an effect overrides those of the stages it acts at

    def on_light(self, t_s: np.ndarray) -> np.ndarray | None:
        """The factor the scene's light is multiplied by at the times ``t_s`` (seconds of
        output time), or ``None``: the light as the source gives it."""
        return None

    def on_aps(self, aps: ApsConfig) -> ApsConfig:
        """The APS frame model with this effect (frames only)."""
        return aps

    def log_offset(self, nominal_dn: float) -> float:
        """The dark level (DN) of the log response ``log(I + dark)`` the sensor sees, given
        the one so far (the config's nominal offset, or an earlier effect's)."""
        return nominal_dn

    def applies_dead_time(self) -> bool:
        """Whether this effect's timestamps apply the pixels' dead time themselves (then the
        kernel leaves it out: :attr:`SimContext.stamps_apply_dead_time`)."""
        return False

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        """Set this effect's parameters of the per-pixel kernel in ``kp`` (in place)."""
        return None

    def after_kernel(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        """The kernel's events (times as the kernel's, sorted) with this effect's."""
        return events

    def on_timestamps(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        """The events (output times: ``t_origin_us`` added) as this effect stamps them,
        sorted by time."""
        return events

    @classmethod
    def hooks(cls) -> tuple[str, ...]:
        """The simulation hooks this effect overrides: the stages it acts at."""
        return tuple(h for h in HOOKS if getattr(cls, h) is not getattr(Effect, h))


HOOKS: tuple[str, ...] = ("on_light", "on_aps", "log_offset", "applies_dead_time", "kernel_setup",
                          "after_kernel", "on_timestamps")


def simulation_order(effects: Iterable[Effect]) -> list[Effect]:
    """``effects`` in the simulation's fixed order (:attr:`Effect.order`, then name)."""
    return sorted(effects, key=lambda e: (e.order, e.name))


class SimEvents(NamedTuple):
    """Events inside the simulator: times (us, int64), pixel indices ``y W + x`` (int32),
    polarities (int8), labels (uint8, :data:`LABEL_LEGEND`). No events: empty arrays."""

    t_us: np.ndarray
    pix: np.ndarray
    pol: np.ndarray
    lab: np.ndarray

    def take(self, index: np.ndarray) -> SimEvents:
        return SimEvents(self.t_us[index], self.pix[index], self.pol[index], self.lab[index])

    def sorted_by_time(self) -> SimEvents:
        """Sorted by time, stably (the order of events at one time is kept)."""
        return self.take(np.argsort(self.t_us, kind="stable"))

    def merged(self, added: tuple[np.ndarray, np.ndarray, np.ndarray], label: int
               ) -> SimEvents:
        """These events with the ``added`` ones (times, pixels, polarities) of one
        ``label``, sorted by time (stably: among equal times these come first, in their
        order)."""
        t = np.concatenate([self.t_us, added[0]])
        order = np.argsort(t, kind="stable")
        pix = np.concatenate([self.pix, added[1]])[order]
        pol = np.concatenate([self.pol, added[2]])[order]
        lab = np.concatenate([self.lab, np.full(added[0].size, label, np.uint8)])[order]
        return SimEvents(t[order], pix, pol, lab)


@dataclass(kw_only=True, eq=False)
class KernelParams:
    """The parameters of the per-pixel kernel (:func:`evcal.sim.kernel.run_steps`) that
    effects set in :meth:`Effect.kernel_setup`; mutable, one per run, at first an ideal pixel.
    Per-pixel arrays are flat (``y W + x``)."""

    th_on_nom: np.ndarray  # nominal thresholds c + b, c - b (log units)
    th_off_nom: np.ndarray
    th_on: np.ndarray  # the thresholds until a pixel's first event
    th_off: np.ndarray
    th_sigma: float = 0.0  # threshold noise, a fraction of the nominal threshold
    refr_us: float = 0.0  # dead time (0: none)
    refr_delay: bool = False  # crossings in the dead time delayed, not dropped
    leak_rate_hz: np.ndarray
    leak_exp: float = 0.0
    leak_ref_dn: float = 128.0
    shot_rate_hz: float = 0.0  # the kernel's law: rate (ref / I)**exp, I floored at ref / 10
    shot_ref_dn: float = 16.0
    shot_exp: float = 1.0
    shot_next_us: np.ndarray  # each pixel's first shot-noise candidate (inf: none)
    bw_cutoff_hz: float = 0.0  # bandwidth (0: none)
    bw_ref_dn: float = 128.0
    bw_min_cutoff_hz: float = 0.5
    response_exp: float = 0.0  # the comparator's response (0: log(I + dark); ThresholdLight)
    response_ref_dn: np.ndarray
    # every reference set to the comparator's input at the first sample (StartReset), in
    # place of a running sensor's anywhere within a threshold of it
    start_reset: bool = False

    @classmethod
    def ideal(cls, th_on_nom: np.ndarray, th_off_nom: np.ndarray) -> KernelParams:
        """An ideal pixel's parameters with the nominal thresholds ``th_on_nom``,
        ``th_off_nom`` (flat)."""
        n = th_on_nom.size
        return cls(th_on_nom=th_on_nom, th_off_nom=th_off_nom, th_on=th_on_nom.copy(),
                   th_off=th_off_nom.copy(), leak_rate_hz=np.zeros(n),
                   shot_next_us=np.full(n, np.inf), response_ref_dn=np.full(n, 128.0))

    def comparator_input(self, intensity_dn: np.ndarray, log_offset: float) -> np.ndarray:
        """The log intensity the kernel's comparator sees at ``intensity_dn`` (flat float64):
        ``log(I + dark)``, or the response of light-dependent thresholds
        (:meth:`ThresholdLight.response`)."""
        i = np.asarray(intensity_dn)
        if self.response_exp > 0:
            return light_response(i.ravel(), log_offset, self.response_exp,
                                  self.response_ref_dn)
        return np.log(i.astype(np.float64) + log_offset).ravel()


@dataclass(kw_only=True, eq=False)
class SimContext:
    """What one simulation run tells its effects, and what they leave for later stages
    (mutable). Times in us relative to the run (the kernel's), unless named output."""

    shape: tuple[int, int]  # (H, W)
    times_us: np.ndarray  # the internal sample times (int64)
    t_origin_us: int  # added to every output time
    log_offset: float  # the dark level the sensor sees (DN)
    rng_kernel: np.random.Generator  # the kernel's draws (after the per-pixel states)
    rng_maps: np.random.Generator  # per-pixel parameter maps
    rng_events: np.random.Generator  # events added after the kernel
    rng_timestamps: np.random.Generator  # timestamp noise
    root_rng: np.random.Generator  # the run's generator, for spawn_rng only
    # some effect's timestamps apply the dead time (Effect.applies_dead_time): the kernel
    # leaves it out, and the dead-time effect leaves itself in stamp_dead_time for them
    stamps_apply_dead_time: bool = False
    stamp_dead_time: Refractory | None = None
    # per-pixel truth (flat) an effect reports, e.g. "hot_pixels"
    pixel_truth: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_pix(self) -> int:
        return int(self.shape[0]) * int(self.shape[1])

    @property
    def t_lo_us(self) -> int:
        """The first sample time."""
        return int(self.times_us[0])

    @property
    def t_hi_us(self) -> int:
        """The last sample time."""
        return int(self.times_us[-1])

    @property
    def t_start_out_us(self) -> int:
        """The first sample time in output time (``t_origin_us`` added)."""
        return int(self.times_us[0]) + int(self.t_origin_us)

    def spawn_rng(self) -> np.random.Generator:
        """A new generator of its own, spawned from the run's (no other draw moves)."""
        (out,) = self.root_rng.spawn(1)
        return out


def light_response(intensity_dn: np.ndarray, dark_dn: float, exponent: float,
                   ref: np.ndarray | float) -> np.ndarray:
    """``G(I + dark)`` of light-dependent thresholds (:class:`ThresholdLight`) with
    ``exponent`` and reference ``ref`` (``ln x`` at exponent 0)."""
    r = np.asarray(ref, np.float64)
    x = np.maximum(np.asarray(intensity_dn, np.float64) + dark_dn, 1e-3)
    if exponent == 0:
        return np.log(x)
    e = float(exponent)
    return np.asarray(np.log(r) + ((x / r) ** e - 1.0) / e)


@dataclass(frozen=True, kw_only=True)
class Refractory(Effect):
    name: ClassVar[str] = "refractory"
    primary: ClassVar[str] = "period_us"
    order: ClassVar[int] = 30
    period_us: float = 1000.0
    mode: str = "drop"

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.period_us) and self.period_us >= 0,
               "period_us must be finite and >= 0", self.period_us)
        _check(self.name, self.mode in ("drop", "delay"), "mode must be 'drop' or 'delay'",
               self.mode)

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        kp.refr_delay = self.mode == "delay"
        if ctx.stamps_apply_dead_time:
            # a frame-driven simulator applies its dead time to the stamps of its steps: the
            # kernel's crossings come without one
            ctx.stamp_dead_time = self
        else:
            kp.refr_us = float(self.period_us)


@dataclass(frozen=True, kw_only=True)
class Leak(Effect):
    name: ClassVar[str] = "leak"
    primary: ClassVar[str] = "rate_hz"
    order: ClassVar[int] = 60
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

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        if self.rate_hz > 0:
            kp.leak_rate_hz = self.pixel_rates_hz(ctx.n_pix, ctx.rng_maps)
            kp.leak_exp, kp.leak_ref_dn = float(self.light_exponent), float(self.ref_dn)


@dataclass(frozen=True, kw_only=True)
class ShotNoise(Effect):
    name: ClassVar[str] = "shot_noise"
    primary: ClassVar[str] = "rate_hz"
    n_fitted: ClassVar[int] = 2
    order: ClassVar[int] = 50
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

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        kp.shot_rate_hz, kp.shot_ref_dn, kp.shot_exp = self.kernel_law()
        if kp.shot_rate_hz > 0:
            # each pixel's first candidate (the kernel draws the following ones)
            kp.shot_next_us = float(ctx.t_lo_us) + ctx.rng_kernel.exponential(
                1e6 / (kp.shot_rate_hz * 10.0 ** kp.shot_exp), ctx.n_pix)


@dataclass(frozen=True, kw_only=True)
class Bandwidth(Effect):
    name: ClassVar[str] = "bandwidth"
    primary: ClassVar[str] = "cutoff_hz"
    order: ClassVar[int] = 70
    cutoff_hz: float = 100.0
    ref_dn: float = 128.0
    min_cutoff_hz: float = 0.5

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.cutoff_hz) and self.cutoff_hz > 0,
               "cutoff_hz must be finite and > 0", self.cutoff_hz)
        _check(self.name, self.ref_dn > 0, "ref_dn must be > 0", self.ref_dn)
        _check(self.name, self.min_cutoff_hz > 0, "min_cutoff_hz must be > 0",
               self.min_cutoff_hz)

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        kp.bw_cutoff_hz = float(self.cutoff_hz)
        kp.bw_ref_dn = float(self.ref_dn)
        kp.bw_min_cutoff_hz = float(self.min_cutoff_hz)


@dataclass(frozen=True, kw_only=True)
class ThresholdNoise(Effect):
    name: ClassVar[str] = "threshold_noise"
    primary: ClassVar[str] = "sigma"
    order: ClassVar[int] = 40
    sigma: float = 0.1

    def __post_init__(self) -> None:
        _check(self.name, 0 <= self.sigma <= 1, "sigma (a fraction of the threshold) must be "
               "in [0, 1]", self.sigma)

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        if self.sigma > 0:
            # the thresholds until each pixel's first event (the kernel re-draws them at each)
            s = kp.th_sigma = float(self.sigma)
            kp.th_on = kp.th_on_nom * np.maximum(
                0.2, 1 + s * ctx.rng_kernel.standard_normal(ctx.n_pix))
            kp.th_off = kp.th_off_nom * np.maximum(
                0.2, 1 + s * ctx.rng_kernel.standard_normal(ctx.n_pix))


@dataclass(frozen=True, kw_only=True)
class HotPixels(Effect):
    name: ClassVar[str] = "hot_pixels"
    primary: ClassVar[str] = "rate_hz"
    n_fitted: ClassVar[int] = 2
    order: ClassVar[int] = 80
    fraction: float = 0.002
    rate_hz: float = 50.0
    on_fraction: float = 0.5

    def __post_init__(self) -> None:
        _check(self.name, 0 <= self.fraction <= 1, "fraction must be in [0, 1]", self.fraction)
        _check(self.name, np.isfinite(self.rate_hz) and self.rate_hz >= 0,
               "rate_hz must be finite and >= 0", self.rate_hz)
        _check(self.name, 0 <= self.on_fraction <= 1, "on_fraction must be in [0, 1]",
               self.on_fraction)

    def after_kernel(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        if not (self.fraction > 0 and self.rate_hz > 0):
            return events
        rng, npix = ctx.rng_events, ctx.n_pix
        n_hot = int(round(self.fraction * npix))
        hp = np.sort(rng.choice(npix, size=n_hot, replace=False)) if n_hot else np.zeros(0, int)
        mask = np.zeros(npix, bool)
        mask[hp] = True
        ctx.pixel_truth["hot_pixels"] = mask
        t_lo, t_hi = ctx.t_lo_us, ctx.t_hi_us
        counts = rng.poisson(self.rate_hz * (t_hi - t_lo) * 1e-6, hp.size)
        h_pix = np.repeat(hp, counts).astype(np.int32)
        h_t = rng.integers(t_lo, t_hi + 1, h_pix.size)
        h_p = np.where(rng.random(h_pix.size) < self.on_fraction, 1, -1).astype(np.int8)
        return events.merged((h_t, h_pix, h_p), LABEL_HOT_PIXEL)


@dataclass(frozen=True, kw_only=True)
class LogOffset(Effect):
    name: ClassVar[str] = "log_offset"
    primary: ClassVar[str] = "dark_dn"
    order: ClassVar[int] = 10
    dark_dn: float = 20.0

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.dark_dn) and self.dark_dn >= 0,
               "dark_dn must be finite and >= 0", self.dark_dn)

    def log_offset(self, nominal_dn: float) -> float:
        return float(self.dark_dn)


@dataclass(frozen=True, kw_only=True)
class TimestampJitter(Effect):
    name: ClassVar[str] = "timestamp_jitter"
    primary: ClassVar[str] = "sigma_us"
    order: ClassVar[int] = 110
    sigma_us: float = 100.0
    quantum_us: int = 1

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.sigma_us) and self.sigma_us >= 0,
               "sigma_us must be finite and >= 0", self.sigma_us)
        _check(self.name, int(self.quantum_us) >= 1 and int(self.quantum_us) == self.quantum_us,
               "quantum_us must be an integer >= 1", self.quantum_us)

    def on_timestamps(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        if not (self.sigma_us > 0 or self.quantum_us > 1):
            return events
        t = events.t_us
        if self.sigma_us > 0:
            t = t + np.rint(ctx.rng_timestamps.normal(0.0, self.sigma_us, t.size)
                            ).astype(np.int64)
        t = np.maximum(t, ctx.t_start_out_us)
        q = int(self.quantum_us)
        if q > 1:
            t = (t // q) * q
        return events._replace(t_us=t).sorted_by_time()


@dataclass(frozen=True, kw_only=True)
class StartReset(Effect):
    """Every pixel's reference set to the log intensity it sees at the recording's first
    instant, where a sensor that ran before the recording started holds it anywhere within
    a threshold of it: a pixel's first event then needs a whole threshold of change. A
    property of simulators that start from their first input frame (v2e,
    v2ecore/emulator.py: ``base_log_frame`` set from the first frame), or of a sensor whose
    pixels are reset as it starts; no parameter."""

    name: ClassVar[str] = "start_reset"
    primary: ClassVar[str] = ""
    n_fitted: ClassVar[int] = 0
    order: ClassVar[int] = 150

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        kp.start_reset = True


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
    order: ClassVar[int] = 100
    step_us: float = 1000.0
    scheme: str = "spread"
    phase_us: float = 0.0  # step ends at t0 + phase_us + k step_us

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.step_us) and self.step_us >= 1,
               "step_us must be finite and >= 1", self.step_us)
        _check(self.name, self.scheme in ("spread", "end"), "scheme must be 'spread' or 'end'",
               self.scheme)
        _check(self.name, np.isfinite(self.phase_us), "phase_us must be finite", self.phase_us)

    def applies_dead_time(self) -> bool:
        return self.scheme == "spread"

    def on_timestamps(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        t0 = ctx.t_start_out_us
        out = quantise_events(
            *events, self, t0, n_pix=ctx.n_pix,
            t_end_us=float(ctx.times_us[-1]) + int(ctx.t_origin_us),
            refractory=ctx.stamp_dead_time if self.applies_dead_time() else None)
        return SimEvents(*out).sorted_by_time()


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
    order: ClassVar[int] = 20
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
        return light_response(intensity_dn, dark_dn, self.exponent,
                              self.ref_dn if ref is None else ref)

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        # the comparator runs on the response G(I + dark) (its initial reference too); the
        # noise and bandwidth laws in the kernel keep the true intensity
        kp.response_exp = float(self.exponent)
        kp.response_ref_dn = self.references(ctx.shape).ravel().copy()


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
    order: ClassVar[int] = 90
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

    def after_kernel(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        if not self.rate_hz > 0:
            return events
        # a disturbance of a shared readout or bias line, not of any pixel's state: its own
        # generator, so no other draw moves
        added = self.events(ctx.shape, ctx.t_lo_us, ctx.t_hi_us, ctx.spawn_rng())
        return events.merged(added, LABEL_ROW_NOISE)


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
    order: ClassVar[int] = 120
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

    def on_aps(self, aps: ApsConfig) -> ApsConfig:
        return replace(aps, dsnu_sigma_dn=float(self.sigma_dn), dsnu_mean_dn=float(self.mean_dn),
                       dsnu_seed=int(self.seed))


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
    order: ClassVar[int] = 130
    lag_us: float = 2500.0
    exposure_us: float = 5000.0

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.lag_us), "lag_us must be finite", self.lag_us)
        _check(self.name, np.isfinite(self.exposure_us) and self.exposure_us >= 0,
               "exposure_us must be finite and >= 0", self.exposure_us)

    def on_aps(self, aps: ApsConfig) -> ApsConfig:
        return replace(aps, exposure_us=int(round(self.exposure_us)), lag_us=float(self.lag_us))


@dataclass(frozen=True, kw_only=True)
class Flicker(Effect):
    """The light of the scene flickers: multiplied by ``1 + depth sin(2 pi freq_hz t +
    phase_rad)``, ``t`` the recording's time in seconds (lamps on the mains flicker at twice
    its frequency, 100 or 120 Hz; an LED's driver at its own). A property of the scene,
    not of the sensor: the events see it between the frames, the frames average it over
    their exposure (one at each phase: they alias it)."""

    name: ClassVar[str] = "flicker"
    primary: ClassVar[str] = "depth"
    n_fitted: ClassVar[int] = 3
    order: ClassVar[int] = 140
    freq_hz: float = 100.0
    depth: float = 0.05
    phase_rad: float = 0.0

    def __post_init__(self) -> None:
        _check(self.name, np.isfinite(self.freq_hz) and self.freq_hz > 0,
               "freq_hz must be finite and > 0", self.freq_hz)
        _check(self.name, np.isfinite(self.depth) and 0 <= self.depth < 1,
               "depth must be in [0, 1)", self.depth)
        _check(self.name, bool(np.isfinite(self.phase_rad)), "phase_rad must be finite",
               self.phase_rad)

    def on_light(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, np.float64)
        out: np.ndarray = 1.0 + self.depth * np.sin(2 * np.pi * self.freq_hz * t
                                                    + self.phase_rad)
        return out

    def exposure_mean(self, t_us: np.ndarray, exposure_us: np.ndarray) -> np.ndarray:
        """The factor's mean over each exposure ``[t - e/2, t + e/2]`` (centres ``t_us``,
        lengths ``exposure_us``): what a frame stamped at its exposure's centre saw."""
        t = np.asarray(t_us, np.float64) * 1e-6
        e = np.asarray(exposure_us, np.float64) * 1e-6
        # the mean of sin over a window of length e is sin at its centre times sinc(f e)
        out: np.ndarray = 1.0 + self.depth * np.sinc(self.freq_hz * e) * np.sin(
            2 * np.pi * self.freq_hz * t + self.phase_rad)
        return out


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
        for e in simulation_order(effects.values()):
            out = e.on_aps(out)
        return out


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (Refractory, Leak, ShotNoise, Bandwidth, ThresholdNoise, HotPixels, LogOffset,
                TimestampJitter, TimestampQuantisation, ThresholdLight, RowNoise, ApsFpn,
                Exposure, Flicker, StartReset)
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
