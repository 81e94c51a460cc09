"""What a named effect's estimate goes through before it is named: its moment estimate
bias-corrected by simulation (a parametric bootstrap, on the band of rows first when the run
screens on one) and, unless that confirms it, refined by a three-point search of the gap."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ..sim.effects import Effect
from . import effects as registry
from .compare import discrepancy
from .effects import FitContext, Fitted
from .model import Model
from .runner import Evaluation, Evaluator, drop_derived, model_on_rows
from .stats import Observation, rows_of, summarise

DEBIAS_STEPS = 2  # bootstrap steps per named effect (an evaluation each)


def refit(ev: Evaluator, eff: Effect, sim: Observation, on: Evaluation) -> Effect | None:
    """``eff``'s fitter on ``sim`` (a simulation made with it, in place of the measurement)
    against ``on``'s simulations, on every row."""
    res = registry.spec(eff.name).fit(ev.fit_context(on.model, on.sims, held_out=False,
                                                     meas=sim))
    return res.effect if isinstance(res, Fitted) else None


def debias(ev: Evaluator, on: Evaluation, best: Evaluation, eff: Effect, moment: float
           ) -> tuple[Effect, Evaluation, dict[str, Any]]:
    """The moment estimate's own bias, removed by simulation (a parametric bootstrap):
    the fitter applied to the simulations made *with* the effect at ``v`` (in place of
    the measurement, against the same effect-free simulations of ``on``) returns
    ``f(v)``; where ``f(v) != v`` the estimator is biased on data like these (leak's excess
    of ON events in still windows misses the drift a pixel pays off before the pause ends:
    at 25 Hz with short pauses ``f(v)`` is ~0.4 v). The value whose simulations give the
    measured ``moment`` ``m`` (the fitter's on every row) solves ``f(v) = m``:
    ``v <- v m / f(v)``, up to ``DEBIAS_STEPS`` times (each step's factor clipped to
    [1/4, 4]) while it moves by more than 5 %. The result is kept when its gap is not
    clearly worse than the moment estimate's (the gap is noisy; the bootstrap is the
    better-founded value)."""
    key = eff.primary
    m = float(moment)
    info: dict[str, Any] = {"moment": m, "value": float(eff.parameters()[key]), "steps": []}
    if m <= 0:
        return eff, best, info
    if ev.band is not None:
        return _debias_on_band(ev, on, best, eff, m, info)

    def evaluate(nxt: Effect, at: Evaluation) -> Evaluation:
        out = ev.evaluate(ev.near_model(on.model, at.model, nxt), f"debias {eff.name}")
        info["steps"][-1]["gap_next"] = float(out.gap)
        return out

    cur_eff, cur_ev = _bootstrap(ev, eff, m, best,
                                 lambda sim: refit(ev, eff, sim, on), evaluate, info)
    drop_derived(on.sims)
    if cur_eff is eff or cur_ev.gap > best.gap + max(0.3, 0.1 * best.gap):
        return eff, best, info
    info["value"] = float(cur_eff.parameters()[key])
    return cur_eff, cur_ev, info


