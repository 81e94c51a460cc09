"""How the gap workflow's base model anchors its maps, against the truth (issue 38).

A research probe, not a method: figures for docs/notes/gap-anchor-2026-11-30.md.

The base model's ``c`` and ``b`` are OffEI's at the nominal log offset, shrunk towards the
population and spread again (:func:`evcal.gap.model.fit_base`), then anchored
(:func:`evcal.gap.model.anchor`): per bin of measured activity, ``c`` scaled until a
simulation's per-pixel block fits have the measured median. Per dev recording of the gap
benchmark (test recordings are refused) it prints:

- per activity bin (the anchor's six, quietest first): the factor the anchor applied to
  ``c`` (anchored over base), and the anchored ``c`` over the true ``c`` (medians over the
  bin's pixels that the measurement fits), and for the pixels the measurement does not fit
  (quiet ones, whose thresholds the anchor sets by their counts, and the others);
- per bin, a simulation's median block fit over the measured one with the true maps, the
  base maps and the anchored maps (1 where the model reproduces the measured fits);
- the same-pixel intervals below 0.1-5 ms of the measurement and of simulations with the
  true maps, the base maps and the anchored ones (busiest 1 % of pixels left out, as the
  refractory fitter does), scaled to the measured number of intervals.

    python scripts/probe_anchor.py --data /work/gapbench --only dev1025,dev1022   # ~1 min each
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from evcal.gap import model as gm
from evcal.gap.runner import Evaluator, GapConfig
from evcal.gap.stats import Observation, _iei, block_fit, observe
from evcal.io import open_recording

sys.path.insert(0, str(Path(__file__).parent))
import gap_benchmark as gb  # noqa: E402  (the benchmark's truth models, beside this script)

GRID_US = np.array([100, 200, 300, 500, 700, 1000, 1500, 2000, 3000, 5000])
N_BINS = 6  # the anchor's default


def _ratio(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    return float(np.median(a[m]) / np.median(b[m])) if m.sum() >= 10 else float("nan")


def _short_intervals(obs: Observation, keep: np.ndarray, n_ref: int | None
                     ) -> tuple[np.ndarray, int]:
    iei, _, pix = _iei(obs)
    iei = np.sort(iei[keep[pix]])
    n = np.searchsorted(iei, GRID_US).astype(np.float64)
    if n_ref is not None and iei.size:
        n *= n_ref / iei.size
    return n, int(iei.size)


def probe(npz: Path, case: dict[str, Any]) -> None:
    rec = open_recording(npz)
    ev = Evaluator(rec, GapConfig(), tick=lambda _s: None)
    truth = gb.truth_model(npz, case["truth"], backend=case["backend"],
                           illumination=case["illumination"])
    base = gm.fit_base(rec)
    anchored = ev.evaluate(base, "base").model
    meas = ev.meas_obs
    fm = block_fit(meas)
    ok = fm["ok"]
    bins = gm._bins(meas, ok, N_BINS)
    quiet = gm._quiet(meas)
    other = ~ok & ~quiet
    tc, c0, c1 = (m.contrast.ravel() for m in (truth, base, anchored))
    hidden = ",".join(case["truth"]["hidden"]) or "-"
    print(f"{case['id']} {case['backend']} hidden {hidden}: {rec.n_events} events")
    rows = [("anchor factor", c1, c0), ("anchored / true c", c1, tc)]
    for label, a, b in rows:
        cells = [_ratio(a, b, ok & (bins == j)) for j in range(N_BINS)]
        print(f"  {label:24s} " + " ".join(f"{x:5.2f}" for x in cells) +
              f" | quiet {_ratio(a, b, quiet):.2f} other {_ratio(a, b, other):.2f}")
    count = np.bincount(meas.pix, minlength=meas.n_pixels)
    keep = count <= np.quantile(count, 0.99)
    n_meas, n_ref = _short_intervals(meas, keep, None)
    lines = [f"  {'intervals below (us)':24s} " + " ".join(f"{g:>7d}" for g in GRID_US),
             f"  {'measured':24s} " + " ".join(f"{x:7.0f}" for x in n_meas) + f"  N {n_ref}"]
    models = {"true maps": dataclasses.replace(base, contrast=truth.contrast,
                                               bias=truth.bias),
              "base maps": base, "anchored maps": anchored}
    for name, model in models.items():
        obs = observe(gm.simulate_model(model, rec, 0, ev.settings, None), trusted=ev.trusted)
        fs = block_fit(obs)
        both = ok & fs["ok"]
        cells = [_ratio(fs["c"], fm["c"], both & (bins == j)) for j in range(N_BINS)]
        print(f"  fit sim/meas, {name:13s}" + " ".join(f"{x:5.2f}" for x in cells))
        n, n_sim = _short_intervals(obs, keep, n_ref)
        lines.append(f"  {name:24s} " + " ".join(f"{x:7.0f}" for x in n) + f"  N {n_sim}")
    print("\n".join(lines), flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="the gap benchmark's directory")
    p.add_argument("--only", required=True, help="dev case ids, comma-separated")
    args = p.parse_args()
    data = Path(args.data)
    man = {c["id"]: c for c in json.loads((data / "manifest.json").read_text())["cases"]}
    for cid in args.only.split(","):
        if not cid.startswith("dev"):
            raise SystemExit(f"{cid}: only the benchmark's dev recordings may be read here")
        probe(data / "dev" / f"{cid}.npz", man[cid])


if __name__ == "__main__":
    main()
