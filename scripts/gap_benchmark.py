#!/usr/bin/env python3
"""A seeded benchmark of the model-gap workflow (``evcal gap``): recordings with known
hidden effects, the workflow run on them, and its naming accuracy scored.

Run with evcal's venv (``. .venv/bin/activate``)::

    python scripts/gap_benchmark.py plan [--out DIR]               # the case table
    python scripts/gap_benchmark.py generate --out DIR [--split dev|test|all] [--jobs 2]
    python scripts/gap_benchmark.py run --data DIR --split dev --results dev.jsonl
    python scripts/gap_benchmark.py report --results dev.jsonl [--markdown OUT.md]
        [--oracle oracle.jsonl]                        # singles by what their truth shows
    python scripts/gap_benchmark.py oracle --data DIR [--only dev1002] [--results FILE]

**Cases.** ``--n-dev`` cases with seeds ``--dev-seed-base`` (1000).. form the ``dev`` split
(for tuning), ``--n-test`` with seeds ``--test-seed-base`` (2000).. the ``test`` split (run
only to report). In each split, 40 % of the cases use v2e's ``EventEmulator`` (backend
``v2e``, ``scripts/gapbench_v2e_worker.py`` in v2e's venv), the others evcal's simulator
(``sim``); per backend, 20 % hide nothing (``none``), 45 % one effect (``single``, cycling
through the backend's effects so that each gets near-equal counts), 20 % two (``pair``) and
15 % a realistic sensor of 3-4 (``mix``). Backend, category and scene are laid out per
split (permutations seeded by the split's seed base; scenes cycle through every bundled
photo of scikit-image and the procedural textures); everything else of a case (sensor,
duration, frames, scene parameters, motion, illumination, thresholds, effect parameters) is
drawn from ``np.random.default_rng(seed)``. :func:`draw_case` lists the ranges.

**Backends.** ``sim`` cases are simulated by evcal (``evcal.sim.nonideal.simulate``, in a
subprocess of this venv; ``--evcal-src`` simulates with a copy of evcal at a fixed commit
instead of the installed one, so that the benchmark does not move with the code under
test); ``v2e`` cases by ``scripts/gapbench_v2e_worker.py`` in v2e's venv
(``--v2e-python``, ``--v2e``). Both see the same scenes (``scripts/gapbench_scene.py``) and
the same APS frame model.

**Files.** ``DIR/<split>/<id>.npz`` (an evcal recording with truth maps, readable by
``evcal.io.open_recording``), ``DIR/<split>/<id>.json`` (the case's truth in evcal's terms
and what was generated) and ``DIR/manifest.json`` (every case of the plan with its truth
where generated). A case is generated again only when its description (``spec_hash``)
changed. The default DIR is ``/work/gapbench``, outside the repository.

**Scoring** (``report``): see :func:`score_case` and :func:`split_metrics`; the acceptance
criteria are :data:`CRITERIA`.
"""

from __future__ import annotations

import argparse
import gc
import hashlib
import json
import math
import os
import subprocess
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
import psutil

SCRIPTS = Path(__file__).resolve().parent
sys.path.insert(0, str(SCRIPTS))
import gapbench_scene as gs  # noqa: E402

GENERATOR_VERSION = 1
DEFAULT_DATA = Path("/work/gapbench")
DEFAULT_V2E_PYTHON = os.environ.get("V2E_PYTHON", "/work/v2e-venv/bin/python")
DEFAULT_V2E_SRC = os.environ.get("V2E_SRC", "/work/v2e-src")
SPLITS = ("dev", "test")

# effects each backend can hide, in the order single cases cycle through them
SIM_EFFECTS = ("refractory", "leak", "shot_noise", "bandwidth", "threshold_noise",
               "hot_pixels", "log_offset", "timestamp_jitter", "threshold_light", "row_noise",
               "aps_fpn", "exposure")
V2E_EFFECTS = ("refractory", "leak", "shot_noise", "bandwidth")
MIX_CORE = ("bandwidth", "leak", "shot_noise", "refractory")
SCHEME_EFFECT = "timestamp_quantisation"  # a frame-driven simulator's stamps, not a sensor's
SCENE_EFFECTS = ("flicker",)  # the scene's light: scored against the case's illumination
# how the recording began (every reference set at the first frame, as v2e starts): not a
# sensor effect, counted per backend like the scheme
START_EFFECT = "start_reset"
V2E_SHARE = 0.4
CATEGORY_SHARES = {"none": 0.20, "single": 0.45, "pair": 0.20, "mix": 0.15}
SIM_LOG_OFFSET = 1.0          # SimConfig.log_offset: the base model's nominal offset
V2E_INPUT_RATE_HZ = 2000.0    # v2e input frames per second (one emulator step = 500 us)
V2E_FRAME_PHASE_US = 230      # v2e APS stamps m period + 230 us: never on a v2e event time
V2E_MIN_DN = 22.0             # v2e's lin_log is linear below 20 DN
REF_DN = 128.0
# the scenes cases cycle through: every photo once, every procedural texture twice (31 %)
SCENE_POOL = gs.PHOTOS + gs.PROCEDURAL + gs.PROCEDURAL


# The plan --------------------------------------------------------------------------------

def _r(x: float, digits: int = 3) -> float:
    """``x`` rounded to ``digits`` significant digits (readable case tables)."""
    if x == 0 or not math.isfinite(x):
        return float(x)
    return float(round(x, digits - 1 - int(math.floor(math.log10(abs(x))))))


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw_motion(rng: np.random.Generator, duration_s: float) -> list[dict[str, Any]]:
    """Motion segments filling ``duration_s``: one still stretch of 0.3-0.6 s somewhere,
    the rest segments of 0.2-1.0 s (15 % still, else pan, rotation, zoom or shake; at most
    half of the time still). Pans: peak 20-300 px/s (uniform) heading back towards the
    start when far from it, ``constant`` or ``smooth`` profile; rotations 0.2-1.5 rad/s;
    zooms 0.1-0.5 /s log zoom (towards zoom 1); shakes 5-15 Hz, 1-4 px."""
    still_s = float(rng.uniform(0.3, 0.6))
    rest = duration_s - still_s
    durs: list[float] = []
    while sum(durs) < rest - 1e-9:
        durs.append(float(rng.uniform(0.2, 1.0)))
    durs[-1] -= sum(durs) - rest
    if durs[-1] < 0.2 and len(durs) > 1:
        last = durs.pop()
        durs[-1] += last
    moving = ("pan", "rotation", "zoom", "shake")
    kinds = [str(rng.choice(moving, p=(0.5, 0.2, 0.12, 0.18))) if rng.random() >= 0.15
             else "still" for _ in durs]
    where = int(rng.integers(0, len(durs) + 1))
    durs.insert(where, still_s)
    kinds.insert(where, "still")
    for i in rng.permutation(len(kinds)):  # at most half of the time still
        if sum(d for d, k in zip(durs, kinds, strict=True) if k == "still") <= duration_s / 2:
            break
        if i != where and kinds[i] == "still":
            kinds[i] = "pan"
    # adjacent stills are one still
    merged: list[list[Any]] = []
    for d, k in zip(durs, kinds, strict=True):
        if merged and merged[-1][1] == "still" and k == "still":
            merged[-1][0] += d
        else:
            merged.append([d, k])
    bounds = np.concatenate([[0.0], np.cumsum([d for d, _ in merged])])
    bounds = np.round(bounds, 3)
    bounds[-1] = duration_s
    segments: list[dict[str, Any]] = []
    for (_, kind), t0, t1 in zip(merged, bounds[:-1], bounds[1:], strict=True):
        seg: dict[str, Any] = {"kind": kind, "t0_s": float(t0), "t1_s": float(t1)}
        profile = "constant" if rng.random() < 0.5 else "smooth"
        if kind == "pan":
            tx, ty, _, _ = gs.Motion(segments, duration_s).end_pose()
            heading = (math.atan2(-ty, -tx) + rng.uniform(-1.0, 1.0)
                       if math.hypot(tx, ty) > 15.0 else rng.uniform(0.0, 2 * math.pi))
            seg.update(speed_px_s=_r(rng.uniform(20.0, 300.0)), profile=profile,
                       heading_rad=_r(heading),
                       turn_rad=_r(rng.uniform(-0.8, 0.8)) if profile == "smooth" else 0.0)
        elif kind == "rotation":
            seg.update(rate_rad_s=_r(rng.uniform(0.2, 1.5) * rng.choice((-1.0, 1.0))),
                       profile=profile)
        elif kind == "zoom":
            lz = gs.Motion(segments, duration_s).end_pose()[3]
            sign = -math.copysign(1.0, lz) if abs(lz) > 0.05 else float(rng.choice((-1, 1)))
            seg.update(rate_per_s=_r(sign * rng.uniform(0.1, 0.5)), profile=profile)
        elif kind == "shake":
            seg.update(amplitude_px=_r(rng.uniform(1.0, 4.0)),
                       freq_x_hz=_r(rng.uniform(5.0, 15.0)), freq_y_hz=_r(rng.uniform(5.0, 15.0)),
                       phase_x_rad=_r(rng.uniform(0, 2 * math.pi)),
                       phase_y_rad=_r(rng.uniform(0, 2 * math.pi)))
        segments.append(seg)
    return segments


