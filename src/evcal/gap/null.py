"""The null calibration: what each candidate shows when nothing is missing.

The current model's own simulations lack every candidate effect. Each of them, taken in
turn as a pseudo-measurement against the others (leave one out), is given to every fitter:
the strength (:attr:`~.effects.EffectSpec.strength`) a fitter reads there is what the noise of
the comparison and the fitter's own bias make of nothing. A candidate's fitted value on the
measurement must exceed ``null_factor`` times the largest of those to be evaluated at all.

On the first pseudo-measurement, each effect its fitter reads anything into is also
simulated (anchored to the pseudo-measurement, as a candidate is to the measurement) and
its gain counted on the held-out rows, as the round counts a candidate's: the gain an effect
shows with nothing missing, its free parameters and per-pixel maps included. A candidate is
named only when its gain exceeds that by the gain the workflow asks for
(:func:`.runner.need`).

Both are measured once, on the base model: what they measure is the fitters' and the
comparison's noise on recordings of this size and activity, which the effects named later
change little.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from ..sim.effects import Effect
from . import effects as registry
from .compare import discrepancy
from .effects import FitContext, FitResult, Fitted, NoEvidence
from .model import anchor, simulate_model
from .runner import Evaluation, Evaluator, gain, longest_first
from .stats import Observation, StatValue, observe, summarise

_log = logging.getLogger("evcal.gap")

NULL_SEED_OFFSET = 500  # null simulations' seeds: the run's seed * 1000 + this + k


@dataclass
class NullCalibration:
    """Per effect: the strengths its fitter read on each pseudo-measurement (0 where it saw
    nothing), and the held-out gain of the effect fitted on the first one (measured when
    first asked for: only a candidate about to be named needs it; 0 when its fitter saw
    nothing there)."""

    strengths: dict[str, list[float]] = field(default_factory=dict)
    gains: dict[str, float] = field(default_factory=dict)
    reasons: dict[str, list[str]] = field(default_factory=dict)
    simulations: int = 0
    # what the gains are measured with: the effects fitted on the first pseudo-measurement,
    # the base model, that simulation and the held-out statistics of it and of the others
    fitted: dict[str, Effect] = field(default_factory=dict)
    base: Evaluation | None = None
    pseudo: Observation | None = None
    pseudo_held: dict[str, StatValue] = field(default_factory=dict)
    others_held: list[dict[str, StatValue]] = field(default_factory=list)

    def limit(self, name: str, factor: float) -> float:
        """The strength a measured fit must exceed (``factor`` times the largest null one;
        0 when the fitter saw nothing in any pseudo-measurement)."""
        return factor * max(self.strengths.get(name, [0.0]) or [0.0])

    def gain(self, ev: Evaluator, name: str) -> float:
        """The held-out gain of ``name`` with nothing missing (at least 0), measured now
        when it was not yet."""
        if name not in self.gains:
            self.gains[name] = self._measure(ev, name)
        return max(self.gains[name], 0.0)

    def _measure(self, ev: Evaluator, name: str) -> float:
        eff = self.fitted.get(name)
        if eff is None or self.base is None or self.pseudo is None or \
                registry.spec(name).kind == "scheme" or name == "log_offset":
            # nothing fitted on the pseudo-measurement: no gain. The log offset's candidate
            # refits the base maps on the measured recording itself: its null is the
            # fitter's (an offset at the nominal one)
            return 0.0
        base = discrepancy(self.pseudo_held, self.others_held)
        model, _ = anchor(self.base.model.with_effect(eff), ev.rec, self.pseudo,
                          ev.seeds[0], ev.settings, render=ev.render, trusted=ev.trusted)
        seed = ev.cfg.seed * 1000 + NULL_SEED_OFFSET + len(self.gains)
        obs = observe(simulate_model(model, ev.rec, seed, ev.settings, ev.render),
                      trusted=ev.trusted)
        self.simulations += 1
        held = discrepancy(self.pseudo_held, [summarise(ev.whole.held_of(obs))],
                           spread=base)
        g = float(gain(base.gap, held.gap + ev.cfg.penalty_per_parameter * eff.n_fitted))
        _log.info("null gain of %s: %.3g (held-out gap %.3g -> %.3g)", name, g, base.gap,
                  held.gap)
        return g

    def to_json(self) -> dict[str, Any]:
        return {name: {"strengths": [float(x) for x in self.strengths[name]],
                       **({"gain": float(self.gains[name])} if name in self.gains else {})}
                for name in self.strengths}


def calibrate(ev: Evaluator, current: Evaluation, names: list[str], *,
              pseudo_measurements: int = 1) -> NullCalibration:
    """The null calibration of the candidates ``names`` on ``current`` (an evaluation on
    every seed, whole sensor): see the module docstring. ``pseudo_measurements`` of its
    simulations are taken in turn (each fitter's work again for each)."""
    sims = current.sims
    k_all = len(sims)
    out = NullCalibration()
    if k_all < 3 or len(current.held_summaries) != k_all:
        _log.info("null calibration skipped: %d simulations", k_all)
        return out
    names = [n for n in names if registry.spec(n).kind != "scheme"]
    for k in range(min(pseudo_measurements, k_all)):
        pseudo = sims[k]
        others = sims[:k] + sims[k + 1:]
        ctxs = {held: ev.fit_context(current.model, others, held_out=held, meas=pseudo)
                for held in (True, False)}

        def fit(name: str, ctxs: dict[bool, FitContext] = ctxs) -> FitResult:
            spec = registry.spec(name)
            return spec.fit(ctxs[spec.held_out])

        with ThreadPoolExecutor(max_workers=ev.workers) as pool:
            order = longest_first(names, {})
            results = dict(zip(order, pool.map(fit, order), strict=True))
        for name in names:
            res = results[name]
            strength = 0.0
            if isinstance(res, Fitted):
                strength = float(registry.spec(name).strength(res.effect, ev.light_dn))
                if k == 0:
                    out.fitted[name] = res.effect
            else:
                assert isinstance(res, NoEvidence)
                out.reasons.setdefault(name, []).append(res.reason)
            out.strengths.setdefault(name, []).append(strength)
        for o in [pseudo, *others]:
            o.extra.clear()
    out.base = current.lightened()
    out.pseudo = sims[0]
    out.pseudo_held = current.held_summaries[0]
    out.others_held = list(current.held_summaries[1:])
    _log.info("null calibration: strengths %s",
              {n: [round(x, 4) for x in v] for n, v in out.strengths.items()})
    return out
