"""The model-gap workflow on the v2e recordings (tests/data/v2e): what it names, with which
parameters, the gap before and after, and each named sensor effect's main parameter against
v2e's, per recording.

    python scripts/v2e_data/gap_table.py [NAME ...]     # default: every recording

NAME is a file stem such as none_camera. Prints one line per recording (20-60 s each on one
core of the development machine), then a line per named sensor effect that v2e's case has.

v2e's values in evcal's terms (scripts/v2e_data/README.md has v2e's formulas):

- ``leak``: the mean of the recording's ``truth_leak_rate_hz`` map;
- ``refractory``: ``refractory_period_s`` in us;
- ``bandwidth``: evcal's cutoff is ``cutoff_hz (I + dark) / 128 DN``, v2e's
  ``cutoff_hz (I + 20) / 275``: at 128 DN (and evcal's nominal dark level of 1 DN) the same
  filter has evcal ``cutoff_hz = v2e cutoff_hz * 148 / 275``;
- ``shot_noise``: v2e's nominal ``shot_noise_rate_hz`` (its rate at inten01 = 0, i.e.
  -20 DN) beside the ratio of the fitted law's mean rate over the still windows' pixels to
  v2e's law there (``(rate / 2) ((0.25 - 1) inten01 + 1) 0.2 / threshold`` per sign,
  ``inten01 = (I + 20) / 275``): the fitted ``rate_hz`` is quoted at 16 DN, below every
  pixel of these scenes (25-235 DN), an extrapolation along the fitted exponent of a law
  that is not v2e's.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from evcal.gap.stats import _static, observe
from evcal.gap.workflow import GapConfig, GapResult, run_gap
from evcal.io import open_recording
from evcal.sim.effects import Effect, ShotNoise

DATA = Path(__file__).resolve().parents[2] / "tests" / "data" / "v2e"
V2E_REF_DN = 275.0  # v2e's inten01 = (I + 20) / 275 (emulator_utils.py:48-54)
V2E_DARK_DN = 20.0
SHOT_NOISE_INTEN_FACTOR = 0.25  # v2e emulator.py:210


def _step(s: dict[str, Any]) -> str:
    params = ", ".join(f"{k}={v}" for k, v in s["parameters"].items())
    r = s.get("refit")
    refit = "" if r is None or r["named_value"] == s["parameters"][r["parameter"]] else \
        f" [named at {r['parameter']}={r['named_value']}; refitted: {r['gap_before']:.1f} " \
        f"-> {r['gap_after']:.1f}]"
    return f"{s['effect']}({params}) -> {s['gap_after']:.1f}{refit}"


def _shot_ratio(rec: Any, z: Any, eff: ShotNoise) -> float:
    """Mean rate of ``eff`` over the still windows' pixels / v2e's law's there."""
    obs = observe(rec)
    st = _static(obs)
    i_mid = (0.5 * (obs.intensity[1:] + obs.intensity[:-1]))[st].astype(np.float64)
    w = np.broadcast_to(obs.window_s[:, None], st.shape)[st]
    pix = np.broadcast_to(np.arange(st.shape[1])[None, :], st.shape)[st]
    on = (z["truth_contrast"] + z["truth_bias"]).ravel()[pix].astype(np.float64)
    off = (z["truth_contrast"] - z["truth_bias"]).ravel()[pix].astype(np.float64)
    rate = float(z["__shot_rate_hz"])
    inten01 = (i_mid + V2E_DARK_DN) / V2E_REF_DN
    v2e = 0.5 * rate * ((SHOT_NOISE_INTEN_FACTOR - 1) * inten01 + 1) * (0.2 / on + 0.2 / off)
    return float(np.average(eff.rate_at(i_mid), weights=w) / np.average(v2e, weights=w))


def truth_lines(name: str, rec: Any, res: GapResult, params: dict[str, Any]) -> list[str]:
    """One line per named sensor effect that v2e's case has: fitted against v2e's value."""
    out = []
    with np.load(DATA / f"{name}.npz") as npz:
        z = dict(npz)
    z["__shot_rate_hz"] = params["shot_noise_rate_hz"]
    for s in res.steps:
        e: Effect = s.effect
        v = float(e.parameters()[e.primary])
        if e.name == "leak" and params["leak_rate_hz"] > 0:
            t = float(np.mean(z["truth_leak_rate_hz"]))
            out.append(f"leak rate {v:.3f} Hz, v2e {t:.3f} Hz ({v / t - 1:+.0%})")
        elif e.name == "refractory" and params["refractory_period_s"] > 0:
            t = params["refractory_period_s"] * 1e6
            out.append(f"refractory {v:.0f} us ({e.parameters()['mode']}), v2e {t:.0f} us "
                       f"({v / t - 1:+.0%})")
        elif e.name == "bandwidth" and params["cutoff_hz"] > 0:
            t = params["cutoff_hz"] * (128.0 + V2E_DARK_DN) / V2E_REF_DN
            out.append(f"bandwidth {v:.2f} Hz at 128 DN, v2e {t:.2f} Hz ({v / t - 1:+.0%})")
        elif isinstance(e, ShotNoise) and params["shot_noise_rate_hz"] > 0:
            t = params["shot_noise_rate_hz"]
            out.append(f"shot noise {v:.3f} Hz at {e.ref_dn:g} DN (v2e nominal {t:g} Hz: "
                       f"{v / t - 1:+.0%}); mean rate over the still pixels / v2e's: "
                       f"{_shot_ratio(rec, z, e):.2f}")
    return out


def main(names: list[str]) -> None:
    import json  # noqa: PLC0415

    manifest = json.loads((DATA / "manifest.json").read_text())
    params = {Path(r["file"]).stem: r["params"] for r in manifest["recordings"]}
    names = names or sorted(p.stem for p in DATA.glob("*.npz"))
    for name in names:
        rec = open_recording(DATA / f"{name}.npz")
        t0 = time.perf_counter()
        res = run_gap(rec, GapConfig(max_effects=3, n_seeds=3, seed=1))
        j = res.to_json()
        steps = "; ".join(_step(s) for s in j["steps"]) or "nothing named"
        print(f"{name:24s} {time.perf_counter() - t0:5.0f} s  gap {j['gap_initial']:7.1f} -> "
              f"{j['gap_final']:6.1f}  {steps}", flush=True)
        for line in truth_lines(name, rec, res, params[name]):
            print(f"{'':26s}{line}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
