"""What a named effect's estimate goes through before it is named: its moment estimate
bias-corrected by simulation (a parametric bootstrap, on the band of rows first when the run
screens on one) and, unless that confirms it, refined by a three-point search of the gap."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ..sim.effects import Effect
from .compare import discrepancy
from .model import Model, fit_candidate
from .runner import Evaluation, Runner, drop_derived
from .stats import Observation, rows_of, summarise

DEBIAS_STEPS = 2  # bootstrap steps per named effect (an evaluation each)


def debias(run: Runner, current: Evaluation, best: Evaluation, eff: Effect
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
    if run.band is not None:
        return _debias_on_band(run, current, best, eff, info)
    def refit(sim: Observation) -> Effect | None:
        return fit_candidate(eff.name, sim, current.sims, current.model, run.rec)

    def evaluate(nxt: Effect, at: Evaluation) -> Evaluation:
        ev = run.evaluate(run.near_model(current.model, at.model, nxt),
                           f"debias {eff.name}")
        info["steps"][-1]["gap_next"] = float(ev.gap)
        return ev

    cur_eff, cur_ev = _bootstrap(run, eff, m, best, refit, evaluate, info)
    drop_derived(current.sims)
    if cur_eff is eff or cur_ev.gap > best.gap + max(0.3, 0.1 * best.gap):
        return eff, best, info
    info["value"] = float(cur_eff.parameters()[key])
    return cur_eff, cur_ev, info


def _bootstrap(run: Runner, eff: Effect, m: float, start: Evaluation,
               refit: Callable[[Observation], Effect | None],
               evaluate: Callable[[Effect, Evaluation], Evaluation],
               info: dict[str, Any]) -> tuple[Effect, Evaluation]:
    """The steps of :meth:`debias` from ``start`` (the evaluation at the moment
    estimate): ``refit`` of each simulation gives a value, their median ``f(v)`` (a mean
    follows one seed's wild refit), ``evaluate`` the evaluation at the next value; returns
    the last value and its evaluation."""
    key = eff.primary
    cur_eff, cur_ev = eff, start
    for _ in range(DEBIAS_STEPS):
        v = float(cur_eff.parameters()[key])
        again = [float(e.parameters()[key]) for e in map(refit, cur_ev.sims)
                 if e is not None and float(e.parameters()[key]) > 0]
        drop_derived(cur_ev.sims)
        if len(again) < max(2, len(cur_ev.sims) // 2):
            info["note"] = "the fitter did not find the effect in its own simulations"
            break
        f_v = float(np.median(again))
        factor = float(np.clip(m / f_v, 0.25, 4.0))
        info["steps"].append({"value": v, "refits": again, "factor": round(factor, 4)})
        if abs(np.log(factor)) < 0.05:
            break
        try:
            nxt = cur_eff.with_params(**{key: _cast(eff, key, v * factor)})
        except ValueError:  # outside the parameter's range
            info["note"] = "the corrected value is outside the parameter's range"
            break
        cur_ev = evaluate(nxt, cur_ev)
        cur_eff = nxt
    return cur_eff, cur_ev


def _debias_on_band(run: Runner, current: Evaluation, best: Evaluation, eff: Effect,
                    info: dict[str, Any]) -> tuple[Effect, Evaluation, dict[str, Any]]:
    """:meth:`debias` with its bootstrap on the band of rows: the moment ``m`` is the
    band's measurement's, each ``f(v)`` the fitter's on the band's rows of simulations
    at ``v`` (``best``'s own cut to the band first, then the band's simulations on every
    seed), both against ``current``'s simulations cut to the band. Only a corrected value
    not clearly worse on the band is evaluated on the whole sensor."""
    band = run.band
    assert band is not None
    key = eff.primary
    cur_band = [rows_of(o, band.rows) for o in current.sims]
    model_band = band.model(current.model)

    def refit(sim: Observation) -> Effect | None:
        return fit_candidate(eff.name, sim, cur_band, model_band, band.rec)

    def evaluate(nxt: Effect, _at: Evaluation) -> Evaluation:
        ev = run.screen_on_band(run.near_model(current.model, best.model, nxt), None,
                                  len(run.seeds))
        info["steps"][-1]["gap_next_band"] = float(ev.gap)
        return ev

    m_fit = refit(run.meas_band)
    if m_fit is None or float(m_fit.parameters()[key]) <= 0:
        info["note"] = "the fitter does not see the effect on the band of rows"
        return eff, best, info
    m = float(m_fit.parameters()[key])
    info["moment_band"] = m
    at_m = Evaluation(best.model, [rows_of(o, band.rows) for o in best.sims], best.disc)
    best_band = discrepancy(run.meas_stats_band, [summarise(o) for o in at_m.sims]).gap
    cur_eff, band_ev = _bootstrap(run, eff, m, at_m, refit, evaluate, info)
    if cur_eff is eff:
        return eff, best, info
    info["gap_band"] = {"moment": best_band, "corrected": float(band_ev.gap)}
    if band_ev.gap > best_band + max(0.3, 0.1 * best_band):
        info["note"] = "the corrected value explains the band of rows worse"
        return eff, best, info
    ev = run.evaluate(run.near_model(current.model, best.model, cur_eff),
                       f"debias {eff.name}")
    if ev.gap > best.gap + max(0.3, 0.1 * best.gap):
        return eff, best, info
    info["value"] = float(cur_eff.parameters()[key])
    return cur_eff, ev, info


def finish(run: Runner, current: Evaluation, ev: Evaluation, eff: Effect,
           tried: dict[str, dict[str, Any]]) -> tuple[Effect, Evaluation]:
    """A named candidate's estimate bias-corrected and refined (as configured)."""
    if run.cfg.debias:
        eff, ev, info = debias(run, current, ev, eff)
        tried[eff.name]["debias"] = info
        if info["steps"] and abs(np.log(info["steps"][0]["factor"])) < 0.05:
            # the fitter gives back its own value on the model's simulations: the
            # estimate is consistent, and a search of the gap would trade it against
            # what the model misses elsewhere (interpolated frames)
            return eff, ev
    if run.cfg.refine:
        eff, ev = refine(run, current.model, ev, eff)
    return eff, ev


def refine(run: Runner, current: Model, best: Evaluation, eff: Effect) -> tuple[Effect, Evaluation]:
    key = eff.primary
    v0 = float(eff.parameters()[key])
    if v0 <= 0:
        return eff, best
    factors = (0.7, 1.0, 1 / 0.7)
    points: list[Effect] = []
    for f in factors:
        try:
            points.append(eff if f == 1.0 else
                          eff.with_params(**{key: _cast(eff, key, v0 * f)}))
        except ValueError:  # outside the parameter's range (e.g. sigma above 1)
            return eff, best  # no three-point search: the moment estimate stands
    # screened (one seed, ``best``'s spread; side by side): only a winner is confirmed.
    # On the band (the busiest rows) screenings are compared with each other, not with
    # ``best``'s gap on the whole sensor: the centre is screened too
    todo = [e for f, e in zip(factors, points, strict=True)
            if f != 1.0 or run.band is not None]
    with ThreadPoolExecutor(max_workers=max(1, min(run.workers, len(todo)))) as pool:
        screened = dict(zip(map(id, todo), pool.map(
            lambda e: run.evaluate(run.near_model(current, best.model, e),
                                    f"refine {eff.name}", spread=best), todo),
            strict=True))
    gaps = []
    evals = []
    for f, e in zip(factors, points, strict=True):
        ev = screened.get(id(e), best)
        gaps.append(ev.gap)
        evals.append((e, best if f == 1.0 else ev))
    y = np.asarray(gaps)
    x = np.log(np.asarray(factors))
    den = y[0] - 2 * y[1] + y[2]
    if den > 0:
        xv = float(np.clip(x[1] + 0.5 * (x[1] - x[0]) * (y[0] - y[2]) / den, x[0], x[2]))
        if abs(xv) > 0.05 and int(np.argmin(y)) != 0 and int(np.argmin(y)) != 2:
            e = eff.with_params(**{key: _cast(eff, key, v0 * np.exp(xv))})
            ev = run.evaluate(run.near_model(current, best.model, e), f"refine {eff.name}",
                               spread=best)
            gaps.append(ev.gap)
            evals.append((e, ev))
    i = int(np.argmin(gaps))
    # keep the moment estimate unless the search clearly beats it (the gap is noisy),
    # screened and then on every seed
    margin = max(0.3, 0.1 * best.gap)
    if gaps[i] < gaps[1] - max(0.3, 0.1 * gaps[1]) and evals[i][1] is not best:
        e, ev = evals[i]
        ev = run.confirm(ev, f"confirm refined {eff.name}")
        if ev.gap < best.gap - margin:
            return e, ev
    return eff, best


def _cast(eff: Effect, key: str, value: float) -> Any:
    old = eff.parameters()[key]
    if isinstance(old, int) and not isinstance(old, bool):
        return max(1, int(round(value)))
    return round(float(value), 6)
