"""The gap workflow's light between frames against the scene's own (issue 38).

A research probe, not a method: figures for docs/notes/gap-light-2026-11-30.md.

For a dev recording of the gap benchmark simulated by evcal (the scene is known; test
recordings are refused, v2e's scenes are not rebuilt here), the sensor's true maps with no
effect are simulated twice over the recording's time base: driven by the scene itself (what
the recording's events saw, less the hidden effects) and by the light the gap workflow
renders from the recording's frames (:func:`evcal.gap.model.simulate_model`: flow
interpolation of the deblurred latent frames, the sub-frame shift read from the events).
Printed per recording: the events of the workflow's light over the scene's, and the same-pixel
intervals shorter than 0.3-5 ms of both (only pairs in the windows the workflow trusts for its
timing statistics). Where the workflow's light fires more short intervals than the scene's,
a model with the true maps already shows a deficit that a dead time would explain.

Flickering lights are left out: the flicker is an effect of the workflow's models, not part
of its light.

    python scripts/probe_light.py --data /work/gapbench --only dev1025,dev1033 [--results F]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from evcal.gap import model as gm
from evcal.gap.runner import Evaluator, GapConfig
from evcal.gap.stats import _iei, observe
from evcal.io import open_recording
from evcal.recording import Recording
from evcal.sim.ideal import SimConfig
from evcal.sim.nonideal import simulate

sys.path.insert(0, str(Path(__file__).parent))
import gap_benchmark as gb  # noqa: E402  (the benchmark's truth models, beside this script)
import gapbench_scene as gs  # noqa: E402  (its scenes)

GRID_US = np.array([300, 500, 1000, 2000, 5000])


def short_intervals(rec: Recording, trusted: np.ndarray | None) -> np.ndarray:
    iei = np.sort(_iei(observe(rec, trusted=trusted))[0])
    return np.searchsorted(iei, GRID_US)


def probe(npz: Path, case: dict[str, Any]) -> dict[str, Any]:
    rec = open_recording(npz)
    fr = rec.frames
    assert fr is not None
    ev = Evaluator(rec, GapConfig(), tick=lambda _s: None)
    # the true maps and log offset, no effect (a flicker is left out by the caller)
    truth = gb.truth_model(npz, case["truth"], effects=False, backend="sim")
    times = gm._times(fr, case["input_rate_hz"])
    h, w = rec.sensor.shape
    cfg = SimConfig(height=h, width=w, duration_s=times[-1] * 1e-6, frame_rate_hz=1.0,
                    internal_rate_hz=case["input_rate_hz"], log_offset=float(truth.log_offset),
                    seed=3)
    scene = simulate(cfg, {}, source=gs.build_scene(case), maps=(truth.contrast, truth.bias),
                     frames=fr, times_us=times, t_origin_us=int(fr.t_us[0])).recording
    workflow = gm.simulate_model(truth, rec, 0, ev.settings, None)
    n_s, n_w = short_intervals(scene, ev.trusted), short_intervals(workflow, ev.trusted)
    return {"id": case["id"], "events_scene": int(scene.n_events),
            "events_workflow": int(workflow.n_events), "grid_us": GRID_US.tolist(),
            "short_scene": n_s.tolist(), "short_workflow": n_w.tolist()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="the gap benchmark's directory")
    p.add_argument("--only", required=True, help="dev case ids, comma-separated")
    p.add_argument("--results", help="append one JSON line per recording here")
    args = p.parse_args()
    data = Path(args.data)
    man = {c["id"]: c for c in json.loads((data / "manifest.json").read_text())["cases"]}
    print("recording  events wf/scene | intervals below " +
          " ".join(f"{g:>6d}" for g in GRID_US) + " us: scene, wf/scene")
    for cid in args.only.split(","):
        if not cid.startswith("dev"):
            raise SystemExit(f"{cid}: only the benchmark's dev recordings may be read here")
        if cid not in man:
            raise SystemExit(f"{cid}: not in {data / 'manifest.json'}")
        case = man[cid]
        if case["backend"] != "sim" or case["illumination"]["kind"] == "flicker":
            print(f"{cid}: skipped ({case['backend']}, {case['illumination']['kind']} light)")
            continue
        r = probe(data / "dev" / f"{cid}.npz", case)
        ratio = [a / b if b else float("nan") for a, b in
                 zip(r["short_workflow"], r["short_scene"], strict=True)]
        print(f"{cid}  {r['events_workflow'] / r['events_scene']:5.2f}           | " +
              " ".join(f"{x:>6d}" for x in r["short_scene"]) + "  " +
              " ".join(f"{x:5.2f}" for x in ratio), flush=True)
        if args.results:
            with open(args.results, "a") as f:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
