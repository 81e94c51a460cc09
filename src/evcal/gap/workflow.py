"""The model-gap loop: fit, simulate, compare, name the missing effect, repeat.

1. Fit the base model (``c``, ``b`` by OffEI at the nominal log offset) and anchor it.
2. Simulate the measured recording under the model with ``n_seeds`` seeds (driven by its
   frames) and compute the standardised discrepancy of every statistic (:mod:`.stats`); the
   gap is their mean (about 1 when the model explains the data).
3. For each effect not in the model yet: estimate its parameters (:func:`.model.fit_candidate`),
   anchor, simulate with the same seeds, and compute the gap. The score is the gap plus
   ``penalty_per_parameter`` per fitted parameter.
4. The best candidate is named if it lowers the gap (counted down to 1, what a model that
   explains the data leaves) by more than its penalty plus ``min_improvement`` and by at
   least ``min_relative_improvement`` of the part of the gap above 1. Its moment estimate is
   bias-corrected by simulation and, unless that confirms it, refined by a three-point
   search. Repeat from 3 until nothing is named or ``max_effects`` are.

The timestamp scheme of a frame-driven simulator (``timestamp_quantisation``) is not a
sensor effect: once its fitter sees the timestamps on a step grid, the sensor candidates are
evaluated on top of it, and it is named when it closes the gap alone or with the best of
them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..jsonable import to_jsonable
from ..recording import Recording
from ..sim.effects import EFFECT_NAMES, Effect
from .model import (
    Model,
    SimSettings,
    anchor,
    estimate_read_noise,
    fit_base,
    fit_candidate,
    population,
    simulate_model,
    variants,
)
from .stats import Discrepancy, GapError, Observation, discrepancy, observe, summarise


@dataclass(frozen=True, kw_only=True)
class GapConfig:
    max_effects: int = 3
    seed: int = 0
    n_seeds: int = 3
    internal_rate_hz: float = 1000.0
    interpolation: str = "flow"  # between frames: "flow" (evcal.gap.flow) or "linear"
    # timing statistics only in windows whose flow is consistent and at most this many pixels
    # (evcal.gap.flow.trusted_windows); None: every window
    trusted_max_px: float | None = math.inf
    penalty_per_parameter: float = 0.1
    min_improvement: float = 0.3
    min_relative_improvement: float = 0.25
    refine: bool = True
    # bias-correct each named effect's moment estimate by refitting it on the simulations
    # made with it (see _Runner.debias)
    debias: bool = True
    candidates: tuple[str, ...] = EFFECT_NAMES

    def __post_init__(self) -> None:
        if self.max_effects < 0:
            raise ValueError(f"max_effects={self.max_effects} must be >= 0")
        if self.n_seeds < 2:
            raise ValueError(f"n_seeds={self.n_seeds} must be >= 2 (the spread needs two)")
        unknown = set(self.candidates) - set(EFFECT_NAMES)
        if unknown:
            raise ValueError(f"unknown candidate effect(s) {sorted(unknown)}")


@dataclass
class Evaluation:
    model: Model
    sims: list[Observation]  # during a run; empty in a GapResult (see run_gap)
    disc: Discrepancy

    @property
    def gap(self) -> float:
        return self.disc.gap


@dataclass
class Step:
    effect: Effect
    before: Evaluation
    after: Evaluation
    candidates: dict[str, dict[str, Any]]

    def moved_statistics(self, top: int = 4) -> list[str]:
        drops = {k: self.before.disc.per_stat[k] - self.after.disc.per_stat[k]
                 for k in self.before.disc.per_stat}
        ranked = sorted(drops, key=lambda k: -drops[k])
        return [k for k in ranked[:top] if drops[k] > 0.5]


@dataclass
class GapResult:
    recording_info: dict[str, Any]
    measured: dict[str, Any]
    initial: Evaluation
    final: Evaluation
    steps: list[Step] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    # candidates of the round that named nothing (why the loop stopped)
    rejected: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def named_effects(self) -> list[str]:
        return [s.effect.name for s in self.steps]

    def to_json(self) -> dict[str, Any]:
        """The stable ``report.json`` schema."""
        d0, d1 = self.initial.disc, self.final.disc
        stats = []
        for name in d0.per_stat:
            stats.append({
                "name": name,
                "measured": _list(d0.measured[name]),
                "simulated_initial": _list(d0.sim_mean[name]),
                "simulated_final": _list(d1.sim_mean[name]),
                "z_initial": float(np.sqrt(d0.per_stat[name])),
                "z_final": float(np.sqrt(d1.per_stat[name])),
            })
        return {
            "named_effects": self.named_effects,
            "gap_initial": float(self.initial.gap),
            "gap_final": float(self.final.gap),
            "steps": [{
                "effect": s.effect.name,
                "parameters": to_jsonable(s.effect.parameters()),
                "gap_before": float(s.before.gap),
                "gap_after": float(s.after.gap),
                "moved_statistics": s.moved_statistics(),
            } for s in self.steps],
            "statistics": stats,
        }


def _list(a: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(a, np.float64).ravel()]


class _Runner:
    DEBIAS_STEPS = 2  # bootstrap steps per named effect (an evaluation each)

    def __init__(self, rec: Recording, cfg: GapConfig, tick: Callable[[str], None]):
        self.rec = rec
        self.cfg = cfg
        self.tick = tick
        self.trusted = None
        if cfg.trusted_max_px is not None:
            from .flow import trusted_windows  # noqa: PLC0415

            self.trusted = trusted_windows(rec.frames, max_px=cfg.trusted_max_px)
        self.meas = observe(rec, trusted=self.trusted)
        self.meas_stats = summarise(self.meas)
        self.meas_pop = population(self.meas)
        self.settings = SimSettings(internal_rate_hz=cfg.internal_rate_hz,
                                    read_noise_dn=estimate_read_noise(rec.frames),
                                    interpolation=cfg.interpolation)
        self.seeds = [cfg.seed * 1000 + k for k in range(cfg.n_seeds)]
        self.anchor_seed = cfg.seed * 1000 + 999

    def evaluate(self, model: Model, what: str) -> Evaluation:
        model = anchor(model, self.rec, self.meas, self.anchor_seed, self.settings)
        self.tick(f"{what}: anchor")
        sims = []
        for s in self.seeds:
            sims.append(observe(simulate_model(model, self.rec, s, self.settings),
                                trusted=self.trusted))
            self.tick(f"{what}: seed {s}")
        disc = discrepancy(self.meas_stats, [summarise(o) for o in sims])
        return Evaluation(model, sims, disc)

    def candidate_model(self, current: Model, eff: Effect) -> Model:
        if eff.name == "log_offset":
            base = fit_base(self.rec, log_offset=float(eff.parameters()["dark_dn"]))
            m = Model(base.contrast, base.bias, base.log_offset, dict(current.effects))
            return m.with_effect(eff)
        return current.with_effect(eff)

    def debias(self, current: Evaluation, best: Evaluation, eff: Effect
               ) -> tuple[Effect, Evaluation, dict[str, Any]]:
        """The moment estimate's own bias, removed by simulation (a parametric bootstrap):
        the fitter applied to the simulations made *with* the effect at ``v`` (in place of
        the measurement, against the same effect-free simulations) returns ``f(v)``; where
        ``f(v) != v`` the estimator is biased on data like these (leak's excess of ON events
        in still windows misses the drift a pixel pays off before the pause ends: at 25 Hz
        with short pauses ``f(v)`` is ~0.4 v). The value whose simulations give the measured
        moment ``m`` solves ``f(v) = m``: ``v <- v m / f(v)`` from ``v = m``, up to
        ``DEBIAS_STEPS`` times (each step's factor clipped to [1/4, 4]) while it moves by
        more than 5 %. The result is kept when its gap is not clearly worse than the moment
        estimate's (the gap is noisy; the bootstrap is the better-founded value)."""
        key = eff.primary
        m = float(eff.parameters()[key])
        info: dict[str, Any] = {"moment": m, "value": m, "steps": []}
        if m <= 0:
            return eff, best, info
        cur_eff, cur_ev = eff, best
        for _ in range(self.DEBIAS_STEPS):
            v = float(cur_eff.parameters()[key])
            again = []
            for sim in cur_ev.sims:
                e = fit_candidate(eff.name, sim, current.sims, current.model, self.rec)
                if e is not None and float(e.parameters()[key]) > 0:
                    again.append(float(e.parameters()[key]))
            if len(again) < max(2, len(cur_ev.sims) // 2):
                info["note"] = "the fitter did not find the effect in its own simulations"
                break
            f_v = float(np.exp(np.mean(np.log(again))))
            factor = float(np.clip(m / f_v, 0.25, 4.0))
            step: dict[str, Any] = {"value": v, "refits": again, "factor": round(factor, 4)}
            info["steps"].append(step)
            if abs(np.log(factor)) < 0.05:
                break
            try:
                nxt = cur_eff.with_params(**{key: _cast(eff, key, v * factor)})
            except ValueError:  # outside the parameter's range
                info["note"] = "the corrected value is outside the parameter's range"
                break
            cur_ev = self.evaluate(self.candidate_model(current.model, nxt),
                                   f"debias {eff.name}")
            cur_eff = nxt
            step["gap_next"] = float(cur_ev.gap)
        if cur_eff is eff or cur_ev.gap > best.gap + max(0.3, 0.1 * best.gap):
            return eff, best, info
        info["value"] = float(cur_eff.parameters()[key])
        return cur_eff, cur_ev, info

    def scheme_candidate(self, current: Evaluation, tried: dict[str, dict[str, Any]]
                         ) -> tuple[Effect, Evaluation] | None:
        """The timestamp scheme fitted and evaluated, when it is a candidate not yet in the
        model and its fitter sees it."""
        if SCHEME_EFFECT not in self.cfg.candidates or SCHEME_EFFECT in current.model.effects:
            return None
        eff = fit_candidate(SCHEME_EFFECT, self.meas, current.sims, current.model, self.rec)
        if eff is None:
            tried[SCHEME_EFFECT] = {"parameters": None, "gap": None}
            return None
        ev = self.evaluate(self.candidate_model(current.model, eff), f"candidate {eff.name}")
        tried[SCHEME_EFFECT] = {"parameters": eff.parameters(), "gap": ev.gap,
                                "score": ev.gap + self.cfg.penalty_per_parameter * eff.n_fitted}
        return eff, ev

    def best_candidate(self, current: Evaluation, tried: dict[str, dict[str, Any]], *,
                       skip: str) -> tuple[float, Effect, Evaluation] | None:
        """Every candidate but ``skip`` not in ``current``'s model, fitted from its
        simulations and evaluated on top of it; the one of the lowest score."""
        best: tuple[float, Effect, Evaluation] | None = None
        for name in self.cfg.candidates:
            if name in current.model.effects or name == skip:
                continue
            fitted = fit_candidate(name, self.meas, current.sims, current.model, self.rec)
            if fitted is None:
                tried[name] = {"parameters": None, "gap": None}
                continue
            for eff in variants(fitted):  # discrete alternatives: the gap decides
                ev = self.evaluate(self.candidate_model(current.model, eff),
                                   f"candidate {name}")
                score = ev.gap + self.cfg.penalty_per_parameter * eff.n_fitted
                if name in tried and tried[name]["score"] <= score:
                    tried[name].setdefault("variants", []).append(
                        {"parameters": eff.parameters(), "gap": ev.gap})
                    continue
                tried[name] = {"parameters": eff.parameters(), "gap": ev.gap, "score": score,
                               "variants": [{"parameters": e["parameters"], "gap": e["gap"]}
                                            for e in [tried.get(name)] if e is not None]}
                if best is None or score < best[0]:
                    best = (score, eff, ev)
        return best

    def finish(self, current: Evaluation, ev: Evaluation, eff: Effect,
               tried: dict[str, dict[str, Any]]) -> tuple[Effect, Evaluation]:
        """A named candidate's estimate bias-corrected and refined (as configured)."""
        if self.cfg.debias:
            eff, ev, info = self.debias(current, ev, eff)
            tried[eff.name]["debias"] = info
            if info["steps"] and abs(np.log(info["steps"][0]["factor"])) < 0.05:
                # the fitter gives back its own value on the model's simulations: the
                # estimate is consistent, and a search of the gap would trade it against
                # what the model misses elsewhere (interpolated frames)
                return eff, ev
        if self.cfg.refine:
            eff, ev = self.refine(current.model, ev, eff)
        return eff, ev

    def refine(self, current: Model, best: Evaluation, eff: Effect) -> tuple[Effect, Evaluation]:
        key = eff.primary
        v0 = float(eff.parameters()[key])
        if v0 <= 0:
            return eff, best
        factors = (0.7, 1.0, 1 / 0.7)
        gaps = []
        evals = []
        for f in factors:
            if f == 1.0:
                gaps.append(best.gap)
                evals.append((eff, best))
                continue
            try:
                e = eff.with_params(**{key: _cast(eff, key, v0 * f)})
            except ValueError:  # outside the parameter's range (e.g. sigma above 1)
                return eff, best  # no three-point search: the moment estimate stands
            ev = self.evaluate(self.candidate_model(current, e), f"refine {eff.name}")
            gaps.append(ev.gap)
            evals.append((e, ev))
        y = np.asarray(gaps)
        x = np.log(np.asarray(factors))
        den = y[0] - 2 * y[1] + y[2]
        if den > 0:
            xv = float(np.clip(x[1] + 0.5 * (x[1] - x[0]) * (y[0] - y[2]) / den, x[0], x[2]))
            if abs(xv) > 0.05 and int(np.argmin(y)) != 0 and int(np.argmin(y)) != 2:
                e = eff.with_params(**{key: _cast(eff, key, v0 * np.exp(xv))})
                ev = self.evaluate(self.candidate_model(current, e), f"refine {eff.name}")
                gaps.append(ev.gap)
                evals.append((e, ev))
        i = int(np.argmin(gaps))
        # keep the moment estimate unless the search clearly beats it (the gap is noisy)
        if gaps[i] < best.gap - max(0.3, 0.1 * best.gap):
            return evals[i]
        return eff, best


SCHEME_EFFECT = "timestamp_quantisation"  # a simulator's timestamp scheme, not a sensor effect


def _need(cfg: GapConfig, current: Evaluation) -> float:
    """The least gain that names a candidate against ``current``."""
    return max(cfg.min_improvement, cfg.min_relative_improvement * (current.gap - 1.0))


def _gain(gap: float, score: float) -> float:
    """How much a candidate of ``score`` (its gap plus penalty) takes off ``gap``, counted
    down to 1 only: a model that explains the data leaves a gap of about 1, and what a
    candidate takes off below that fits the noise of the comparison."""
    return gap - max(score, 1.0)


def _cast(eff: Effect, key: str, value: float) -> Any:
    old = eff.parameters()[key]
    if isinstance(old, int) and not isinstance(old, bool):
        return max(1, int(round(value)))
    return round(float(value), 6)


def n_simulations(cfg: GapConfig) -> int:
    """Upper-bound estimate of simulations (for a progress bar)."""
    per = cfg.n_seeds + 1
    k = len(cfg.candidates)
    return per * (1 + sum(k - i for i in range(cfg.max_effects + 1)) + 6 * cfg.max_effects)


def run_gap(rec: Recording, config: GapConfig | None = None, *,
            progress: Callable[[str], None] | None = None) -> GapResult:
    """Run the gap workflow on ``rec`` (measured or simulated; it needs frames).

    Raises
    ------
    GapError
        When the recording lacks frames or events between them.
    """
    cfg = config or GapConfig()
    if len(rec.frames) < 4:
        raise GapError("the gap workflow needs a recording with at least 4 frames (APS or "
                       "images.txt): simulations are driven by the measured frames")
    tick = progress or (lambda _msg: None)
    run = _Runner(rec, cfg, tick)
    base = fit_base(rec)
    current = run.evaluate(base, "base model")
    initial = current
    steps: list[Step] = []
    rejected: dict[str, dict[str, Any]] = {}

    def n_sensor() -> int:  # max_effects counts sensor effects, not the timestamp scheme
        return sum(s.effect.name != SCHEME_EFFECT for s in steps)

    while n_sensor() < cfg.max_effects:
        tried: dict[str, dict[str, Any]] = {}
        # the timestamp scheme first: once the timestamps are seen to lie on a step grid,
        # every sensor candidate is fitted and simulated with the scheme (how a frame-driven
        # simulator stamps its events changes what its dead time, noise and jitter look like:
        # v2e's refractory period shows only in its slots, neither alone)
        scheme = run.scheme_candidate(current, tried)
        on = scheme[1] if scheme is not None else current
        best = run.best_candidate(on, tried, skip=SCHEME_EFFECT)
        if scheme is not None:
            eff_q, ev_q = scheme
            pen_q = cfg.penalty_per_parameter * eff_q.n_fitted
            q_alone = _gain(current.gap, ev_q.gap + pen_q) > _need(cfg, current)
            joint = best is not None and _gain(ev_q.gap, best[0]) > _need(cfg, ev_q) and \
                _gain(current.gap, best[0] + pen_q) > _need(cfg, current)
            if not (q_alone or joint):
                rejected = tried
                break
            # read off the timestamps: neither bias-corrected nor refined, so the candidates
            # evaluated on top of it stand
            steps.append(Step(eff_q, current, ev_q, tried))
            current = ev_q
            tried = {k: v for k, v in tried.items() if k != SCHEME_EFFECT}
        if best is None or _gain(current.gap, best[0]) <= _need(cfg, current):
            rejected = tried
            break
        _, eff, ev = best
        eff, ev = run.finish(current, ev, eff, tried)
        steps.append(Step(eff, current, ev, tried))
        current = ev
    info = {"sensor": str(rec.sensor), "n_events": rec.n_events,
            "n_frames": len(rec.frames), "duration_s": rec.duration_s}
    settings = {"seed": cfg.seed, "n_seeds": cfg.n_seeds, "internal_rate_hz": cfg.internal_rate_hz,
                "read_noise_dn": run.settings.read_noise_dn,
                "penalty_per_parameter": cfg.penalty_per_parameter,
                "min_improvement": cfg.min_improvement,
                "min_relative_improvement": cfg.min_relative_improvement}
    # the result keeps each evaluation's model and statistics, not its simulated
    # observations (about 200 MB per evaluation at 2 s of 96x128: a run held 0.4 GB)
    light: dict[int, Evaluation] = {}

    def lighten(ev: Evaluation) -> Evaluation:
        return light.setdefault(id(ev), Evaluation(ev.model, [], ev.disc))

    steps = [Step(s.effect, lighten(s.before), lighten(s.after), s.candidates) for s in steps]
    return GapResult(info, run.meas_stats, lighten(initial), lighten(current), steps, settings,
                     rejected)
