"""What the model still does not explain, in words a sensor engineer reads.

:func:`unexplained` takes a :class:`~.compare.Discrepancy` (usually the final model's) and
returns, for each statistic whose discrepancy is significant, its worst component as a
sentence: which statistic, in which regime (the component's label: an intensity bin, an
interval range, a time bin), in which direction and by how much, e.g.

    still pixels (static, I (DN) 12.5..31) fire 3.1x fewer events than the model
    (0.41 vs 1.27 per pixel-second, z = -8.2)

Ratios are given where a quantity is a positive amount (rates, counts, shares); signed
quantities (a mean residual, a polarity balance) are given as differences.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .compare import Discrepancy


@dataclass(frozen=True)
class _Words:
    subject: str  # what is measured, as the subject of the sentence
    unit: str  # of the values ("" when they are plain numbers)
    ratio: bool  # a positive amount: said as "Nx more / fewer"; else as a difference
    more: str = "higher"
    less: str = "lower"
    verb: str = "is"


# per statistic: how its components are said (statistics not listed get a generic wording)
WORDS: dict[str, _Words] = {
    "iei_distribution": _Words("the share of a pixel's inter-event intervals", "", True,
                               "larger", "smaller"),
    "iei_lower_edge": _Words("the shortest inter-event intervals (log10 us)", "", False,
                             "longer", "shorter"),
    "static_rate_vs_intensity": _Words("still pixels", "events per pixel-second", True,
                                       "more events", "fewer events", "fire"),
    "static_balance_vs_intensity": _Words("the ON minus OFF rate of still pixels",
                                          "events per pixel-second", False, "more ON",
                                          "more OFF"),
    "on_fraction_over_time": _Words("the share of ON events", "", True, "larger",
                                    "smaller"),
    "offei_residual_vs_dl": _Words("the per-pixel fit's RMS residual", "log units", True,
                                   "larger", "smaller"),
    "offei_residual_vs_intensity": _Words(
        "the fit's residual along the change (events explain the frames' change by "
        "less when positive)", "log units", False, "more positive", "more negative"),
    "offei_residual_vs_time": _Words("the per-pixel fit's RMS residual", "log units", True,
                                     "larger", "smaller"),
    "fit_population": _Words("the fitted thresholds", "", True, "larger", "smaller"),
    "estimate_stability": _Words("the change of a pixel's fit between the two halves", "",
                                 True, "larger", "smaller"),
    "polarity_alternation": _Words("the share of consecutive events of opposite polarity",
                                   "", True, "larger", "smaller"),
    "rate_tail": _Words("the still-pixel rate (log10(1 + Hz))", "", False, "higher",
                        "lower"),
    "speed_response": _Words("events per unit of log change", "", True, "more", "fewer"),
    "lag_vs_intensity": _Words("the weight of the previous window's change in a window's "
                               "events (lag)", "", False, "larger", "smaller"),
    "sensitivity_vs_intensity": _Words("pixels", "events per unit of log change", True,
                                       "more events per unit of log change",
                                       "fewer events per unit of log change", "fire"),
    "line_coincidence": _Words("still pixels' events that other pixels of their row or "
                               "column share within 20 us", "per pixel-second", True,
                               "more", "fewer", "are"),
    "timestamp_quantum": _Words("the share of timestamps on the grid", "", True, "larger",
                                "smaller"),
}

MIN_DISCREPANCY = 2.0  # a statistic's D (mean z^2) below this is within the model's noise


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def sentence(stat: str, label: str, measured: float, simulated: float, z: float) -> str:
    """One component's disagreement in words (see the module docstring)."""
    w = WORDS.get(stat, _Words(stat, "", False))
    unit = f" {w.unit}" if w.unit else ""
    where = f" ({label})" if label else ""
    if w.ratio and measured >= 0 and simulated >= 0 and max(measured, simulated) > 0:
        if min(measured, simulated) <= 0:
            how = "much " + (w.more if measured > simulated else w.less)
        else:
            r = measured / simulated
            how = f"{r:.2g}x {w.more}" if r >= 1 else f"{1 / r:.2g}x {w.less}"
        return (f"{w.subject}{where} {w.verb} {how} than the model "
                f"({_fmt(measured)} vs {_fmt(simulated)}{unit}, z = {z:+.1f})")
    d = measured - simulated
    how = w.more if d > 0 else w.less
    return (f"{w.subject}{where} {w.verb} {how} than the model by {_fmt(abs(d))}{unit} "
            f"({_fmt(measured)} vs {_fmt(simulated)}, z = {z:+.1f})")


def unexplained(disc: Discrepancy, *, top: int = 6, min_discrepancy: float = MIN_DISCREPANCY
                ) -> list[dict[str, Any]]:
    """The statistics the model does not explain (``D >= min_discrepancy``), largest first
    (at most ``top``), each with its worst component: ``statistic``, ``discrepancy`` (D),
    ``component`` (label), ``measured``, ``simulated``, ``z`` and ``sentence``."""
    out: list[dict[str, Any]] = []
    for name, d in sorted(disc.per_stat.items(), key=lambda kv: -kv[1]):
        if d < min_discrepancy or len(out) >= top:
            break
        z = np.asarray(disc.z[name], np.float64)
        k = int(np.argmax(np.abs(z)))
        m = float(np.asarray(disc.measured[name]).ravel()[k])
        s = float(np.asarray(disc.sim_mean[name]).ravel()[k])
        label = disc.labels[name][k] if k < len(disc.labels[name]) else ""
        out.append({"statistic": name, "discrepancy": float(d), "component": label,
                    "measured": m, "simulated": s, "z": float(z[k]),
                    "sentence": sentence(name, label, m, s, float(z[k]))})
    return out


def summary(disc: Discrepancy, **kw: Any) -> list[str]:
    """:func:`unexplained` as lines of text; one line saying so when nothing is left."""
    items = unexplained(disc, **kw)
    if not items:
        return [f"nothing significant: every statistic within the model's noise "
                f"(D < {kw.get('min_discrepancy', MIN_DISCREPANCY):g})"]
    return [f"{it['statistic']} (D = {it['discrepancy']:.1f}): {it['sentence']}"
            for it in items]
