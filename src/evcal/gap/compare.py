"""The comparison of a measurement's statistics with its simulations': each component
standardised by the simulations' seed-to-seed spread and floors, a statistic's discrepancy,
and the gap (their mean; about 1 when the model explains the data). The statistics
themselves are :mod:`.stats`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .stats import StatValue

REL_FLOOR = 0.03  # a relative difference below this is never significant


@dataclass
class Discrepancy:
    """Standardised discrepancy of measured statistics against simulated ones.

    Per component ``z = (m - mean_sim) / s`` with
    ``s^2 = var_sim (1 + 1/n) + (REL_FLOOR * |mean_sim|)^2 + floor^2``: the spread over the
    simulation seeds (the measured value is one more draw), plus floors that keep a handful of
    seeds from declaring tiny differences significant. A statistic's discrepancy is ``mean z^2``
    over its components (about 1 when the model explains the data); the gap is the mean of
    those over statistics.
    """

    measured: dict[str, np.ndarray]
    sim_mean: dict[str, np.ndarray]
    sim_std: dict[str, np.ndarray]
    z: dict[str, np.ndarray]
    per_stat: dict[str, float]
    labels: dict[str, list[str]]
    n_sims: int = 0  # the simulations (seeds) the spread is from

    @property
    def gap(self) -> float:
        return float(np.mean(list(self.per_stat.values())))

    def where(self, name: str) -> str:
        z = self.z[name]
        k = int(np.argmax(np.abs(z)))
        return f"{self.labels[name][k]} (z = {z[k]:+.1f})"


def discrepancy(measured: dict[str, StatValue], sims: list[dict[str, StatValue]], *,
                spread: Discrepancy | None = None) -> Discrepancy:
    """The discrepancy of ``measured`` against the simulations ``sims``.

    With one simulation (a candidate screened on one seed) the seed-to-seed variance is
    taken from ``spread``, an evaluation of a neighbouring model on several seeds (the spread
    of a statistic changes little between the models one round compares); the mean of one
    simulation is one draw, so ``1 + 1/n`` is 2 there. Without ``spread`` one simulation has
    no spread (its floors only).

    A component that is NaN (too little data for it) in the measurement or in any simulation
    (or in the spread's) is left out (z = 0); a statistic with none left counts D = 1, what
    a model that explains the data gives, so it neither raises nor dilutes the gap."""
    n = len(sims)
    meas, mean, std, z, per, labels = {}, {}, {}, {}, {}, {}
    for name, mv in measured.items():
        arr = np.stack([s[name].values for s in sims])
        ok = np.isfinite(mv.values) & np.isfinite(arr).all(0)
        with np.errstate(invalid="ignore"):
            mu = arr.mean(0)
            if n > 1:
                var = arr.var(0, ddof=1)
            elif spread is not None:
                var = spread.sim_std[name] ** 2
            else:
                var = np.zeros_like(mu)
            sd = np.sqrt(var * (1 + 1 / n) + (REL_FLOOR * np.abs(mu)) ** 2 + mv.floor ** 2)
            # a screening's component whose spread the neighbouring model could not say
            # (NaN in one of its simulations) is left out too
            ok &= np.isfinite(sd)
            zz = np.where(ok, (mv.values - mu) / np.where(ok, sd, 1.0), 0.0)
        meas[name], mean[name], std[name], z[name] = mv.values, mu, np.sqrt(var), zz
        per[name] = float(np.mean(zz[ok] ** 2)) if ok.any() else 1.0
        labels[name] = mv.labels
    return Discrepancy(meas, mean, std, z, per, labels, n)