def draw_illumination(rng: np.random.Generator) -> dict[str, Any]:
    """Constant (40 %), a ramp to x0.5-x2 over the case (20 %), a global sine of 0.2-2 Hz
    and 5-30 % depth (25 %), mains flicker at 100 or 120 Hz of 2-10 % depth (15 %)."""
    u = rng.random()
    if u < 0.40:
        return {"kind": "constant"}
    if u < 0.60:
        factor = math.exp(rng.uniform(math.log(1.25), math.log(2.0)) * rng.choice((-1, 1)))
        return {"kind": "ramp", "gain_end": _r(factor)}
    if u < 0.85:
        return {"kind": "sine", "freq_hz": _r(rng.uniform(0.2, 2.0)),
                "depth": _r(rng.uniform(0.05, 0.30)), "phase_rad": _r(rng.uniform(0, 6.283))}
    return {"kind": "flicker", "freq_hz": float(rng.choice((100.0, 120.0))),
            "depth": _r(rng.uniform(0.02, 0.10)), "phase_rad": _r(rng.uniform(0, 6.283))}


def draw_scene(rng: np.random.Generator, seed: int, name: str) -> dict[str, Any]:
    """The scene ``name`` (a photo of scikit-image or a procedural texture, whose parameters
    are drawn here) and how much of it the sensor sees (``view_fraction`` 0.4-0.75)."""
    view = _r(rng.uniform(0.4, 0.75))
    if name in gs.PHOTOS:
        return {"kind": "photo", "name": name, "view_fraction": view}
    spec: dict[str, Any] = {"kind": "procedural", "name": name, "texture_seed": int(seed),
                            "view_fraction": view}
    if name == "noise":
        spec["sigma_px"] = float(rng.choice((1.5, 4.0, 10.0)))
    elif name == "checkerboard":
        spec.update(square_px=_r(rng.uniform(8, 40)), angle_rad=_r(rng.uniform(0, math.pi)))
    elif name == "grating":
        spec.update(period_px=_r(rng.uniform(8, 48)), angle_rad=_r(rng.uniform(0, math.pi)),
                    square=bool(rng.random() < 0.5))
    elif name == "blobs":
        spec.update(blob_size_fraction=_r(rng.uniform(0.03, 0.12)),
                    volume_fraction=_r(rng.uniform(0.3, 0.6)))
    elif name == "edges":
        spec.update(angle_rad=_r(rng.uniform(0, 2 * math.pi)),
                    n_shapes=int(rng.integers(15, 61)))
    else:
        raise ValueError(f"unknown scene {name!r}")
    return spec


def draw_effect(name: str, backend: str, rng: np.random.Generator, exposure_us: int
                ) -> dict[str, Any]:
    """Parameters of a hidden effect: evcal's (``sim``) or ``EventEmulator``'s (``v2e``).

    sim: refractory 200-3000 us (drop or delay); leak 0.05-1 Hz, spread 0.1-0.5, light
    exponent 0 or 0-1; shot noise 0.2-5 Hz at the scene's median intensity (the law's
    ``rate_hz`` is set from it when the scene is rendered), light exponent 0.5-1; bandwidth
    20-200 Hz at 128 DN; threshold noise 0.05-0.3; hot pixels 0.1-1 % at 20-200 Hz;
    log offset 5-60 DN; timestamp jitter 50-500 us; threshold_light exponent 0.1-0.5; row
    noise 0.2-2 Hz, 10-50 % of a row; aps_fpn 2-8 DN; exposure: frames stamped at the start
    of their exposure. v2e: refractory 0.2-3 ms, leak 0.05-1 Hz, shot noise 0.5-5 Hz,
    cutoff 30-300 Hz. Rates are log-uniform."""
    if backend == "v2e":
        if name == "refractory":
            return {"refractory_period_s": _r(_loguniform(rng, 0.2e-3, 3e-3))}
        if name == "leak":
            return {"leak_rate_hz": _r(_loguniform(rng, 0.05, 1.0))}
        if name == "shot_noise":
            return {"shot_noise_rate_hz": _r(_loguniform(rng, 0.5, 5.0))}
        if name == "bandwidth":
            return {"cutoff_hz": _r(_loguniform(rng, 30.0, 300.0))}
        raise ValueError(f"v2e cannot hide {name!r}")
    draws: dict[str, Callable[[], dict[str, Any]]] = {
        "refractory": lambda: {"period_us": _r(_loguniform(rng, 200.0, 3000.0)),
                               "mode": str(rng.choice(("drop", "delay")))},
        "leak": lambda: {"rate_hz": _r(_loguniform(rng, 0.05, 1.0)),
                         "spread_log": _r(rng.uniform(0.1, 0.5)),
                         "light_exponent": 0.0 if rng.random() < 0.5
                         else _r(rng.uniform(0.0, 1.0))},
        "shot_noise": lambda: {"rate_at_median_hz": _r(_loguniform(rng, 0.2, 5.0)),
                               "light_exponent": _r(rng.uniform(0.5, 1.0))},
        "bandwidth": lambda: {"cutoff_hz": _r(_loguniform(rng, 20.0, 200.0)), "ref_dn": REF_DN},
        "threshold_noise": lambda: {"sigma": _r(rng.uniform(0.05, 0.3))},
        "hot_pixels": lambda: {"fraction": _r(_loguniform(rng, 0.001, 0.01)),
                               "rate_hz": _r(_loguniform(rng, 20.0, 200.0))},
        "log_offset": lambda: {"dark_dn": _r(rng.uniform(5.0, 60.0))},
        "timestamp_jitter": lambda: {"sigma_us": _r(_loguniform(rng, 50.0, 500.0))},
        "threshold_light": lambda: {"exponent": _r(rng.uniform(0.1, 0.5)), "ref_dn": REF_DN},
        "row_noise": lambda: {"rate_hz": _r(rng.uniform(0.2, 2.0)),
                              "fraction": _r(rng.uniform(0.1, 0.5))},
        "aps_fpn": lambda: {"sigma_dn": _r(rng.uniform(2.0, 8.0)),
                            "seed": int(rng.integers(1, 2**31 - 1))},
        "exposure": lambda: {"lag_us": exposure_us / 2, "exposure_us": float(exposure_us)},
    }
    return draws[name]()


def hidden_names(backend: str, category: str, single: str | None,
                 rng: np.random.Generator) -> list[str]:
    """The names of a case's hidden effects. ``mix``: 3-4 of bandwidth, leak, shot noise,
    refractory; a third of the sim mixes put threshold noise in place of one of 4 or as the
    fourth of 3."""
    if category == "none":
        return []
    if category == "single":
        if single is None:
            raise ValueError("a single case needs its effect")
        return [single]
    if category == "pair":
        pool = SIM_EFFECTS if backend == "sim" else V2E_EFFECTS
        return [str(e) for e in rng.choice(pool, 2, replace=False)]
    n = int(rng.choice((3, 4)))
    names = [str(e) for e in rng.choice(MIX_CORE, n, replace=False)]
    if backend == "sim" and rng.random() < 1 / 3:
        names = names[:3] + ["threshold_noise"]
    return names


def draw_case(split: str, seed: int, backend: str, category: str, scene: str,
              single: str | None = None) -> dict[str, Any]:
    """A case's description: ``backend``, ``category``, ``scene`` (a name of
    :data:`SCENE_POOL`) and the ``single`` effect as laid out by :func:`plan_split`, the
    rest drawn from ``np.random.default_rng(seed)``.

    Sensor 240x180 (65 %, 2.0-3.0 s) or 346x260 (1.5-2.0 s); APS frames at 20-30 Hz (the
    period a multiple of 500 us), exposure 2-12 ms, read noise 0.5-1.5 DN; DN range ``[lo,
    hi]`` over the recording, illumination included: lo 3-40 DN (v2e 22-40), hi 80-250 and
    at least 3 lo times the illumination's gain ratio; thresholds c 0.15-0.3, b -0.03..0.03
    (sim: c spread 0.02-0.05, b spread 0.005-0.015; v2e: sigma_thres 0.02-0.05); sim
    internal rate 1 kHz (2 kHz with flicker); v2e input 2 kHz."""
    rng = np.random.default_rng(seed)
    big = rng.random() >= 0.65
    sensor = [260, 346] if big else [180, 240]
    duration_s = _r(rng.uniform(1.5, 2.0) if big else rng.uniform(2.0, 3.0))
    fps = rng.uniform(20.0, 30.0)
    period_us = int(500 * round(1e6 / fps / 500))
    exposure_us = int(100 * round(rng.uniform(2000, 12000) / 100))
    read_noise_dn = _r(rng.uniform(0.5, 1.5))
    scene_spec = draw_scene(rng, seed, scene)
    motion = draw_motion(rng, duration_s)
    illumination = draw_illumination(rng)
    g_min, g_max = gs.gain_bounds(illumination)
    lo = rng.uniform(V2E_MIN_DN if backend == "v2e" else 3.0, 40.0)
    hi = rng.uniform(min(max(80.0, 3.0 * lo * g_max / g_min), 249.0), 250.0)
    c = rng.uniform(0.15, 0.30)
    b = rng.uniform(-0.03, 0.03)
    if backend == "sim":
        thresholds = {"contrast_mean": _r(c), "contrast_std": _r(rng.uniform(0.02, 0.05)),
                      "bias_mean": _r(b), "bias_std": _r(rng.uniform(0.005, 0.015))}
    else:
        thresholds = {"contrast": _r(c), "bias": _r(b),
                      "sigma_thres": _r(rng.uniform(0.02, 0.05))}
    names = hidden_names(backend, category, single, rng)
    effects = [{"name": n, "params": draw_effect(n, backend, rng, exposure_us)} for n in names]
    case: dict[str, Any] = {
        "id": f"{split}{seed}", "split": split, "seed": int(seed), "backend": backend,
        "category": category, "sensor": sensor, "duration_s": duration_s,
        "frame_period_us": period_us, "frame_rate_hz": _r(1e6 / period_us, 4),
        "frame_phase_us": V2E_FRAME_PHASE_US if backend == "v2e" else 0,
        "exposure_us": exposure_us, "read_noise_dn": read_noise_dn,
        "scene": scene_spec, "dn_range": [_r(lo), _r(hi)], "motion": motion,
        "illumination": illumination, "thresholds": thresholds,
        "input_rate_hz": V2E_INPUT_RATE_HZ if backend == "v2e" else
        (2000.0 if illumination["kind"] == "flicker" else 1000.0),
        "effects": effects,
    }
    case["spec_hash"] = spec_hash(case)
    return case


