"""The model-gap workflow on the v2e recordings (tests/data/v2e): what it names, with which
parameters, and the gap before and after, per recording.

    python scripts/v2e_data/gap_table.py [NAME ...]     # default: every recording

NAME is a file stem such as none_camera. Prints one line per recording (about a minute each
on one core of the development machine).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from evcal.gap.workflow import GapConfig, run_gap
from evcal.io import open_recording

DATA = Path(__file__).resolve().parents[2] / "tests" / "data" / "v2e"


def _step(s: dict) -> str:
    params = ", ".join(f"{k}={v}" for k, v in s["parameters"].items())
    return f"{s['effect']}({params}) -> {s['gap_after']:.1f}"


def main(names: list[str]) -> None:
    names = names or sorted(p.stem for p in DATA.glob("*.npz"))
    for name in names:
        rec = open_recording(DATA / f"{name}.npz")
        t0 = time.perf_counter()
        res = run_gap(rec, GapConfig(max_effects=3, n_seeds=3, seed=1))
        j = res.to_json()
        steps = "; ".join(_step(s) for s in j["steps"]) or "nothing named"
        print(f"{name:24s} {time.perf_counter() - t0:5.0f} s  gap {j['gap_initial']:7.1f} -> "
              f"{j['gap_final']:6.1f}  {steps}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
