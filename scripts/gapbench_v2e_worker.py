#!/usr/bin/env python3
"""Write one v2e recording of the gap benchmark (run with the v2e venv's python).

``scripts/gap_benchmark.py generate`` starts this worker for every case whose backend is
``v2e``::

    /work/v2e-venv/bin/python scripts/gapbench_v2e_worker.py --case CASE.json \\
        --out DIR/dev/dev1003.npz [--v2e /work/v2e-src]

It builds the case's scene (:mod:`gapbench_scene`), renders it at the case's input rate
(2 kHz) and feeds the frames one by one to v2e's ``EventEmulator`` (imported from the v2e
checkout; no v2e code is in this repository), the way ``scripts/v2e_data/generate.py`` does
(see ``scripts/v2e_data/README.md`` for the v2e facts relied on). Every emulator argument
that shapes events is given explicitly: the constructor's defaults are not "off"
(``leak_rate_hz=0.1``). torch runs on one CPU thread.

Writes ``OUT`` (an evcal ``.npz`` recording with event columns, APS frames and truth maps)
and ``OUT`` with suffix ``.json`` (the case's truth in evcal's terms and what was made),
both atomically.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gapbench_scene as gs  # noqa: E402

PINNED_V2E_COMMIT = "cac638444557a224ba6ee5c29260916f152c00bd"
LIN_LOG_THRESHOLD_DN = 20.0       # v2ecore/emulator_utils.py lin_log: ln(I) above 20 DN
SHOT_NOISE_INTEN_FACTOR = 0.25    # v2ecore/emulator.py: shot noise at white / at black
INTEN01_OFFSET_DN, INTEN01_SCALE_DN = 20.0, 275.0  # inten01 = (I + 20) / 275
REF_DN = 128.0                    # evcal's reference intensity of the bandwidth law
# every EventEmulator argument that shapes events, off; a case switches its effects on
V2E_OFF = dict(cutoff_hz=0.0, leak_rate_hz=0.0, refractory_period_s=0.0,
               shot_noise_rate_hz=0.0, photoreceptor_noise=False, leak_jitter_fraction=0.1,
               noise_rate_cov_decades=0.1)
V2E_EFFECT_ARGS = {"refractory": "refractory_period_s", "leak": "leak_rate_hz",
                   "shot_noise": "shot_noise_rate_hz", "bandwidth": "cutoff_hz"}
BLOCK = 200                       # input frames rendered at once

log = logging.getLogger("gapbench_v2e")


def import_v2e(v2e_path: str) -> Any:
    """v2e's ``EventEmulator`` from the checkout at ``v2e_path`` (its per-step chatter off)."""
    sys.path.insert(0, v2e_path)
    from v2ecore.emulator import EventEmulator

    for name in ("v2ecore.emulator", "v2ecore.emulator_utils"):
        logging.getLogger(name).setLevel(logging.ERROR)
    return EventEmulator