def spec_hash(case: dict[str, Any]) -> str:
    """A digest of the case's description and the generator version (resume key)."""
    body = {k: v for k, v in case.items() if k != "spec_hash"}
    text = json.dumps(body, sort_keys=True) + f"|v{GENERATOR_VERSION}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _largest_remainder(n: int, shares: dict[str, float]) -> dict[str, int]:
    raw = {k: n * s for k, s in shares.items()}
    counts = {k: int(math.floor(v)) for k, v in raw.items()}
    for k in sorted(raw, key=lambda k: -(raw[k] - counts[k]))[:n - sum(counts.values())]:
        counts[k] += 1
    return counts


def plan_split(split: str, n: int, seed_base: int) -> list[dict[str, Any]]:
    """The cases of one split: seeds ``seed_base..seed_base + n - 1``; backend and category
    laid out in exact proportions and permuted with ``default_rng(seed_base)``; singles
    cycle through their backend's effects in case order; scenes cycle through
    :data:`SCENE_POOL` in an order permuted with ``default_rng(seed_base + 1)``."""
    n_v2e = int(round(V2E_SHARE * n))
    layout: list[tuple[str, str]] = []
    for backend, m in (("sim", n - n_v2e), ("v2e", n_v2e)):
        for cat, k in _largest_remainder(m, CATEGORY_SHARES).items():
            layout += [(backend, cat)] * k
    order = np.random.default_rng(seed_base).permutation(n)
    pool = np.random.default_rng(seed_base + 1).permutation(len(SCENE_POOL))
    scenes = [SCENE_POOL[int(pool[i % len(pool)])] for i in range(n)]
    cycle = {"sim": 0, "v2e": 0}
    cases = []
    for i, j in enumerate(order):
        backend, cat = layout[int(j)]
        single = None
        if cat == "single":
            pool = SIM_EFFECTS if backend == "sim" else V2E_EFFECTS
            single = pool[cycle[backend] % len(pool)]
            cycle[backend] += 1
        cases.append(draw_case(split, seed_base + i, backend, cat, scenes[i], single))
    return cases