def _bootstrap(ev: Evaluator, eff: Effect, m: float, start: Evaluation,
               refit_one: Callable[[Observation], Effect | None],
               evaluate: Callable[[Effect, Evaluation], Evaluation],
               info: dict[str, Any]) -> tuple[Effect, Evaluation]:
    """The steps of :func:`debias` from ``start`` (the evaluation at the moment
    estimate): ``refit_one`` of each simulation gives a value, their median ``f(v)`` (a
    mean follows one seed's wild refit), ``evaluate`` the evaluation at the next value;
    returns the last value and its evaluation."""
    key = eff.primary
    cur_eff, cur_ev = eff, start
    for _ in range(DEBIAS_STEPS):
        v = float(cur_eff.parameters()[key])
        again = [float(e.parameters()[key]) for e in map(refit_one, cur_ev.sims)
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


def _debias_on_band(ev: Evaluator, on: Evaluation, best: Evaluation, eff: Effect, m: float,
                    info: dict[str, Any]) -> tuple[Effect, Evaluation, dict[str, Any]]:
    """:func:`debias` with its bootstrap on the band of rows: the moment ``m`` is the
    band's measurement's, each ``f(v)`` the fitter's on the band's rows of simulations
    at ``v`` (``best``'s own cut to the band first, then the band's simulations on every
    seed), both against ``on``'s simulations cut to the band. Only a corrected value
    not clearly worse on the band is evaluated on the whole sensor."""
    band, target = ev.band, ev.on_band
    assert band is not None
    assert target is not None
    key = eff.primary
    rows = np.arange(band.rows.start, band.rows.stop)
    on_band = [rows_of(o, band.rows) for o in on.sims]
    model_band = model_on_rows(on.model, rows)
    spec = registry.spec(eff.name)

    def ctx(meas: Observation) -> FitContext:
        return FitContext(meas, on_band, model_band, ev.rec, meas, None, ev.cfg.seed,
                          frame_rows=band.rows)

    def refit_band(sim: Observation) -> Effect | None:
        res = spec.fit(ctx(sim))
        return res.effect if isinstance(res, Fitted) else None

    def evaluate(nxt: Effect, _at: Evaluation) -> Evaluation:
        out = ev.screen_on_band(ev.near_model(on.model, best.model, nxt), None,
                                len(ev.seeds))
        info["steps"][-1]["gap_next_band"] = float(out.gap)
        return out

    m_fit = refit_band(target.obs)
    if m_fit is None or float(m_fit.parameters()[key]) <= 0:
        info["note"] = "the fitter does not see the effect on the band of rows"
        return eff, best, info
    m = float(m_fit.parameters()[key])
    info["moment_band"] = m
    at_m = Evaluation(best.model, [rows_of(o, band.rows) for o in best.sims], best.disc,
                      best.held)
    best_band = discrepancy(target.stats, [summarise(o) for o in at_m.sims]).gap
    cur_eff, band_ev = _bootstrap(ev, eff, m, at_m, refit_band, evaluate, info)
    if cur_eff is eff:
        return eff, best, info
    info["gap_band"] = {"moment": best_band, "corrected": float(band_ev.gap)}
    if band_ev.gap > best_band + max(0.3, 0.1 * best_band):
        info["note"] = "the corrected value explains the band of rows worse"
        return eff, best, info
    out = ev.evaluate(ev.near_model(on.model, best.model, cur_eff), f"debias {eff.name}")
    if out.gap > best.gap + max(0.3, 0.1 * best.gap):
        return eff, best, info
    info["value"] = float(cur_eff.parameters()[key])
    return cur_eff, out, info


def finish(ev: Evaluator, on: Evaluation, best: Evaluation, eff: Effect, moment: float
           ) -> tuple[Effect, Evaluation, dict[str, Any]]:
    """A named candidate's estimate bias-corrected and refined (as configured); what was
    done, for the report."""
    info: dict[str, Any] = {}
    if ev.cfg.debias:
        eff, best, info = debias(ev, on, best, eff, moment)
        if info["steps"] and abs(np.log(info["steps"][0]["factor"])) < 0.05:
            # the fitter gives back its own value on the model's simulations: the
            # estimate is consistent, and a search of the gap would trade it against
            # what the model misses elsewhere (interpolated frames)
            return eff, best, info
    if ev.cfg.refine:
        eff2, best2 = refine(ev, on.model, best, eff)
        if eff2 is not eff:
            info["refined"] = float(eff2.parameters()[eff.primary])
        eff, best = eff2, best2
    return eff, best, info


def refine(ev: Evaluator, current: Model, best: Evaluation, eff: Effect
           ) -> tuple[Effect, Evaluation]:
    """A three-point search of the gap over ``eff``'s primary parameter (0.7x, 1x, 1/0.7x,
    then the parabola's minimum), screened; a point that clearly beats the centre on one
    seed and then on every seed replaces it."""
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
            if f != 1.0 or ev.band is not None]
    with ThreadPoolExecutor(max_workers=max(1, min(ev.workers, len(todo)))) as pool:
        screened = dict(zip(map(id, todo), pool.map(
            lambda e: ev.evaluate(ev.near_model(current, best.model, e),
                                  f"refine {eff.name}", spread=best), todo),
            strict=True))
    gaps = []
    evals = []
    for f, e in zip(factors, points, strict=True):
        out = screened.get(id(e), best)
        gaps.append(out.gap)
        evals.append((e, best if f == 1.0 else out))
    y = np.asarray(gaps)
    x = np.log(np.asarray(factors))
    den = y[0] - 2 * y[1] + y[2]
    if den > 0:
        xv = float(np.clip(x[1] + 0.5 * (x[1] - x[0]) * (y[0] - y[2]) / den, x[0], x[2]))
        if abs(xv) > 0.05 and int(np.argmin(y)) != 0 and int(np.argmin(y)) != 2:
            e = eff.with_params(**{key: _cast(eff, key, v0 * np.exp(xv))})
            out = ev.evaluate(ev.near_model(current, best.model, e), f"refine {eff.name}",
                              spread=best)
            gaps.append(out.gap)
            evals.append((e, out))
    i = int(np.argmin(gaps))
    # keep the moment estimate unless the search clearly beats it (the gap is noisy),
    # screened and then on every seed
    margin = max(0.3, 0.1 * best.gap)
    if gaps[i] < gaps[1] - max(0.3, 0.1 * gaps[1]) and evals[i][1] is not best:
        e, out = evals[i]
        out = ev.confirm(out, f"confirm refined {eff.name}")
        if out.gap < best.gap - margin:
            return e, out
    return eff, best


def _cast(eff: Effect, key: str, value: float) -> Any:
    old = eff.parameters()[key]
    if isinstance(old, int) and not isinstance(old, bool):
        return max(1, int(round(value)))
    return round(float(value), 6)
