"""The house of the gap workflow's effects: one :class:`EffectSpec` per effect, one registry.

An effect of the simulator (:mod:`evcal.sim.effects`: its parameters and its simulation hook)
enters the gap workflow through its spec here, which says

- ``fit``: how its parameters are estimated from a measurement and the current model's
  simulations (a :class:`FitContext`), returning :class:`Fitted` or, when the data show
  none of it, :class:`NoEvidence` with the reason in words (the report prints it);
- ``strength``: one number, 0 when the effect is absent and growing with it, in which
  the null calibration compares what the fitter reads on the measurement with what it
  reads on the model's own simulations (:mod:`evcal.gap.null`);
- ``moves``: the statistics (:mod:`evcal.gap.stats`) its signature shows in;
- ``says``: the sentence the report uses for a fitted value;
- ``kind``: ``"sensor"`` (the DVS pixel), ``"frames"`` (the APS readout: the frames that
  drive the simulation), ``"scheme"`` (how a frame-driven simulator stamps its events:
  not a property of a sensor, reported apart), ``"scene"`` (the light itself, a lamp's
  flicker: read before the sensor's effects, reported apart) or ``"start"`` (how the
  recording began: every reference reset at its first instant, as a frame-driven simulator
  starts; read before the sensor's effects, reported apart).

To add an effect: write its parameter object and simulation hook in
:mod:`evcal.sim.effects`, its fitter (a function of a :class:`FitContext`) beside the others
(:mod:`.fitters`, :mod:`.fitters_events`, :mod:`.frames`), and one :class:`EffectSpec` in
:data:`REGISTRY` below. Nothing else in the workflow names an effect.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError
from ..recording import Recording
from ..sim.effects import (
    ApsFpn,
    Bandwidth,
    Effect,
    Exposure,
    Flicker,
    HotPixels,
    Leak,
    LogOffset,
    Refractory,
    RowNoise,
    ShotNoise,
    StartReset,
    ThresholdLight,
    ThresholdNoise,
    TimestampJitter,
    TimestampQuantisation,
)
from .stats import Observation

if TYPE_CHECKING:
    from .model import Model


@dataclass(frozen=True)
class Fitted:
    """A fitter's estimate: the effect with its parameters, and what it rests on (a few
    figures for the report: events, excess, z)."""

    effect: Effect
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class NoEvidence:
    """A fitter that sees none of its effect says why, in words."""

    reason: str


FitResult = Fitted | NoEvidence


@dataclass(frozen=True)
class FitContext:
    """What a fitter sees.

    ``meas`` and ``sims`` are the measurement's and the current model's simulations'
    observations on the rows the fit may use (``rows``, indices into the whole sensor; all
    of them when ``None``): the workflow fits a candidate on one half of the rows and judges
    it on the other. ``model`` is the current model cut to those rows. ``rec`` is the
    recording (its frames and their timing; a fitter reads its events only where it fits
    a global quantity, such as the log offset). ``whole`` is the measurement on every row,
    for what depends on the frames alone (each pixel's light). ``shape`` is the whole
    sensor's. A fitter that estimates a per-pixel map returns it for the whole sensor:
    :meth:`whole_map` fills the rows it did not see with draws from the fitted spread.
    """

    meas: Observation
    sims: list[Observation]
    model: Model
    rec: Recording
    whole: Observation
    rows: np.ndarray | None = None
    seed: int = 0
    # the rows of the recording's frames that ``meas`` holds when they are not ``rows``
    # (a band of rows the fit sees as a sensor of its own)
    frame_rows: slice | None = None
    # the current model (whole sensor) with an effect added, simulated on one seed (not
    # anchored), its observation on the rows of ``meas``: for a fitter that matches or
    # settles by simulation (a scene's flicker, the dark level); ``None`` outside the
    # workflow (each call costs a whole-sensor simulation)
    simulate: Callable[[Effect], Observation] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.whole.shape

    def recording(self) -> Recording:
        """The measurement's events on the fit rows with the frames cut to them, as a
        recording (for the estimators of the calibration, which read recordings)."""
        from ..events import EVENTS_DTYPE, SensorSize  # noqa: PLC0415
        from ..recording import Frames  # noqa: PLC0415

        h, w = self.meas.shape
        ev = np.empty(self.meas.t_us.size, EVENTS_DTYPE)
        ev["t_us"] = self.meas.t_us
        ev["x"] = self.meas.pix % w
        ev["y"] = self.meas.pix // w
        ev["p"] = self.meas.p
        fr = self.rec.frames
        rows = self.frame_rows if self.frame_rows is not None else self.rows
        images = fr.images if rows is None else fr.images[:, rows]
        return Recording(SensorSize(h, w), ev, Frames(fr.t_us, images, fr.exposure_us),
                         dict(self.rec.metadata))

    def whole_map(self, part: np.ndarray, spread: float, mean: float = 0.0) -> np.ndarray:
        """``part`` (a map of :attr:`rows`) on the whole sensor, the other rows drawn from
        ``N(mean, spread)`` (a fixed seed): the held-out rows get a pattern of the fitted
        spread, not the fit of their own data."""
        h, w = self.shape
        part = np.asarray(part, np.float64).reshape(-1, w)
        if self.rows is None:
            return part.reshape(h, w)
        rng = np.random.default_rng([self.seed, 0x4E11])
        out = mean + spread * rng.standard_normal((h, w))
        out[self.rows] = part
        return out


KINDS = ("sensor", "frames", "scheme", "scene", "start")
# the kinds tried before the sensor's effects, on the base model and again after each named
# effect, and named by their held-out gain alone (no null calibration: the model's own
# simulations have neither a lamp nor a reset)
BEFORE_SENSOR_KINDS = ("scene", "start")
# the kinds that count as the sensor's (``max_effects``, the benchmark's confusion table)
SENSOR_KINDS = ("sensor", "frames")


@dataclass(frozen=True)
class EffectSpec:
    name: str
    effect: type[Effect]
    fit: Callable[[FitContext], FitResult]
    strength: Callable[[Effect, float], float]
    moves: tuple[str, ...]
    says: Callable[[Effect], str]
    kind: str = "sensor"
    # the alternatives of a discrete parameter the fitter cannot tell apart reliably, each
    # evaluated by the workflow (the fitted effect first)
    alternatives: Callable[[Effect], list[Effect]] = field(default=lambda e: [e])
    # fitted on the fit rows and judged on the held-out rows (True), or fitted on every row
    # (False): for an effect whose per-pixel parameters only its own pixels can say (a map
    # of the frames' dark offsets), which the base model's per-pixel maps, fitted on the
    # same pixels, have absorbed part of. Such an effect is held to the gain it shows, fitted
    # the same way, on the model's own simulations (the null calibration)
    held_out: bool = True
    # the value reported as the effect's main one, in a user's units, from the effect and
    # the recording's median light (DN); default its primary parameter
    value: Callable[[Effect, float], float] = field(
        default=lambda e, _light: float(e.parameters()[e.primary]))

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"{self.name}: kind {self.kind!r} is not one of {KINDS}")
        if self.effect.name != self.name:
            raise ConfigError(f"spec {self.name!r} holds effect {self.effect.name!r}")


# ------------------------------------------------------------------------- strengths
# one number per effect, 0 when absent, in units of the effect (light_dn: the recording's
# median frame value, DN, where a light-dependent law is read)


def _p(e: Effect, key: str) -> float:
    return float(e.parameters()[key])


def _leak_rate(e: Effect, light_dn: float) -> float:
    assert isinstance(e, Leak)
    rel = max(light_dn, 1e-3) / float(e.ref_dn)
    return float(e.rate_hz) * float(rel ** float(e.light_exponent))


def _shot_rate(e: Effect, light_dn: float) -> float:
    assert isinstance(e, ShotNoise)
    return float(e.rate_at(np.asarray(light_dn)))


def _bandwidth_delay_us(e: Effect, light_dn: float) -> float:
    """The low-pass's time constant at ``light_dn`` (us): what it delays a ramp by."""
    assert isinstance(e, Bandwidth)
    f = max(float(e.cutoff_hz) * (light_dn + 1.0) / float(e.ref_dn), float(e.min_cutoff_hz))
    return 1e6 / (2.0 * np.pi * f)


def _refractory_modes(e: Effect) -> list[Effect]:
    """A dead time that drops crossings or delays them: the pile of intervals just above
    the period that tells them apart is blurred where timestamps are quantised."""
    assert isinstance(e, Refractory)
    return [e, e.with_params(mode="drop" if e.mode == "delay" else "delay")]


# ------------------------------------------------------------------------------- words


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def _words_refractory(e: Effect) -> str:
    assert isinstance(e, Refractory)
    how = "lost" if e.mode == "drop" else "delayed to its end"
    return f"a dead time of {_fmt(e.period_us)} us after every event (crossings in it {how})"


def _words_leak(e: Effect) -> str:
    assert isinstance(e, Leak)
    law = "" if e.light_exponent == 0 else \
        f", growing with light as I^{_fmt(e.light_exponent)}"
    return f"ON events from reset leakage, {_fmt(e.rate_hz)} Hz per pixel at " \
           f"{_fmt(e.ref_dn)} DN{law}"


def _words_shot(e: Effect) -> str:
    assert isinstance(e, ShotNoise)
    return f"noise events of both polarities, {_fmt(e.rate_hz)} Hz per pixel at " \
           f"{_fmt(e.ref_dn)} DN, falling with light as I^-{_fmt(e.light_exponent)}"


def _words_bandwidth(e: Effect) -> str:
    assert isinstance(e, Bandwidth)
    return f"a photoreceptor low-pass of {_fmt(e.cutoff_hz)} Hz at {_fmt(e.ref_dn)} DN, " \
           "slower in proportion in the dark"


REGISTRY: dict[str, EffectSpec] = {}


def register(spec: EffectSpec) -> EffectSpec:
    """Add ``spec`` to :data:`REGISTRY` (one per effect name)."""
    if spec.name in REGISTRY:
        raise ConfigError(f"effect {spec.name!r} is registered already")
    REGISTRY[spec.name] = spec
    return spec


def _register_all() -> None:
    from . import fitters as fx  # noqa: PLC0415 - the fitters import this module's types
    from . import fitters_events as fe  # noqa: PLC0415
    from . import flicker as fl  # noqa: PLC0415
    from . import frames as fr  # noqa: PLC0415
    from . import start as st  # noqa: PLC0415

    def plain(key: str) -> Callable[[Effect, float], float]:
        return lambda e, _light: abs(_p(e, key))

    register(EffectSpec(
        # timestamp_quantum: where stamps lie on a grid (a frame-driven simulator's steps),
        # a dead time that delays crossings to its end moves them between the grid's slots,
        # and there it shows in nothing else (v2e's refractory period)
        "refractory", Refractory, fx.fit_refractory, plain("period_us"),
        ("iei_distribution", "iei_lower_edge", "polarity_alternation", "timestamp_quantum"),
        _words_refractory,
        alternatives=_refractory_modes))
    register(EffectSpec(
        "leak", Leak, fe.fit_leak, _leak_rate,
        ("static_balance_vs_intensity", "on_fraction_over_time", "static_rate_vs_intensity"),
        _words_leak, value=_leak_rate))
    register(EffectSpec(
        "shot_noise", ShotNoise, fx.fit_shot_noise, _shot_rate,
        ("static_rate_vs_intensity", "polarity_alternation", "rate_tail"), _words_shot,
        value=_shot_rate))
    register(EffectSpec(
        "bandwidth", Bandwidth, fx.fit_bandwidth, _bandwidth_delay_us,
        # a low-pass lags a window's events into the next in proportion to its change: the
        # per-pixel fit's residual grows with |dL|; it carries a moving edge's events into
        # the still windows after it, the longer the darker
        ("speed_response", "lag_vs_intensity", "sensitivity_vs_intensity",
         "offei_residual_vs_dl", "static_rate_vs_intensity", "static_balance_vs_intensity"),
        _words_bandwidth))
    register(EffectSpec(
        "threshold_noise", ThresholdNoise, fx.fit_threshold_noise, plain("sigma"),
        ("offei_residual_vs_dl", "offei_residual_vs_time", "estimate_stability"),
        lambda e: f"thresholds drawn anew at every event, spread "
                  f"{_fmt(_p(e, 'sigma'))} of their value"))
    register(EffectSpec(
        "hot_pixels", HotPixels, fx.fit_hot_pixels,
        lambda e, _l: _p(e, "fraction") * _p(e, "rate_hz"),
        ("rate_tail", "static_rate_vs_intensity"),
        lambda e: f"{_fmt(100 * _p(e, 'fraction'))} % of the pixels fire "
                  f"{_fmt(_p(e, 'rate_hz'))} Hz whatever the light"))
    register(EffectSpec(
        "log_offset", LogOffset, fx.fit_log_offset, plain("dark_dn"),
        ("sensitivity_vs_intensity", "offei_residual_vs_intensity", "fit_population"),
        lambda e: f"the pixels see log(I + {_fmt(_p(e, 'dark_dn'))} DN): a dark current "
                  "under the frames' zero"))
    register(EffectSpec(
        "timestamp_jitter", TimestampJitter, fx.fit_timestamp_jitter, plain("sigma_us"),
        ("iei_distribution", "iei_lower_edge", "timestamp_quantum"),
        lambda e: f"timestamps jittered by {_fmt(_p(e, 'sigma_us'))} us"
                  + (f" on a {int(_p(e, 'quantum_us'))} us grid"
                     if _p(e, "quantum_us") > 1 else "")))
    register(EffectSpec(
        "timestamp_quantisation", TimestampQuantisation, fx.fit_timestamp_quantisation,
        plain("step_us"), ("timestamp_quantum", "iei_distribution", "iei_lower_edge"),
        lambda e: f"events stamped on the {_fmt(_p(e, 'step_us'))} us steps of a "
                  "frame-driven simulator", kind="scheme"))
    register(EffectSpec(
        "threshold_light", ThresholdLight, fe.fit_threshold_light, plain("exponent"),
        ("sensitivity_vs_intensity", "offei_residual_vs_intensity"),
        lambda e: f"thresholds that grow in the dark as I^-{_fmt(_p(e, 'exponent'))}"))
    register(EffectSpec(
        "row_noise", RowNoise, fe.fit_row_noise,
        lambda e, _l: _p(e, "rate_hz") * _p(e, "fraction"),
        # the bursts' events are noise, of either polarity, in still pixels too: they add
        # short pairs of opposite polarity and still pixels' events as shot noise does
        ("line_coincidence", "polarity_alternation", "static_rate_vs_intensity", "rate_tail"),
        lambda e: f"bursts along a readout {e.parameters()['axis']}, "
                  f"{_fmt(_p(e, 'rate_hz'))} Hz per line, "
                  f"{_fmt(100 * _p(e, 'fraction'))} % of its pixels each"))
    register(EffectSpec(
        "aps_fpn", ApsFpn, fr.fit_aps_fpn, plain("sigma_dn"),
        ("offei_residual_vs_intensity", "sensitivity_vs_intensity", "fit_population"),
        lambda e: f"a dark offset per pixel in the frames only, spread "
                  f"{_fmt(_p(e, 'sigma_dn'))} DN", kind="frames", held_out=False))
    register(EffectSpec(
        "exposure", Exposure, fr.fit_exposure, plain("lag_us"),
        ("lag_vs_intensity", "speed_response", "offei_residual_vs_dl"),
        lambda e: f"the frames' exposure centred {_fmt(_p(e, 'lag_us'))} us after their "
                  "stamps (every pixel alike)", kind="frames"))
    register(EffectSpec(
        "start_reset", StartReset, st.fit_start_reset, lambda _e, _l: 1.0,
        ("first_event_change", "static_rate_vs_intensity", "static_balance_vs_intensity",
         "on_fraction_over_time", "sensitivity_vs_intensity", "speed_response"),
        lambda _e: "every pixel's reference set to its light at the recording's first "
                   "instant (a simulator that starts from its first frame, not a sensor "
                   "that ran before)", kind="start", value=lambda _e, _l: 1.0))
    register(EffectSpec(
        "flicker", Flicker, fl.fit_flicker, plain("depth"),
        ("polarity_alternation", "iei_distribution", "static_rate_vs_intensity"),
        lambda e: f"the scene's light flickers at {_fmt(_p(e, 'freq_hz'))} Hz, "
                  f"{_fmt(100 * _p(e, 'depth'))} % deep (a lamp on the mains)", kind="scene"))


def spec(name: str) -> EffectSpec:
    """The spec of effect ``name``."""
    if not REGISTRY:
        _register_all()
    try:
        return REGISTRY[name]
    except KeyError:
        raise ConfigError(f"no gap effect {name!r}; known: {', '.join(names())}") from None


def names() -> tuple[str, ...]:
    """Every registered effect, in the registry's order."""
    if not REGISTRY:
        _register_all()
    return tuple(REGISTRY)


def with_reason(result: FitResult, prefix: str) -> FitResult:
    """``result`` with ``prefix`` before its reason (a :class:`Fitted` unchanged)."""
    if isinstance(result, NoEvidence):
        return replace(result, reason=f"{prefix}{result.reason}")
    return result