def v2e_commit(v2e_path: str) -> str:
    """The checkout's commit (``unknown`` when git cannot tell)."""
    try:
        return subprocess.run(["git", "-C", v2e_path, "rev-parse", "HEAD"], check=True,
                              capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def emulator_args(case: dict[str, Any]) -> dict[str, Any]:
    """The ``EventEmulator`` arguments of a case: thresholds ``pos = c + b``, ``neg = c -
    b`` (evcal's ON threshold ``c + b``, OFF ``c - b``), its effects on, the rest off."""
    th = case["thresholds"]
    args: dict[str, Any] = dict(V2E_OFF, pos_thres=th["contrast"] + th["bias"],
                                neg_thres=th["contrast"] - th["bias"],
                                sigma_thres=th["sigma_thres"])
    for eff in case["effects"]:
        key = V2E_EFFECT_ARGS[eff["name"]]
        args[key] = float(eff["params"][key])
    return args


def v2e_shot_rate_hz(rate_hz: float, intensity_dn: float) -> float:
    """v2e's mean shot-noise rate (ON + OFF, Hz per pixel) at ``intensity_dn`` for its
    ``shot_noise_rate_hz`` (emulator_utils.py: ``(rate/2) ((0.25 - 1) inten01 + 1)`` per
    polarity, ``inten01 = (I + 20) / 275``; nominal thresholds)."""
    inten01 = (intensity_dn + INTEN01_OFFSET_DN) / INTEN01_SCALE_DN
    return rate_hz * ((SHOT_NOISE_INTEN_FACTOR - 1.0) * inten01 + 1.0)


def truth_effects(case: dict[str, Any], emu: Any, median_dn: float) -> list[dict[str, Any]]:
    """The hidden effects in evcal's terms: name, parameters, the main parameter's name
    (``primary_name``) and the value the workflow's fit is compared with (``primary``)."""
    out = []
    for eff in case["effects"]:
        name, p = eff["name"], eff["params"]
        if name == "refractory":
            period_us = float(p["refractory_period_s"]) * 1e6
            params = {"period_us": period_us, "mode": "delay"}
            primary_name, primary = "period_us", period_us
        elif name == "leak":
            rates = float(p["leak_rate_hz"]) * emu.noise_rate_array.cpu().numpy()
            mean = float(np.mean(rates))
            params = {"rate_hz": mean, "spread_log": float(emu.noise_rate_cov_decades)
                      * math.log(10.0), "light_exponent": 0.0, "ref_dn": REF_DN}
            primary_name, primary = "rate_hz", mean
        elif name == "shot_noise":
            law = v2e_shot_rate_hz(float(p["shot_noise_rate_hz"]), median_dn)
            # v2e scales each pixel's ON (OFF) probability by nominal / own threshold
            # (emulator_utils.py, README's formula): the mean rate has the mean factor (> 1)
            pos = emu.pos_thres.cpu().numpy().astype(np.float64)
            neg = emu.neg_thres.cpu().numpy().astype(np.float64)
            factor = float(np.mean(0.5 * (emu.pos_thres_nominal / pos
                                          + emu.neg_thres_nominal / neg)))
            rate = law * factor
            params = {"rate_at_median_hz": rate, "rate_without_threshold_factor": law,
                      "threshold_factor": factor,
                      "law": "v2e: rate ((0.25 - 1) (I + 20) / 275 + 1) * mean(nominal / "
                             "threshold)"}
            primary_name, primary = "rate_hz", rate
        elif name == "bandwidth":
            cutoff = float(p["cutoff_hz"]) * (REF_DN + INTEN01_OFFSET_DN) / INTEN01_SCALE_DN
            params = {"cutoff_hz": cutoff, "ref_dn": REF_DN,
                      "law": "v2e: cutoff_hz (I + 20) / 275"}
            primary_name, primary = "cutoff_hz", cutoff
        else:
            raise ValueError(f"v2e cannot hide {name!r}; it hides {sorted(V2E_EFFECT_ARGS)}")
        out.append({"name": name, "parameters": params, "primary_name": primary_name,
                     "primary": primary, "v2e": dict(p)})
    return out


def run_emulator(EventEmulator: Any, args: dict[str, Any], seed: int, scene: gs.Scene,
                 times_s: np.ndarray) -> tuple[np.ndarray, Any, float]:
    """Feed the scene at ``times_s`` to a new emulator; return the events (rows ``[t_s, x,
    y, p]`` float64), the emulator and the smallest intensity it saw (DN)."""
    h, w = scene.shape
    emu = EventEmulator(**args, seed=seed, device="cpu", output_width=w, output_height=h)
    chunks = []
    lowest = math.inf
    for k0 in range(0, times_s.size, BLOCK):
        ts = times_s[k0:k0 + BLOCK]
        block = scene.render_block(ts).astype(np.float64)
        lowest = min(lowest, float(block.min()))
        for img, t in zip(block, ts, strict=True):
            ev = emu.generate_events(img, float(t))
            if ev is not None and len(ev):
                chunks.append(np.asarray(ev, dtype=np.float64))
    ev = np.concatenate(chunks) if chunks else np.zeros((0, 4))
    return ev, emu, lowest


def generate(case: dict[str, Any], out: Path, EventEmulator: Any, commit: str) -> dict[str, Any]:
    """Make the case's recording at ``out`` and its sidecar; return the sidecar."""
    t_start = time.time()
    seed = int(case["seed"])
    scene = gs.build_scene(case)
    rate_hz = float(case["input_rate_hz"])
    n_steps = int(round(case["duration_s"] * rate_hz))
    times_s = np.arange(n_steps + 1) / rate_hz
    args = emulator_args(case)
    ev, emu, lowest = run_emulator(EventEmulator, args, seed, scene, times_s)
    t_emulated = time.time() - t_start

    # float32 seconds -> integer us (nearest); v2e's output is non-decreasing already, the
    # stable sort is a safeguard and keeps its order within a time
    t_us = np.rint(ev[:, 0] * 1e6).astype(np.int64)
    order = np.argsort(t_us, kind="stable")
    t_us, x, y, p = t_us[order], ev[order, 1], ev[order, 2], ev[order, 3]
    h, w = scene.shape
    if ev.size and not ((x >= 0).all() and (x < w).all() and (y >= 0).all() and (y < h).all()):
        raise RuntimeError(f"{case['id']}: v2e produced events outside the {w}x{h} sensor")

    frame_t = gs.frame_times_us(case["duration_s"], case["frame_period_us"],
                                case["frame_phase_us"])
    frames = scene.aps_frames(frame_t, case["exposure_us"], case["read_noise_dn"],
                              np.random.default_rng([seed, 2]))
    median_dn = scene.median_frame_dn(frame_t, case["exposure_us"])
    ties = int(np.count_nonzero(np.isin(t_us, frame_t)))

    pos = emu.pos_thres.cpu().numpy().astype(np.float64)
    neg = emu.neg_thres.cpu().numpy().astype(np.float64)
    effects = truth_effects(case, emu, median_dn)
    meta = {"source": "gapbench", "generator": "scripts/gapbench_v2e_worker.py",
            "simulator": "v2e EventEmulator", "v2e_commit": commit, "case": case["id"],
            "input_rate_hz": rate_hz}
    arrays = gs.recording_arrays(t_us, x, y, p, frame_t, frames, case["exposure_us"],
                                 json.dumps(meta, sort_keys=True))
    arrays["truth_contrast"] = ((pos + neg) / 2).astype(np.float32)
    arrays["truth_bias"] = ((pos - neg) / 2).astype(np.float32)
    # v2e's lin_log is ln(I) above 20 DN: offset 0 where every input stayed above it
    offset = 0.0 if lowest > LIN_LOG_THRESHOLD_DN else math.nan
    arrays["truth_log_offset"] = np.full((h, w), offset, np.float32)
    if args["leak_rate_hz"] > 0:
        arrays["truth_leak_rate_hz"] = (args["leak_rate_hz"]
                                        * emu.noise_rate_array.cpu().numpy()).astype(np.float32)
    n_bytes = gs.write_npz(out, arrays)
    n_on = int(np.count_nonzero(p > 0))
    sidecar = {
        "id": case["id"], "spec_hash": case["spec_hash"], "file": out.name,
        "truth": {
            "hidden": [e["name"] for e in effects], "effects": effects,
            "median_dn": median_dn, "contrast_median": float(np.median(arrays["truth_contrast"])),
            "bias_median": float(np.median(arrays["truth_bias"])),
            "log_offset": None if math.isnan(offset) else offset,
        },
        "generated": {
            "backend": "v2e", "v2e_commit": commit, "emulator_args": args,
            "n_events": int(t_us.size), "n_on": n_on, "n_frames": int(frames.shape[0]),
            "events_at_frame_times": ties, "input_dn_min": lowest,
            "scale": scene.scale, "bytes": n_bytes,
            "emulate_s": round(t_emulated, 2), "total_s": round(time.time() - t_start, 2),
        },
    }
    gs.write_json(out.with_suffix(".json"), sidecar)
    return sidecar


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", required=True,
                    help="the case's JSON file (from gap_benchmark.py), - for stdin")
    ap.add_argument("--out", required=True, help="the .npz to write")
    ap.add_argument("--v2e", default=os.environ.get("V2E_SRC", "/work/v2e-src"),
                    help="v2e checkout (default $V2E_SRC or /work/v2e-src)")
    ap.add_argument("--allow-other-commit", action="store_true",
                    help="run although the v2e checkout is not the pinned commit")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    commit = v2e_commit(args.v2e)
    if commit != PINNED_V2E_COMMIT and not args.allow_other_commit:
        log.error("v2e at %s is %s, not the pinned %s (--allow-other-commit to run anyway)",
                  args.v2e, commit, PINNED_V2E_COMMIT)
        return 2
    case = json.loads(sys.stdin.read() if args.case == "-" else Path(args.case).read_text())
    if case["backend"] != "v2e":
        log.error("case %s has backend %s, not v2e", case["id"], case["backend"])
        return 2
    EventEmulator = import_v2e(args.v2e)
    sidecar = generate(case, Path(args.out), EventEmulator, commit)
    g = sidecar["generated"]
    log.info("%s: %d events, %d frames, %.1f MB, v2e %.1f s, total %.1f s", case["id"],
             g["n_events"], g["n_frames"], g["bytes"] / 1e6, g["emulate_s"], g["total_s"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