def plan_cases(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Every case of the benchmark (dev then test)."""
    return (plan_split("dev", args.n_dev, args.dev_seed_base)
            + plan_split("test", args.n_test, args.test_seed_base))


def select(cases: list[dict[str, Any]], split: str = "all", only: str | None = None,
           limit: int | None = None, backend: str | None = None) -> list[dict[str, Any]]:
    """The cases of ``split`` (``all``: both), optionally only the ids ``only``
    (comma-separated), of one ``backend``, and the first ``limit``."""
    out = [c for c in cases if split == "all" or c["split"] == split]
    if only:
        ids = {s.strip() for s in only.split(",") if s.strip()}
        unknown = ids - {c["id"] for c in out}
        if unknown:
            raise SystemExit(f"unknown case id(s) {sorted(unknown)} in split {split}")
        out = [c for c in out if c["id"] in ids]
    if backend:
        out = [c for c in out if c["backend"] == backend]
    return out[:limit] if limit else out


# Describing cases ------------------------------------------------------------------------

def fmt_params(params: dict[str, Any]) -> str:
    return ", ".join(f"{k}={_r(v) if isinstance(v, float) else v}" for k, v in params.items()
                     if k not in ("seed", "ref_dn"))


def fmt_motion(motion: list[dict[str, Any]]) -> str:
    """Segments as ``kind[duration]``: S still, P pan (peak px/s), R rotation (rad/s),
    Z zoom (/s), H shake (px@Hz)."""
    parts = []
    for s in motion:
        d = s["t1_s"] - s["t0_s"]
        k = s["kind"]
        if k == "still":
            parts.append(f"S{d:.2f}")
        elif k == "pan":
            parts.append(f"P{d:.2f}:{s['speed_px_s']:.0f}")
        elif k == "rotation":
            parts.append(f"R{d:.2f}:{s['rate_rad_s']:+.2f}")
        elif k == "zoom":
            parts.append(f"Z{d:.2f}:{s['rate_per_s']:+.2f}")
        else:
            parts.append(f"H{d:.2f}:{s['amplitude_px']:.1f}@{s['freq_x_hz']:.0f}")
    return " ".join(parts)


def fmt_illumination(ill: dict[str, Any]) -> str:
    k = ill["kind"]
    if k == "ramp":
        return f"ramp x{ill['gain_end']:.2f}"
    if k in ("sine", "flicker"):
        return f"{k} {ill['freq_hz']:g}Hz {100 * ill['depth']:.0f}%"
    return k


def fmt_scene(scene: dict[str, Any]) -> str:
    if scene["kind"] == "photo":
        return scene["name"]
    extra = {"noise": "sigma_px", "checkerboard": "square_px", "grating": "period_px",
             "blobs": "blob_size_fraction", "edges": "n_shapes"}[scene["name"]]
    return f"{scene['name']}:{scene[extra]:g}"


def fmt_effects(effects: list[dict[str, Any]]) -> str:
    if not effects:
        return "-"
    return "; ".join(f"{e['name']}({fmt_params(e['params'])})" for e in effects)


def case_row(c: dict[str, Any], status: str | None = None) -> list[str]:
    h, w = c["sensor"]
    row = [c["id"], c["split"], str(c["seed"]), c["backend"], f"{w}x{h}",
           f"{c['duration_s']:.2f}", f"{c['frame_rate_hz']:.1f}",
           f"{c['exposure_us'] / 1000:.1f}", fmt_scene(c["scene"]),
           f"{c['dn_range'][0]:.0f}-{c['dn_range'][1]:.0f}", fmt_motion(c["motion"]),
           fmt_illumination(c["illumination"]), c["category"], fmt_effects(c["effects"])]
    if status is not None:
        row.insert(1, status)
    return row


CASE_HEADER = ["id", "split", "seed", "backend", "sensor", "dur_s", "fps", "exp_ms", "scene",
               "DN", "motion", "illumination", "category", "hidden effects"]


def table(header: Sequence[str], rows: Iterable[Sequence[Any]], markdown: bool = False
          ) -> str:
    """Rows as a plain aligned table (or a Markdown one)."""
    rows = [[str(v) for v in r] for r in rows]
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(header)]
    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()

    out = [line(header), line(["-" * w for w in widths])]
    return "\n".join([*out, *(line(r) for r in rows)])


def plan_summary(cases: list[dict[str, Any]]) -> str:
    """Counts per split: backend x category, effects hidden (all and as singles), sensors,
    illumination and scene kinds."""
    out = []
    for split in SPLITS:
        cs = [c for c in cases if c["split"] == split]
        if not cs:
            continue
        out.append(f"\n== {split}: {len(cs)} cases ==")
        cats = list(CATEGORY_SHARES)
        rows = []
        for b in ("sim", "v2e"):
            bc = [c for c in cs if c["backend"] == b]
            rows.append([b, len(bc)] + [sum(c["category"] == k for c in bc) for k in cats])
        rows.append(["all", len(cs)] + [sum(c["category"] == k for c in cs) for k in cats])
        out.append(table(["backend", "n"] + cats, rows))
        eff_rows = []
        for e in SIM_EFFECTS:
            row: list[Any] = [e]
            for b in ("sim", "v2e"):
                bc = [c for c in cs if c["backend"] == b]
                row.append(sum(c["category"] == "single" and c["effects"][0]["name"] == e
                               for c in bc))
                row.append(sum(any(x["name"] == e for x in c["effects"]) for c in bc))
            eff_rows.append(row)
        out.append(table(["effect", "sim single", "sim any", "v2e single", "v2e any"],
                         eff_rows))
        sensors = Counter(f"{c['sensor'][1]}x{c['sensor'][0]}" for c in cs)
        ill = Counter(c["illumination"]["kind"] for c in cs)
        scn = Counter(c["scene"]["kind"] for c in cs)
        names = Counter(c["scene"]["name"] for c in cs)
        dur = [c["duration_s"] for c in cs]
        out.append(f"sensors {dict(sensors)}; illumination {dict(ill)}; scenes {dict(scn)}; "
                   f"duration {min(dur):.2f}-{max(dur):.2f} s (total {sum(dur):.0f} s)\n"
                   f"scene use: {len(names)} scenes, {min(names.values())}-"
                   f"{max(names.values())} cases each")
    return "\n".join(out)


# Generation ------------------------------------------------------------------------------

def case_paths(data: Path, case: dict[str, Any]) -> tuple[Path, Path]:
    """The case's recording and its sidecar (truth)."""
    npz = data / case["split"] / f"{case['id']}.npz"
    return npz, npz.with_suffix(".json")


def read_sidecar(data: Path, case: dict[str, Any]) -> dict[str, Any] | None:
    """The case's sidecar when its recording is there and was made from this description."""
    npz, side = case_paths(data, case)
    if not (npz.exists() and side.exists()):
        return None
    try:
        s = json.loads(side.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if s.get("spec_hash") != case["spec_hash"] or \
            s.get("generated", {}).get("bytes") != npz.stat().st_size:
        return None
    return dict(s)


def sim_effects(case: dict[str, Any], median_dn: float) -> tuple[list[Any], list[dict[str, Any]]]:
    """evcal effects of a sim case and their truth (``primary`` as the workflow's fit is
    compared: leak and shot noise at the scene's median intensity ``median_dn``)."""
    from evcal.sim.effects import EFFECTS, Leak, ShotNoise, make_effect

    effects, truth = [], []
    for e in case["effects"]:
        name, p = e["name"], dict(e["params"])
        if name == "shot_noise":
            ref = ShotNoise().ref_dn
            # rate (ref / I)^k = target at I = median
            p = {"rate_hz": p["rate_at_median_hz"] * (median_dn / ref) ** p["light_exponent"],
                 "light_exponent": p["light_exponent"]}
        eff = make_effect(name, **p)
        params = eff.parameters()
        primary_name = EFFECTS[name].primary
        if isinstance(eff, ShotNoise):
            primary = float(eff.rate_at(median_dn))
        elif isinstance(eff, Leak):
            primary = eff.rate_hz * (median_dn / eff.ref_dn) ** eff.light_exponent
        else:
            primary = float(params[primary_name])
        effects.append(eff)
        truth.append({"name": name, "parameters": params, "primary_name": primary_name,
                      "primary": primary})
    return effects, truth


def generate_sim(case: dict[str, Any], out: Path) -> dict[str, Any]:
    """Simulate a sim case with evcal (``evcal.sim.nonideal.simulate`` driven by the case's
    scene) and write its recording and sidecar; return the sidecar."""
    from evcal.sim.effects import ApsConfig
    from evcal.sim.ideal import SimConfig
    from evcal.sim.nonideal import simulate

    t_start = time.time()
    scene = gs.build_scene(case)
    h, w = scene.shape
    frame_t = gs.frame_times_us(case["duration_s"], case["frame_period_us"], 0)
    median_dn = scene.median_frame_dn(frame_t, case["exposure_us"])
    effects, truth = sim_effects(case, median_dn)
    duration_s = float(case["duration_s"])
    rate_hz = 1e6 / case["frame_period_us"]
    if int(np.floor(duration_s * rate_hz)) + 1 < frame_t.size:
        # a duration of a whole number of periods rounds below it in the simulator's float
        # count of frames (2.28 s at 38 ms: 59.999...), which drops the last planned frame;
        # half a microsecond more keeps it and adds no event time
        duration_s += 0.5e-6
    cfg = SimConfig(height=h, width=w, duration_s=duration_s,
                    frame_rate_hz=rate_hz,
                    internal_rate_hz=case["input_rate_hz"], log_offset=SIM_LOG_OFFSET,
                    seed=int(case["seed"]), **case["thresholds"])
    # frames stamped at the middle of their exposure; the hidden ``exposure`` effect moves
    # the stamp to its start
    aps = ApsConfig(exposure_us=int(case["exposure_us"]), read_noise_dn=case["read_noise_dn"],
                    timestamp="middle", blur_samples=gs.APS_BLUR_SAMPLES)
    res = simulate(cfg, effects, aps=aps, source=scene)
    t_sim = time.time() - t_start
    rec = res.recording
    if not np.array_equal(rec.frames.t_us, frame_t):
        raise RuntimeError(f"{case['id']}: simulated frame times differ from the plan's")
    ev = rec.events
    meta = {"source": "gapbench", "generator": "scripts/gap_benchmark.py",
            "simulator": "evcal.sim.nonideal", "case": case["id"],
            "internal_rate_hz": case["input_rate_hz"]}
    arrays = gs.recording_arrays(ev["t_us"], ev["x"], ev["y"], ev["p"], rec.frames.t_us,
                                 rec.frames.images, case["exposure_us"],
                                 json.dumps(meta, sort_keys=True))
    tr = res.truth
    arrays["truth_contrast"] = np.asarray(tr["contrast"], np.float32)
    arrays["truth_bias"] = np.asarray(tr["bias"], np.float32)
    arrays["truth_log_offset"] = np.full((h, w), tr["log_offset"], np.float32)
    arrays["truth_labels"] = np.asarray(tr["labels"], np.uint8)
    if any(e["name"] == "leak" for e in case["effects"]):
        arrays["truth_leak_rate_hz"] = np.asarray(tr["leak_rate_hz"], np.float32)
    if any(e["name"] == "hot_pixels" for e in case["effects"]):
        arrays["truth_hot_pixels"] = np.asarray(tr["hot_pixels"], bool)
    n_bytes = gs.write_npz(out, arrays)
    n_on = int(np.count_nonzero(ev["p"] > 0))
    sidecar = {
        "id": case["id"], "spec_hash": case["spec_hash"], "file": out.name,
        "truth": {
            "hidden": [e["name"] for e in truth], "effects": truth, "median_dn": median_dn,
            "contrast_median": float(np.median(tr["contrast"])),
            "bias_median": float(np.median(tr["bias"])), "log_offset": float(tr["log_offset"]),
        },
        "generated": {
            "backend": "sim", "n_events": int(ev.size), "n_on": n_on,
            "n_frames": len(rec.frames),
            "events_at_frame_times": int(np.count_nonzero(np.isin(ev["t_us"], frame_t))),
            "label_counts": {str(k): int(v) for k, v in
                             zip(*np.unique(tr["labels"], return_counts=True), strict=True)},
            "evcal": evcal_source(), "scale": scene.scale, "bytes": n_bytes,
            "simulate_s": round(t_sim, 2),
            "total_s": round(time.time() - t_start, 2),
        },
    }
    gs.write_json(out.with_suffix(".json"), sidecar)
    return sidecar


def write_manifest(data: Path, cases: list[dict[str, Any]], plan_args: dict[str, Any]) -> None:
    """``DIR/manifest.json``: every planned case with its file, truth and generation facts
    (``null`` until generated)."""
    import cv2
    import skimage

    entries = []
    for c in cases:
        s = read_sidecar(data, c)
        npz, _ = case_paths(data, c)
        entries.append({**c, "file": str(npz.relative_to(data)),
                        "truth": s["truth"] if s else None,
                        "generated": s["generated"] if s else None})
    manifest = {
        "description": "gap-workflow benchmark: recordings with known hidden effects "
                       "(scripts/gap_benchmark.py)",
        "generator_version": GENERATOR_VERSION, "plan": plan_args,
        "versions": {"python": sys.version.split()[0], "numpy": np.__version__,
                     "opencv": cv2.__version__, "scikit-image": skimage.__version__},
        "n_cases": len(entries), "n_generated": sum(e["truth"] is not None for e in entries),
        "cases": entries,
    }
    gs.write_json(data / "manifest.json", manifest)


def _generate_one(case: dict[str, Any], data: Path, v2e_python: str, v2e_src: str,
                  evcal_src: str | None) -> tuple[dict[str, Any], float, str]:
    """Generate one case in a subprocess of its backend's venv (sim: with ``evcal_src``
    first on the path when given); ``(case, seconds, error)`` (error empty on success)."""
    npz, _ = case_paths(data, case)
    npz.parent.mkdir(parents=True, exist_ok=True)
    if case["backend"] == "v2e":
        cmd = [v2e_python, str(SCRIPTS / "gapbench_v2e_worker.py"), "--case", "-",
               "--out", str(npz), "--v2e", v2e_src]
    else:
        cmd = [sys.executable, str(Path(__file__).resolve()), "generate-case", "--case", "-",
               "--out", str(npz)]
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if evcal_src and case["backend"] == "sim":
        env["PYTHONPATH"] = os.pathsep.join([evcal_src, *filter(None, [env.get("PYTHONPATH")])])
    t0 = time.time()
    proc = subprocess.run(cmd, input=json.dumps(case), capture_output=True, text=True,
                          env=env, check=False)
    err = "" if proc.returncode == 0 else \
        f"exit {proc.returncode}: " + "\n".join(proc.stderr.strip().splitlines()[-15:])
    return case, time.time() - t0, err


def cmd_generate(args: argparse.Namespace) -> int:
    cases = plan_cases(args)
    todo_all = select(cases, args.split, args.only, None, args.backend)
    data = Path(args.out)
    data.mkdir(parents=True, exist_ok=True)
    plan_args = {k: getattr(args, k) for k in ("n_dev", "n_test", "dev_seed_base",
                                               "test_seed_base")}
    done = [c for c in todo_all if read_sidecar(data, c) is not None]
    todo = [c for c in todo_all if read_sidecar(data, c) is None]
    if args.limit:
        todo = todo[:args.limit]
    print(f"{len(todo_all)} cases selected, {len(done)} up to date, {len(todo)} to generate "
          f"in {data} with {args.jobs} jobs", flush=True)
    failed = 0
    t_start = time.time()
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [pool.submit(_generate_one, c, data, args.v2e_python, args.v2e,
                               args.evcal_src) for c in todo]
        for k, fut in enumerate(as_completed(futures), 1):
            case, secs, err = fut.result()
            if err:
                failed += 1
                print(f"[{k}/{len(todo)}] {case['id']} {case['backend']} FAILED after "
                      f"{secs:.0f} s\n{err}", flush=True)
            else:
                g = (read_sidecar(data, case) or {}).get("generated", {})
                h, w = case["sensor"]
                print(f"[{k}/{len(todo)}] {case['id']:9s} {case['backend']:3s} {w}x{h} "
                      f"{case['duration_s']:.2f}s {g.get('n_events', 0) / 1e6:6.2f} Mev "
                      f"{g.get('bytes', 0) / 1e6:6.1f} MB {secs:6.1f} s  "
                      f"(elapsed {(time.time() - t_start) / 60:.1f} min)", flush=True)
            write_manifest(data, cases, plan_args)
    write_manifest(data, cases, plan_args)
    print(f"done: {len(todo) - failed} generated, {failed} failed, "
          f"{(time.time() - t_start) / 60:.1f} min; manifest {data / 'manifest.json'}")
    return 1 if failed else 0


def cmd_generate_case(args: argparse.Namespace) -> int:
    """One sim case (the subprocess ``generate`` starts); the case's JSON on stdin or in a
    file."""
    import cv2

    cv2.setNumThreads(1)
    text = sys.stdin.read() if args.case == "-" else Path(args.case).read_text()
    case = json.loads(text)
    if case["backend"] != "sim":
        print(f"{case['id']} has backend {case['backend']}: gapbench_v2e_worker.py makes it",
              file=sys.stderr)
        return 2
    s = generate_sim(case, Path(args.out))
    print(f"{case['id']}: {s['generated']['n_events']} events, {s['generated']['total_s']} s")
    return 0


def cmd_plan(args: argparse.Namespace) -> int:
    cases = plan_cases(args)
    data = Path(args.out) if args.out else None
    header = CASE_HEADER if data is None else [CASE_HEADER[0], "made", *CASE_HEADER[1:]]
    rows = [case_row(c, None if data is None else
                     ("yes" if read_sidecar(data, c) is not None else "no")) for c in cases]
    print(table(header, rows))
    print(plan_summary(cases))
    return 0


# Running the workflow --------------------------------------------------------------------

def load_results(path: Path) -> dict[str, dict[str, Any]]:
    """The results file's records by case id (the last line of an id wins)."""
    out: dict[str, dict[str, Any]] = {}
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            out[r["id"]] = r
    return out


def evcal_source() -> dict[str, str]:
    """Where the imported evcal comes from and its commit: the repository's (see
    :func:`evcal_commit`) or, for a copy elsewhere, the ``COMMIT`` file beside its
    package."""
    import evcal

    pkg = Path(evcal.__file__).resolve().parent
    if pkg.is_relative_to(SCRIPTS.parent):
        return {"path": str(pkg), "commit": evcal_commit()}
    marker = pkg.parent / "COMMIT"
    return {"path": str(pkg),
            "commit": marker.read_text().strip() if marker.exists() else "unknown"}


def evcal_commit() -> str:
    """evcal's git commit (with ``+dirty`` when the work tree has changes)."""
    root = SCRIPTS.parent
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "src"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def cmd_run(args: argparse.Namespace) -> int:
    from evcal.gap.workflow import GapConfig, run_gap
    from evcal.io import open_recording

    try:
        from evcal.mallocpolicy import trim_freed_memory
    except ImportError:  # the allocator policy is an optimisation only
        trim_freed_memory = None

    data = Path(args.data)
    manifest = json.loads((data / "manifest.json").read_text())
    cases = select(manifest["cases"], args.split, args.only, None, None)
    results_path = Path(args.results)
    results_path.parent.mkdir(parents=True, exist_ok=True)
    have = load_results(results_path)
    todo = [c for c in cases if c["id"] not in have or (args.retry_errors and
                                                         "error" in have[c["id"]])]
    missing = [c["id"] for c in todo if c["truth"] is None]
    todo = [c for c in todo if c["truth"] is not None]
    if args.shuffle is not None:
        # a seeded order: the first results of a long run are a fair sample of the split
        order = np.random.default_rng(args.shuffle).permutation(len(todo))
        todo = [todo[i] for i in order]
    n_done = len(cases) - len(todo) - len(missing)
    if args.limit:
        todo = todo[:args.limit]
    if missing:
        print(f"not generated (skipped): {', '.join(missing)}", flush=True)
    commit = evcal_source()["commit"]
    print(f"{len(cases)} cases in {args.split}, {n_done} already in {results_path}, "
          f"{len(todo)} to run (evcal {commit})", flush=True)
    t_all = time.time()
    for k, c in enumerate(todo, 1):
        npz, _ = case_paths(data, c)
        h, w = c["sensor"]
        rec_out: dict[str, Any] = {
            "id": c["id"], "split": c["split"], "seed": c["seed"], "backend": c["backend"],
            "category": c["category"], "sensor": [h, w], "duration_s": c["duration_s"],
            "illumination": c["illumination"]["kind"], "scene": fmt_scene(c["scene"]),
            "gap_seed": args.seed, "evcal_commit": commit, "truth": c["truth"]}
        t0 = time.time()
        try:
            rec = open_recording(npz)
            rec_out["load_s"] = round(time.time() - t0, 2)
            rec_out["n_events"] = int(rec.n_events)
            t1 = time.time()
            res = run_gap(rec, GapConfig(seed=args.seed), released=trim_freed_memory)
            rec_out["wall_s"] = round(time.time() - t1, 2)
            js = res.to_json()
            rec_out.update({
                "named_effects": js["named_effects"],
                "steps": [{"effect": s["effect"], "parameters": s["parameters"],
                           "gap_before": s.get("gap_before"), "gap_after": s.get("gap_after"),
                           "held_out_gap_before": s.get("held_out_gap_before"),
                           "held_out_gap_after": s.get("held_out_gap_after"),
                           "why": s.get("why"),
                           "candidates": {k: {q: v.get(q) for q in
                                              ("status", "reason", "held_out_gap", "parameters",
                                               "held_out_statistics")
                                              if q in v}
                                          for k, v in res.steps[i].candidates.items()},
                           "held_out_statistics_before": dict(
                               res.steps[i].before.held.per_stat)}
                          for i, s in enumerate(js["steps"])],
                # the last round's candidates (report.json's not_named, with what they
                # were fitted to and their statistics)
                "not_named": {k: {q: v.get(q) for q in
                                  ("status", "reason", "held_out_gap", "parameters",
                                   "held_out_statistics") if q in v}
                              for k, v in res.rejected.items()},
                "final_held_out_statistics": dict(res.final.held.per_stat),
                "gap_initial": js["gap_initial"], "gap_final": js["gap_final"],
                "simulations": res.recording_info.get("simulations"),
                "recording_info": {k: v for k, v in res.recording_info.items()
                                   if k != "window"}})
            del rec, res
            hidden = ",".join(c["truth"]["hidden"]) or "-"
            named = ",".join(rec_out["named_effects"]) or "-"
            line = (f"hidden {hidden} -> named {named} | gap {rec_out['gap_initial']:.2f} -> "
                    f"{rec_out['gap_final']:.2f} | {rec_out['wall_s']:.0f} s, "
                    f"{rec_out['simulations']} sims")
        except Exception:  # a failing case is a result too; the run goes on
            rec_out["wall_s"] = round(time.time() - t0, 2)
            rec_out["error"] = traceback.format_exc()
            line = "ERROR " + rec_out["error"].strip().splitlines()[-1]
        # what the case let go of goes back to the system before the next: otherwise its
        # freed heaps stay in the process and the next case's peak comes on top of them
        gc.collect()
        if trim_freed_memory is not None:
            trim_freed_memory()
        rec_out["rss_after_mb"] = round(psutil.Process().memory_info().rss / 2**20, 1)
        with open(results_path, "a") as f:
            f.write(json.dumps(_finite(rec_out), allow_nan=False, default=_json_default)
                    + "\n")
        print(f"[{k}/{len(todo)}] {c['id']:9s} {c['backend']:3s} {w}x{h} {c['duration_s']:.2f}s "
              f"{c['category']:6s} {line}  (elapsed {(time.time() - t_all) / 60:.1f} min)",
              flush=True)
    return 0


def _finite(obj: Any, path: str = "") -> Any:
    """``obj`` with every non-finite float as ``None`` (JSON has none), each one reported
    on stderr with its path (a NaN in a result is a finding, not a reason to lose it)."""
    if isinstance(obj, dict):
        return {k: _finite(v, f"{path}/{k}") for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v, f"{path}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, (float, np.floating)) and not math.isfinite(float(obj)):
        print(f"non-finite {float(obj)} at {path}", file=sys.stderr)
        return None
    return obj


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


# Scoring ---------------------------------------------------------------------------------

def fitted_primary(name: str, params: dict[str, Any], median_dn: float) -> float | None:
    """The workflow's fitted main parameter in the terms of the truth's ``primary``: leak
    and shot noise as their rate at the scene's median intensity (``median_dn``), the
    others their ``Effect.primary``."""
    from evcal.sim.effects import EFFECTS, ShotNoise

    try:
        if name == "shot_noise":
            known = {k: v for k, v in params.items() if k in ShotNoise.__dataclass_fields__}
            return float(ShotNoise(**known).rate_at(median_dn))
        if name == "leak":
            return float(params["rate_hz"] * (median_dn / params.get("ref_dn", REF_DN))
                         ** params.get("light_exponent", 0.0))
        value = params.get(EFFECTS[name].primary)
        return None if value is None else float(value)
    except (KeyError, TypeError, ValueError):
        return None


def score_case(r: dict[str, Any]) -> dict[str, Any]:
    """One result scored: ``hidden``, ``named`` (sensor effects, in order; the timestamp
    scheme apart as ``scheme``), whether the first named is the hidden single, each named
    hidden effect's relative parameter error, false effects, the final gap."""
    truth = r.get("truth") or {}
    hidden = list(truth.get("hidden", []))
    h, w = r.get("sensor", [0, 0])
    out: dict[str, Any] = {
        "id": r["id"], "split": r["split"], "backend": r["backend"],
        "category": r["category"], "hidden": hidden, "sensor": f"{w}x{h}",
        "duration_s": r.get("duration_s"), "illumination": r.get("illumination"),
        "error": "error" in r, "wall_s": r.get("wall_s"), "simulations": r.get("simulations"),
        # events per pixel and second: how much the recording shows
        "activity": (r["n_events"] / (h * w * r["duration_s"])
                     if r.get("n_events") and h and r.get("duration_s") else None)}
    if out["error"]:
        out.update(named=[], scheme=False, start_reset=False, flicker_named=False, false=[],
                   gap_final=None,
                   param_err={})
        return out
    named = [n for n in r.get("named_effects", [])
             if n not in (SCHEME_EFFECT, START_EFFECT) and n not in SCENE_EFFECTS]
    out["named"] = named
    out["scheme"] = SCHEME_EFFECT in r.get("named_effects", [])
    out["start_reset"] = START_EFFECT in r.get("named_effects", [])
    out["flicker_named"] = "flicker" in r.get("named_effects", [])
    out["false"] = [n for n in named if n not in hidden]
    out["gap_final"] = r.get("gap_final")
    median = float(truth.get("median_dn", REF_DN))
    errs: dict[str, float] = {}
    for e in truth.get("effects", []):
        step = next((s for s in r.get("steps", []) if s["effect"] == e["name"]), None)
        if step is None:
            continue
        fit = fitted_primary(e["name"], step.get("parameters", {}), median)
        if fit is not None and e.get("primary"):
            errs[e["name"]] = abs(fit - e["primary"]) / abs(e["primary"])
    out["param_err"] = errs
    return out


ACTIVITY_BANDS = (("< 3 ev/px/s", 0.0, 3.0), ("3-10 ev/px/s", 3.0, 10.0),
                  (">= 10 ev/px/s", 10.0, math.inf))


def _share(k: int, n: int) -> float | None:
    return k / n if n else None


def split_metrics(scored: list[dict[str, Any]]) -> dict[str, Any]:
    """The benchmark's measures over ``scored`` cases (one split, one scope)."""
    m: dict[str, Any] = {"n": len(scored), "errors": sum(s["error"] for s in scored)}
    none = [s for s in scored if s["category"] == "none"]
    m["none"] = {"n": len(none), "false_alarm": _share(sum(bool(s["named"]) for s in none),
                                                       len(none)),
                 "named": dict(Counter(n for s in none for n in s["named"]))}
    singles: dict[str, Any] = {}
    for eff in SIM_EFFECTS:
        cs = [s for s in scored if s["category"] == "single" and s["hidden"] == [eff]]
        if not cs:
            continue
        first = [s for s in cs if s["named"][:1] == [eff]]
        errs = [s["param_err"][eff] for s in first if eff in s["param_err"]]
        singles[eff] = {
            "n": len(cs), "named_first": _share(len(first), len(cs)),
            "within_30": _share(sum(e <= 0.3 for e in errs), len(first)),
            "both": _share(sum(s["param_err"].get(eff, math.inf) <= 0.3 for s in first),
                           len(cs)),
            "median_err": float(np.median(errs)) if errs else None,
            "first_named": dict(Counter(s["named"][0] if s["named"] else "-" for s in cs))}
    m["single"] = singles
    # the singles by the recording's activity: a sparse recording shows an effect less
    bands = {}
    for label, lo, hi in ACTIVITY_BANDS:
        cs = [s for s in scored if s["category"] == "single" and s["activity"] is not None
              and lo <= s["activity"] < hi]
        bands[label] = {"n": len(cs), "named_first": _share(
            sum(s["named"][:1] == s["hidden"] for s in cs), len(cs))}
    m["single_by_activity"] = bands
    for cat in ("pair", "mix"):
        cs = [s for s in scored if s["category"] == cat]
        m[cat] = {"n": len(cs),
                  "two_plus": _share(sum(len(set(s["named"]) & set(s["hidden"])) >= 2
                                         for s in cs), len(cs)),
                  "all_named": _share(sum(set(s["hidden"]) <= set(s["named"]) for s in cs),
                                      len(cs)),
                  "no_false": _share(sum(not s["false"] and not s["error"] for s in cs),
                                     len(cs))}
    gaps = [s["gap_final"] for s in scored]
    m["gap_le_3"] = _share(sum(g is not None and g <= 3 for g in gaps), len(gaps))
    by_backend = {}
    for b in ("sim", "v2e"):
        bs = [s for s in scored if s["backend"] == b and not s["error"]]
        by_backend[b] = {"n": len(bs), "scheme_named": sum(s["scheme"] for s in bs),
                         "start_reset_named": sum(s.get("start_reset", False) for s in bs)}
    m["scheme"] = by_backend
    m["speed"] = {"all": _spread([s["wall_s"] for s in scored if not s["error"]]),
                  "240x180_2.5-3s": _spread([
                      s["wall_s"] for s in scored if not s["error"] and s["sensor"] == "240x180"
                      and s["duration_s"] is not None and 2.5 <= s["duration_s"] <= 3.0]),
                  "simulations": _spread([s["simulations"] for s in scored
                                          if s["simulations"] is not None])}
    flick = [s for s in scored if s["illumination"] == "flicker" and not s["error"]]
    other = [s for s in scored if s["illumination"] != "flicker" and not s["error"]]
    m["flicker"] = {"n": len(flick), "named": sum(s["flicker_named"] for s in flick),
                    "n_without": len(other),
                    "named_without": sum(s["flicker_named"] for s in other)}
    m["illumination"] = {
        k: {"n": len(cs), "false": sum(bool(s["false"]) for s in cs)}
        for k in ("constant", "ramp", "sine", "flicker")
        if (cs := [s for s in scored if s["illumination"] == k])}
    return m


def _spread(values: list[float]) -> dict[str, float] | None:
    v = np.asarray([x for x in values if x is not None], np.float64)
    if v.size == 0:
        return None
    q = np.percentile(v, [0, 25, 50, 75, 100])
    return {"n": int(v.size), "min": float(q[0]), "q1": float(q[1]), "median": float(q[2]),
            "q3": float(q[3]), "max": float(q[4])}


# (name, target, value of the metrics, pass test)
CRITERIA: list[tuple[str, str, Callable[[dict[str, Any]], float | None],
                     Callable[[float], bool]]] = [
    ("none: any sensor effect named", "<= 5 %", lambda m: m["none"]["false_alarm"],
     lambda v: v <= 0.05),
    ("mix: 2+ hidden effects named", ">= 80 %", lambda m: m["mix"]["two_plus"],
     lambda v: v >= 0.80),
    ("mix: no false effect", ">= 90 %", lambda m: m["mix"]["no_false"], lambda v: v >= 0.90),
    ("final gap <= 3", ">= 90 %", lambda m: m["gap_le_3"], lambda v: v >= 0.90),
]


def criteria_rows(m: dict[str, Any]) -> list[tuple[str, str, float | None, int]]:
    """``(criterion, target, value, n)`` of the acceptance criteria; singles per effect
    (named first >= 90 %; main parameter within 30 % in >= 90 % of those named first)."""
    rows = [(name, target, get(m), _crit_n(name, m)) for name, target, get, _ in CRITERIA]
    for eff, s in m["single"].items():
        rows.append((f"single {eff}: named first", ">= 90 %", s["named_first"], s["n"]))
        rows.append((f"single {eff}: parameter within 30 %", ">= 90 %", s["within_30"],
                     round((s["named_first"] or 0) * s["n"])))
    return rows


def _crit_n(name: str, m: dict[str, Any]) -> int:
    key = name.split(":")[0]
    return int(m[key]["n"]) if key in ("none", "mix") else int(m["n"])


def _passes(name: str, value: float | None) -> str:
    if value is None:
        return "n/a"
    for cname, _, _, ok in CRITERIA:
        if cname == name:
            return "PASS" if ok(value) else "FAIL"
    return "PASS" if value >= 0.90 else "FAIL"  # the singles' criteria


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.0f}%"


def report_text(scored: list[dict[str, Any]], markdown: bool = False
                ) -> tuple[str, dict[str, Any]]:
    """The report's tables and the metrics behind them (per split: all, sim, v2e)."""
    out: list[str] = []
    metrics: dict[str, Any] = {}
    hdr = (lambda s: f"\n## {s}\n") if markdown else (lambda s: f"\n=== {s} ===")
    for split in SPLITS:
        ss = [s for s in scored if s["split"] == split]
        if not ss:
            continue
        scopes = {"all": ss, "sim": [s for s in ss if s["backend"] == "sim"],
                  "v2e": [s for s in ss if s["backend"] == "v2e"]}
        ms = {k: split_metrics(v) for k, v in scopes.items() if v}
        metrics[split] = ms
        names = list(ms)
        out.append(hdr(f"{split}: {len(ss)} cases ("
                       + ", ".join(f"{k} {ms[k]['n']}" for k in names if k != "all")
                       + f"; errors {ms['all']['errors']})"))
        out.append("1. nothing hidden: share of cases naming a sensor effect")
        out.append(table(["scope", "n", "false alarm", "named"],
                         [[k, ms[k]["none"]["n"], _pct(ms[k]["none"]["false_alarm"]),
                           ", ".join(f"{e} {c}" for e, c in ms[k]["none"]["named"].items())
                           or "-"] for k in names], markdown))
        out.append("\n2. single hidden effect: named first, main parameter (relative error)")
        rows = []
        for k in names:
            for eff, s in ms[k]["single"].items():
                rows.append([k, eff, s["n"], _pct(s["named_first"]), _pct(s["within_30"]),
                             "-" if s["median_err"] is None else f"{100 * s['median_err']:.0f}%",
                             ", ".join(f"{e} {c}" for e, c in s["first_named"].items())])
        out.append(table(["scope", "effect", "n", "named first", "param <=30%",
                          "median err", "first named"], rows, markdown))
        out.append("\n   singles by activity (events per pixel and second)")
        out.append(table(["scope"] + [b[0] for b in ACTIVITY_BANDS],
                         [[k] + [f"{_pct(v['named_first'])} of {v['n']}"
                                 for v in ms[k]["single_by_activity"].values()]
                          for k in names], markdown))
        if any("oracle" in s for s in ss):
            out.append("\n   singles by what their truth shows (`oracle --results`): "
                       "reproduced = the truth's gap at most 3; visible = leaving the effect "
                       "out of the truth gains what naming needs")
            out.append(table(["scope", "class", "n", "named first", "effects"],
                             [[k, cls, *row] for k in names
                              for cls, row in oracle_classes(scopes[k]).items()], markdown))
        out.append("\n3. pairs and mixes")
        rows = [[k, cat, ms[k][cat]["n"], _pct(ms[k][cat]["two_plus"]),
                 _pct(ms[k][cat]["all_named"]), _pct(ms[k][cat]["no_false"])]
                for k in names for cat in ("pair", "mix") if ms[k][cat]["n"]]
        out.append(table(["scope", "category", "n", "2+ named", "all named", "no false"],
                         rows, markdown))
        out.append("\n4. final gap <= 3 (all cases; an error counts as above)")
        out.append(table(["scope", "n", "gap <= 3"],
                         [[k, ms[k]["n"], _pct(ms[k]["gap_le_3"])] for k in names], markdown))
        out.append("\n5. confusion: cases naming each effect (any position), by what was hidden")
        out.append(confusion(ss, markdown))
        out.append(f"\n   {SCHEME_EFFECT} named (not a sensor effect): " + ", ".join(
            f"{b} {v['scheme_named']}/{v['n']}" for b, v in ms["all"]["scheme"].items()))
        out.append(f"   {START_EFFECT} named (how the recording began; v2e resets, evcal's "
                   "simulator does not): " + ", ".join(
                       f"{b} {v.get('start_reset_named', 0)}/{v['n']}"
                       for b, v in ms["all"]["scheme"].items()))
        fl = ms["all"]["flicker"]
        out.append(f"   flicker (the scene's light) named: in {fl['named']}/{fl['n']} cases "
                   f"under a flickering light, {fl['named_without']}/{fl['n_without']} "
                   "without")
        out.append("   false effects by illumination: " + ", ".join(
            f"{k} {v['false']}/{v['n']}" for k, v in ms["all"]["illumination"].items()))
        out.append("\n6. speed (wall seconds of run_gap) and simulations")
        rows = []
        for k in names:
            for what, d in ms[k]["speed"].items():
                if d:
                    rows.append([k, what, d["n"], f"{d['median']:.0f}",
                                 f"{d['q1']:.0f}-{d['q3']:.0f}", f"{d['min']:.0f}",
                                 f"{d['max']:.0f}"])
        out.append(table(["scope", "what", "n", "median", "quartiles", "min", "max"], rows,
                         markdown))
        out.append("\nAcceptance")
        rows = []
        for name, target, _, _ in criteria_rows(ms["all"]):
            cells: list[Any] = [name, target]
            for k in names:
                crit = {r[0]: r for r in criteria_rows(ms[k])}
                if name in crit:
                    _, _, v, n = crit[name]
                    cells.append(f"{_pct(v)} n={n} {_passes(name, v)}")
                else:
                    cells.append("-")
            rows.append(cells)
        out.append(table(["criterion", "target", *names], rows, markdown))
    return "\n".join(out), metrics


ORACLE_CLASSES = ("reproduced, visible", "reproduced, not visible", "not reproduced")


def oracle_class(s: dict[str, Any]) -> str | None:
    """A single case's class by its oracle record (None without one): whether evcal's
    model of the truth reproduces the recording (gap at most 3) and, if so, whether the
    hidden effect shows in the gap (``visible``)."""
    o = s.get("oracle")
    if not o or s["category"] != "single":
        return None
    eff = o["effects"].get(s["hidden"][0])
    if eff is None:
        return None
    if o["gap_truth"] > 3.0:
        return ORACLE_CLASSES[2]
    return ORACLE_CLASSES[0] if eff["visible"] else ORACLE_CLASSES[1]


def oracle_classes(scored: list[dict[str, Any]]) -> dict[str, list[Any]]:
    """Per oracle class of the single cases: n, share named first, the effects (count)."""
    out = {}
    for cls in ORACLE_CLASSES:
        cs = [s for s in scored if oracle_class(s) == cls]
        if cs:
            out[cls] = [len(cs), _pct(_share(sum(s["named"][:1] == s["hidden"] for s in cs),
                                             len(cs))),
                        ", ".join(f"{e} {n}" for e, n in
                                  sorted(Counter(s["hidden"][0] for s in cs).items()))]
    return out


def confusion(scored: list[dict[str, Any]], markdown: bool) -> str:
    """Rows: hidden category (singles by effect); columns: the effects named."""
    rows_key = []
    for s in scored:
        rows_key.append(f"single {s['hidden'][0]}" if s["category"] == "single"
                        else s["category"])
    named_cols = sorted({n for s in scored for n in s["named"]})
    order = ["none"] + [f"single {e}" for e in SIM_EFFECTS] + ["pair", "mix"]
    rows = []
    for key in order:
        cs = [s for s, k in zip(scored, rows_key, strict=True) if k == key]
        if not cs:
            continue
        counts = Counter(n for s in cs for n in set(s["named"]))
        rows.append([key, len(cs), sum(not s["named"] for s in cs),
                     sum(s["error"] for s in cs)]
                    + [counts.get(n, "") for n in named_cols])
    return table(["hidden", "n", "nothing", "errors", *named_cols], rows, markdown)


def cmd_report(args: argparse.Namespace) -> int:
    results = load_results(Path(args.results))
    if not results:
        print(f"no results in {args.results}")
        return 1
    scored = [score_case(r) for r in results.values()]
    if args.oracle:
        oracle = load_results(Path(args.oracle))
        for sc in scored:
            if sc["id"] in oracle:
                sc["oracle"] = oracle[sc["id"]]
    text, metrics = report_text(scored)
    print(text)
    if args.markdown:
        md, _ = report_text(scored, markdown=True)
        Path(args.markdown).write_text(f"# Gap benchmark: {args.results}\n{md}\n")
    if args.json:
        Path(args.json).write_text(json.dumps({"metrics": metrics, "cases": scored}, indent=1,
                                              default=_json_default) + "\n")
    return 0


def truth_model(npz: Path, truth: dict[str, Any], *, effects: bool = True,
                add: tuple[str, ...] = (), backend: str = "sim", drop: str | None = None,
                illumination: dict[str, Any] | None = None) -> Any:
    """The gap model a case was made with: its true maps, log offset and (``effects``) its
    hidden effects in evcal's terms (a v2e case's are evcal's nearest: v2e's shot-noise law,
    linear in light, as the power law of the same rate and slope at the scene's median),
    plus the effects named in ``add`` at their defaults (``start_reset``: how v2e begins),
    less the hidden effect ``drop``. A v2e case also gets v2e's stamps (steps of 1 /
    ``V2E_INPUT_RATE_HZ`` on the absolute time grid, slots spread): a simulator's scheme,
    but one that decides where its dead time acts and stamps its noise at a step's end.
    ``illumination`` (the case's): a flickering light is part of the scene the frames
    cannot show, so the model of the case has it (``flicker``, the same time base)."""
    import dataclasses

    from evcal.gap.model import Model
    from evcal.gap.stats import NOMINAL_LOG_OFFSET_DN
    from evcal.sim.effects import EFFECTS, ApsFpn, LogOffset, TimestampQuantisation

    kinds = dict(EFFECTS)
    with np.load(npz) as z:
        c = z["truth_contrast"].astype(np.float64)
        b = z["truth_bias"].astype(np.float64)
        offset = float(np.median(z["truth_log_offset"]))
        first_frame_us = int(z["frame_t_us"][0])
    chosen = {}
    if effects:
        for e in truth["effects"]:
            if e["name"] == drop:
                continue
            kind = kinds[e["name"]]
            p = dict(e["parameters"])
            if e["name"] == "shot_noise" and "rate_at_median_hz" in p:
                p = _v2e_shot_law(p, float(truth["median_dn"]))
            fields = {f.name for f in dataclasses.fields(kind)}
            eff = kind(**{k: v for k, v in p.items() if k in fields})
            if isinstance(eff, ApsFpn):
                # the gap model corrects the frames by a known map only: the drawn one
                eff = dataclasses.replace(eff, offset_dn=eff.offsets_dn(c.shape))
            chosen[e["name"]] = eff
    if drop == LogOffset.name:
        # the maps' log offset is the dark level the case hid: without it, the nominal one
        offset = NOMINAL_LOG_OFFSET_DN
    for name in add:
        chosen[name] = kinds[name]()
    if illumination is not None and illumination["kind"] == "flicker" and drop != "flicker":
        chosen["flicker"] = kinds["flicker"](
            freq_hz=float(illumination["freq_hz"]), depth=float(illumination["depth"]),
            phase_rad=float(illumination["phase_rad"]))
    if backend == "v2e":
        step_us = 1e6 / V2E_INPUT_RATE_HZ
        chosen[TimestampQuantisation.name] = TimestampQuantisation(
            step_us=step_us, scheme="spread", phase_us=float(-first_frame_us % step_us))
    return Model(c, b, offset, chosen)


def _v2e_shot_law(p: dict[str, Any], median_dn: float) -> dict[str, Any]:
    """evcal's ``ShotNoise`` nearest v2e's: the rate at the median light (thresholds'
    factor included) and the local slope of v2e's law there, ``rate ~ 1 - 0.75 (I + 20) /
    275`` (v2ecore/emulator_utils.py ``generate_shot_noise``), as the power's exponent."""
    f = 1.0 - 0.75 * (median_dn + 20.0) / 275.0
    exponent = float(np.clip(0.75 * median_dn / 275.0 / max(f, 1e-3), 0.0, 2.0))
    return {"rate_hz": float(p["rate_at_median_hz"]), "ref_dn": float(median_dn),
            "light_exponent": exponent, "min_dn": 1.6}


def cmd_oracle(args: argparse.Namespace) -> int:
    """Each case simulated from its own frames with its true maps and hidden effects (no
    anchor, no fit), compared with its recording as the workflow compares a model: the gap
    that remains is the frame-driven base model's own misfit, which no effect can close (or
    an effect evcal's model of it does not reproduce). Then each hidden effect left out in
    turn: what the gap gains by it is what any selection could see of it; an effect is
    *visible* when that gain is what naming it needs (:func:`evcal.gap.runner.need`, on the
    whole sensor rather than held-out rows). Dev cases only: reading the test split this
    way would tune on it."""
    from evcal.gap.runner import Evaluation, Evaluator, GapConfig, _empty, need
    from evcal.io import open_recording

    data = Path(args.data)
    manifest = json.loads((data / "manifest.json").read_text())
    cases = [c for c in select(manifest["cases"], "dev", args.only, args.limit, None)
             if c["truth"] is not None]
    add = tuple(a for a in (args.add or "").split(",") if a)
    cfg = GapConfig(n_seeds=args.seeds, subframe_motion=args.subframe_motion)
    tally: dict[str, list[int]] = {}
    for c in cases:
        npz, _ = case_paths(data, c)
        rec = open_recording(npz)
        ev = Evaluator(rec, cfg, tick=lambda _share: None)
        extra = add + (("start_reset",) if c["backend"] == "v2e" and
                       args.v2e_reset and "start_reset" not in add else ())
        rows = []
        # v2e's start from its first frame is how such a recording begins, named apart by
        # the workflow: left out in turn like the hidden effects
        # and a flickering light, the scene's: what its model gains shows whether the
        # events see it
        lit = ("flicker",) if c["illumination"]["kind"] == "flicker" else ()
        for drop in (None, *c["truth"]["hidden"], *(a for a in extra if a == "start_reset"),
                     *lit):
            model = truth_model(npz, c["truth"], add=tuple(a for a in extra if a != drop),
                                backend=c["backend"], drop=drop,
                                illumination=c["illumination"])
            label = "true maps + effects" if drop is None else f"without {drop}"
            out = ev.extend(Evaluation(model, [], _empty(), _empty()), args.seeds, label)
            per = dict(out.disc.per_stat)
            rows.append((label, drop, float(np.mean(list(per.values()))), per, out))
            out.sims.clear()  # a case's simulations are let go as soon as they are summed
        hidden = ",".join(c["truth"]["hidden"]) or "-"
        print(f"{c['id']}  {c['backend']}  {c['category']}  hidden {hidden}  "
              f"{c['illumination']['kind']}  {fmt_scene(c['scene'])}")
        record: dict[str, Any] = {"id": c["id"], "backend": c["backend"],
                                  "category": c["category"], "gap_truth": rows[0][2],
                                  "effects": {}}
        for label, drop, gap, per, out in rows:
            worst = sorted(per.items(), key=lambda kv: -kv[1])[:args.top]
            tail = ""
            if drop is not None:
                gained = gap - max(rows[0][2], 1.0)
                needed = need(cfg, gap)
                visible = gained > needed
                tally.setdefault(f"{c['backend']} {drop}", [0, 0])[0] += int(visible)
                tally[f"{c['backend']} {drop}"][1] += 1
                record["effects"][drop] = {"gap_without": gap, "gained": gained,
                                           "needed": needed, "visible": visible}
                tail = f"  gains {gained:.2f} ({'visible' if visible else 'not visible'}: " \
                       f"{needed:.2f} needed)"
            print(f"   {label:22s} gap {gap:8.2f}{tail}  " + "  ".join(
                f"{k} {v:.1f} [{out.disc.where(k)}]" for k, v in worst))
        if args.results:
            with open(args.results, "a") as fh:
                fh.write(json.dumps(record) + "\n")
        sys.stdout.flush()
        del ev, rec, rows
        gc.collect()
    if tally:
        print("\nvisible (the truth's gap gains what naming needs by the effect) / cases:")
        for key in sorted(tally):
            print(f"   {key:24s} {tally[key][0]} / {tally[key][1]}")
    return 0


# Command line ----------------------------------------------------------------------------

def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)

    def plan_opts(p: argparse.ArgumentParser) -> None:
        p.add_argument("--n-dev", type=int, default=110, help="dev cases (default 110)")
        p.add_argument("--n-test", type=int, default=50, help="test cases (default 50)")
        p.add_argument("--dev-seed-base", type=int, default=1000)
        p.add_argument("--test-seed-base", type=int, default=2000)

    p = sub.add_parser("plan", help="print the case table (nothing generated)")
    plan_opts(p)
    p.add_argument("--out", default=None, help="also show which cases DIR holds already")
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("generate", help="write the recordings and the manifest")
    plan_opts(p)
    p.add_argument("--out", default=str(DEFAULT_DATA), help=f"default {DEFAULT_DATA}")
    p.add_argument("--split", choices=("dev", "test", "all"), default="all")
    p.add_argument("--jobs", type=int, default=2, help="cases generated at once")
    p.add_argument("--limit", type=int, default=None, help="at most K cases (to generate)")
    p.add_argument("--only", default=None, help="comma-separated case ids")
    p.add_argument("--backend", choices=("sim", "v2e"), default=None)
    p.add_argument("--v2e-python", default=DEFAULT_V2E_PYTHON,
                   help="v2e venv's python (default $V2E_PYTHON or /work/v2e-venv/bin/python)")
    p.add_argument("--v2e", default=DEFAULT_V2E_SRC, help="v2e checkout (default $V2E_SRC "
                   "or /work/v2e-src)")
    p.add_argument("--evcal-src", default=None,
                   help="a directory holding the evcal package the sim backend simulates with "
                   "(e.g. a `git archive` of src/ at a commit, with a COMMIT file naming it); "
                   "default: the installed evcal")
    p.set_defaults(func=cmd_generate)

    p = sub.add_parser("generate-case", help="(internal) simulate one sim case")
    p.add_argument("--case", required=True, help="the case's JSON file, - for stdin")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_generate_case)

    p = sub.add_parser("run", help="run the gap workflow on a split's cases")
    p.add_argument("--data", default=str(DEFAULT_DATA))
    p.add_argument("--split", choices=SPLITS, required=True)
    p.add_argument("--only", default=None, help="comma-separated case ids")
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--seed", type=int, default=0, help="GapConfig.seed (default 0)")
    p.add_argument("--shuffle", type=int, default=None, metavar="SEED",
                   help="run the cases in a seeded random order (a partial run is then a "
                        "fair sample)")
    p.add_argument("--results", required=True, help="JSON lines, appended")
    p.add_argument("--retry-errors", action="store_true",
                   help="run again the cases whose result is an error")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("oracle", help="dev cases simulated with their true maps and "
                       "effects: the base model's own misfit")
    p.add_argument("--data", default=str(DEFAULT_DATA))
    p.add_argument("--only", default=None, help="comma-separated case ids")
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--seeds", type=int, default=3, help="simulation seeds (default 3)")
    p.add_argument("--add", default=None,
                   help="comma-separated effects added at their defaults (e.g. start_reset)")
    p.add_argument("--no-v2e-reset", dest="v2e_reset", action="store_false",
                   help="do not add start_reset to v2e cases (v2e starts every pixel's "
                        "reference at its first frame; added by default)")
    p.add_argument("--no-subframe-motion", dest="subframe_motion", action="store_false",
                   help="drive the simulations by the flow's straight path between frames")
    p.add_argument("--top", type=int, default=3, help="statistics shown per model (3)")
    p.add_argument("--results", default=None,
                   help="JSON lines, appended: per case the truth's gap and per hidden "
                        "effect the gap without it, its gain, what naming needs, visible")
    p.set_defaults(func=cmd_oracle)

    p = sub.add_parser("report", help="score a results file")
    p.add_argument("--results", required=True)
    p.add_argument("--markdown", default=None)
    p.add_argument("--oracle", default=None,
                   help="the oracle's JSON lines (dev): singles split by whether the truth "
                        "reproduces the recording and shows the effect")
    p.add_argument("--json", default=None)
    p.set_defaults(func=cmd_report)
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    rc: int = args.func(args)
    return rc


if __name__ == "__main__":
    sys.exit(main())
