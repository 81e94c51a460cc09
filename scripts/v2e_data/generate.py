#!/usr/bin/env python3
"""Generate evcal's independent v2e test recordings (tests/data/v2e/).

Run with the v2e venv's python (see README.md beside this file), e.g.::

    nice -n 10 /work/v2e-venv/bin/python scripts/v2e_data/generate.py \
        --v2e /work/v2e-src --out tests/data/v2e

Our own scenes (gray textures moved fast, with pauses) are rendered at ``--rate`` Hz and fed,
frame by frame, to v2e's ``EventEmulator`` (imported from the v2e checkout given by ``--v2e`` /
``$V2E_SRC``; no v2e code is copied here). APS frames are the same scene rendered at 25 Hz and
quantised to uint8. Each recording is an evcal ``.npz`` recording (event columns
``t_us, x, y, p``) plus truth maps under extra keys, written byte-reproducibly (fixed zip
member dates), and listed in ``manifest.json`` with its sha256.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import logging
import math
import os
import platform
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np

PINNED_V2E_COMMIT = "cac638444557a224ba6ee5c29260916f152c00bd"
GENERATOR_VERSION = 1

# Sensor and timing ------------------------------------------------------------------------
WIDTH, HEIGHT = 64, 48
DURATION_S = 3.0
RATE_HZ = 2000               # v2e input frames per second (one emulator step = 500 us)
APS_PERIOD_US = 40000        # 25 Hz APS frames
APS_PHASE_US = 230           # APS frame m at m * 40 ms + 230 us: inside a v2e step, no tie with
                             # any v2e event time (see README)
DN_LO, DN_HI = 25.0, 235.0   # scene intensity range (DN); > 20 DN keeps v2e's lin_log in ln()
LIN_LOG_THRESHOLD_DN = 20.0  # v2ecore/emulator_utils.py lin_log(x, threshold=20)

# Motion: still / moving segments (s). Pauses 0.4, 0.5, 0.5 s.
SEGMENTS = (("still", 0.0, 0.4), ("move", 0.4, 1.2), ("still", 1.2, 1.7),
            ("move", 1.7, 2.5), ("still", 2.5, 3.0))

# Scenes: skimage.data image, texture pixels per sensor pixel, peak speed (sensor px / s),
# peak rotation rate (rad / s), peak zoom rate (1 / s), motion seed, v2e emulator seed.
SCENES = {
    "camera":    dict(image="camera",    scale=2.0, speed=260.0, spin=0.8, zoom=0.25,
                      motion_seed=11, emulator_seed=1001),
    "astronaut": dict(image="astronaut", scale=2.0, speed=220.0, spin=1.2, zoom=0.35,
                      motion_seed=22, emulator_seed=1002),
    "coffee":    dict(image="coffee",    scale=3.0, speed=300.0, spin=0.5, zoom=0.20,
                      motion_seed=33, emulator_seed=1003),
    "gravel":    dict(image="gravel",    scale=1.5, speed=200.0, spin=0.6, zoom=0.30,
                      motion_seed=44, emulator_seed=1004),
}

# Emulator parameters per case: every EventEmulator argument that shapes events, explicit.
# (The constructor's own defaults are NOT "off": leak_rate_hz=0.1 Hz by default.)
_BASE = dict(pos_thres=0.2, neg_thres=0.2, sigma_thres=0.03, cutoff_hz=0.0, leak_rate_hz=0.0,
             refractory_period_s=0.0, shot_noise_rate_hz=0.0, photoreceptor_noise=False,
             leak_jitter_fraction=0.1, noise_rate_cov_decades=0.1)
CASES = {
    "none":       dict(_BASE),
    "leak":       dict(_BASE, leak_rate_hz=1.0),
    "refractory": dict(_BASE, refractory_period_s=0.002),
    "shot_noise": dict(_BASE, shot_noise_rate_hz=2.0),
    "cutoff":     dict(_BASE, cutoff_hz=30.0),
    # v2e's 'noisy' preset (EventEmulator.set_dvs_params('noisy')) plus a 1 ms refractory period
    "mix":        dict(_BASE, sigma_thres=0.05, cutoff_hz=30.0, leak_rate_hz=0.1,
                       shot_noise_rate_hz=5.0, refractory_period_s=0.001),
}

log = logging.getLogger("v2e_data")


# Scenes ----------------------------------------------------------------------------------

def load_texture(name: str, scale: float) -> np.ndarray:
    """Gray texture in [0, 1] (float32), low-passed so that one sensor pixel (``scale``
    texture pixels) does not alias, percentile-stretched."""
    import cv2
    import skimage.data
    from skimage.color import rgb2gray

    img = getattr(skimage.data, name)()
    g = rgb2gray(img) if img.ndim == 3 else img.astype(np.float64) / 255.0
    g = cv2.GaussianBlur(g.astype(np.float32), (0, 0), sigmaX=0.6 * scale,
                         borderType=cv2.BORDER_REFLECT_101)
    lo, hi = np.percentile(g, [1.0, 99.0])
    return np.clip((g - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def motion_profile(scene: dict, t: np.ndarray) -> dict[str, np.ndarray]:
    """Pose (translation in sensor px, rotation rad, log zoom) at times ``t`` (s).

    Velocities are smooth (sin^2 envelope per moving segment, exactly 0 in the pauses) with
    a direction that turns at a random, slowly varying rate; the pose is their integral
    (cumulative sum on the fine grid ``t``, which must be uniform)."""
    rng = np.random.default_rng(scene["motion_seed"])
    dt = float(t[1] - t[0])
    vx = np.zeros_like(t)
    vy = np.zeros_like(t)
    w = np.zeros_like(t)
    z = np.zeros_like(t)
    for kind, t0, t1 in SEGMENTS:
        if kind != "move":
            continue
        m = (t >= t0) & (t < t1)
        u = (t[m] - t0) / (t1 - t0)
        env = np.sin(np.pi * u) ** 2
        heading0 = rng.uniform(0, 2 * np.pi)
        turn = rng.uniform(-1.0, 1.0, 3)   # turning-rate harmonics (rad per segment)
        heading = heading0 + sum(turn[k] * np.pi * np.sin((k + 1) * np.pi * u)
                                 for k in range(3))
        speed = scene["speed"] * (0.8 + 0.4 * rng.random())
        vx[m] = speed * env * np.cos(heading)
        vy[m] = speed * env * np.sin(heading)
        w[m] = scene["spin"] * env * np.sin(2 * np.pi * u + rng.uniform(0, 2 * np.pi))
        z[m] = scene["zoom"] * env * np.sin(2 * np.pi * u + rng.uniform(0, 2 * np.pi))
    # pose at t[i] = integral of velocity over [t[0], t[i]] (trapezoid)
    def integ(v):
        out = np.zeros_like(v)
        out[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)
        return out
    return dict(tx=integ(vx), ty=integ(vy), rot=integ(w), logzoom=integ(z),
                speed=np.hypot(vx, vy))


class Renderer:
    """Scene intensity (DN, float64) on the sensor grid at a pose."""

    def __init__(self, texture: np.ndarray, scale: float):
        self.tex = texture
        self.scale = scale
        th, tw = texture.shape
        self.centre = np.array([tw / 2.0, th / 2.0])

    def __call__(self, tx: float, ty: float, rot: float, logzoom: float) -> np.ndarray:
        import cv2
        s = self.scale * math.exp(-logzoom)   # texture px per sensor px
        c, sn = math.cos(rot), math.sin(rot)
        a = s * np.array([[c, -sn], [sn, c]])
        # sensor pixel centre (u, v) -> texture point centre + a @ ((u, v) - sensor centre)
        # + texture shift; the sensor moves over the texture, so the image moves by -t.
        sc = np.array([(WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0])
        off = self.centre + self.scale * np.array([tx, ty]) - a @ sc
        m = np.hstack([a, off[:, None]]).astype(np.float64)
        g = cv2.warpAffine(self.tex, m, (WIDTH, HEIGHT),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REFLECT_101)
        return DN_LO + (DN_HI - DN_LO) * g.astype(np.float64)


# v2e -------------------------------------------------------------------------------------

def import_v2e(v2e_path: str):
    sys.path.insert(0, v2e_path)
    from v2ecore.emulator import EventEmulator  # noqa: E402
    for name in ("v2ecore.emulator", "v2ecore.emulator_utils"):
        logging.getLogger(name).setLevel(logging.ERROR)  # per-step "no signal events" chatter
    return EventEmulator


def v2e_commit(v2e_path: str) -> str:
    try:
        return subprocess.run(["git", "-C", v2e_path, "rev-parse", "HEAD"], check=True,
                              capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run_emulator(EventEmulator, params: dict, seed: int, frames, times):
    """Feed ``frames`` (iterable of (H, W) float64 DN) at ``times`` (s); return events
    (N, 4) float64 rows [t_s, x, y, p=+-1] and the initialised emulator."""
    emu = EventEmulator(**params, seed=seed, device="cpu", output_width=WIDTH,
                        output_height=HEIGHT)
    chunks = []
    for img, t in zip(frames, times, strict=True):
        ev = emu.generate_events(img, float(t))
        if ev is not None and len(ev):
            chunks.append(np.asarray(ev, dtype=np.float64))
    ev = np.concatenate(chunks) if chunks else np.zeros((0, 4))
    return ev, emu


def emulator_params(emu) -> dict:
    """What the emulator actually used (read back from the object)."""
    return dict(pos_thres_nominal=emu.pos_thres_nominal, neg_thres_nominal=emu.neg_thres_nominal,
                sigma_thres=emu.sigma_thres, cutoff_hz=emu.cutoff_hz,
                leak_rate_hz=emu.leak_rate_hz, refractory_period_s=emu.refractory_period_s,
                shot_noise_rate_hz=emu.shot_noise_rate_hz,
                photoreceptor_noise=emu.photoreceptor_noise,
                leak_jitter_fraction=emu.leak_jitter_fraction,
                noise_rate_cov_decades=emu.noise_rate_cov_decades,
                SHOT_NOISE_INTEN_FACTOR=emu.SHOT_NOISE_INTEN_FACTOR,
                hdr=emu.log_input, scidvs=emu.scidvs, csdvs=emu.csdvs_enabled,
                device=str(emu.device))


# Output ----------------------------------------------------------------------------------

def write_npz_reproducible(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez_compressed's layout with fixed member dates, so that equal arrays give
    byte-equal files (np.load reads it like any .npz)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for key, arr in arrays.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            data = io.BytesIO()
            np.lib.format.write_array(data, np.asanyarray(arr), allow_pickle=False)
            zf.writestr(info, data.getvalue(), compresslevel=9)
    path.write_bytes(buf.getvalue())


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def generate_one(EventEmulator, case: str, scene_name: str, out: Path, commit: str,
                 duration_s: float, rate_hz: int) -> dict:
    scene = SCENES[scene_name]
    params = CASES[case]
    n_steps = int(round(duration_s * rate_hz))
    t = np.arange(n_steps + 1) / rate_hz                    # v2e input times, s
    pose = motion_profile(scene, t)
    render = Renderer(load_texture(scene["image"], scene["scale"]), scene["scale"])

    def frames():
        for i in range(t.size):
            yield render(pose["tx"][i], pose["ty"][i], pose["rot"][i], pose["logzoom"][i])

    # the intensity range v2e saw (for the lin-log check) is tracked while feeding
    seen = {"min": np.inf, "max": -np.inf}

    def tracked():
        for img in frames():
            seen["min"] = min(seen["min"], float(img.min()))
            seen["max"] = max(seen["max"], float(img.max()))
            yield img

    t0 = time.time()
    ev, emu = run_emulator(EventEmulator, params, scene["emulator_seed"], tracked(), t)
    wall = time.time() - t0

    # events: float32 seconds -> integer us (nearest), stable sort (v2e's order is kept
    # within a timestamp; it is already non-decreasing, the sort is a safeguard)
    t_us = np.rint(ev[:, 0] * 1e6).astype(np.int64)
    order = np.argsort(t_us, kind="stable")
    n_reordered = int(np.count_nonzero(order != np.arange(order.size)))
    t_us = t_us[order]
    x = ev[order, 1].astype(np.int64)
    y = ev[order, 2].astype(np.int64)
    p = ev[order, 3]
    assert np.all((x >= 0) & (x < WIDTH) & (y >= 0) & (y < HEIGHT))
    assert set(np.unique(p).tolist()) <= {-1.0, 1.0}

    # APS frames: the scene rendered at m * 40 ms + phase, interpolating the pose linearly
    # between the fine grid's samples (exact in the pauses), quantised to uint8.
    aps_t_us = np.arange(APS_PHASE_US, int(duration_s * 1e6), APS_PERIOD_US, dtype=np.int64)
    aps = np.empty((aps_t_us.size, HEIGHT, WIDTH), np.uint8)
    for m, tu in enumerate(aps_t_us):
        ts = tu * 1e-6
        args = [np.interp(ts, t, pose[k]) for k in ("tx", "ty", "rot", "logzoom")]
        aps[m] = np.clip(np.rint(render(*args)), 0, 255).astype(np.uint8)

    n_ties = int(np.count_nonzero(np.isin(t_us, aps_t_us)))

    # truth: v2e's per-pixel thresholds after initialisation
    pos = emu.pos_thres.cpu().numpy().astype(np.float64) if hasattr(emu.pos_thres, "cpu") \
        else np.full((HEIGHT, WIDTH), float(emu.pos_thres))
    neg = emu.neg_thres.cpu().numpy().astype(np.float64) if hasattr(emu.neg_thres, "cpu") \
        else np.full((HEIGHT, WIDTH), float(emu.neg_thres))
    truth_c = ((pos + neg) / 2).astype(np.float32)
    truth_b = ((pos - neg) / 2).astype(np.float32)
    log_offset_ok = seen["min"] > LIN_LOG_THRESHOLD_DN
    truth_offset = np.zeros((HEIGHT, WIDTH), np.float32) if log_offset_ok else \
        np.full((HEIGHT, WIDTH), np.nan, np.float32)
    arrays_extra = {}
    if params["leak_rate_hz"] > 0:
        arrays_extra["truth_leak_rate_hz"] = (
            params["leak_rate_hz"] * emu.noise_rate_array.cpu().numpy()).astype(np.float32)

    name = f"{case}_{scene_name}"
    moving = [[a, b] for k, a, b in SEGMENTS if k == "move"]
    still = [[a, b] for k, a, b in SEGMENTS if k == "still"]
    n_on = int(np.count_nonzero(p > 0))
    meta = {
        "generator": "scripts/v2e_data/generate.py",
        "generator_version": GENERATOR_VERSION,
        "simulator": "v2e (github SensorsINI/v2e), v2ecore.emulator.EventEmulator",
        "v2e_commit": commit,
        "case": case,
        "scene": scene_name,
        "scene_params": {**scene, "source": f"skimage.data.{scene['image']}() gray",
                         "dn_range": [DN_LO, DN_HI], "moving_s": moving, "still_s": still,
                         "peak_speed_px_s": float(pose["speed"].max())},
        "seed": scene["emulator_seed"],
        "motion_seed": scene["motion_seed"],
        "emulator_args": {**params, "seed": scene["emulator_seed"], "device": "cpu"},
        "emulator_params": emulator_params(emu),
        "input_rate_hz": rate_hz,
        "duration_s": duration_s,
        "aps": {"rate_hz": 1e6 / APS_PERIOD_US, "phase_us": APS_PHASE_US, "exposure_us": 0,
                "note": "instantaneous render of the scene at frame_t_us, rounded to uint8; "
                        "no read noise, no blur"},
        "events": {"t_us": "round(v2e float32 seconds * 1e6)", "p": "+1 ON, -1 OFF",
                   "n": int(t_us.size), "n_on": n_on, "n_off": int(t_us.size - n_on),
                   "reordered_by_sort": n_reordered,
                   "at_frame_times": n_ties},
        "truth": {
            "keys": ["truth_contrast", "truth_bias", "truth_log_offset"]
                    + sorted(arrays_extra),
            "contrast": "(pos_thres + neg_thres) / 2 of v2e, float32 [H, W]",
            "bias": "(pos_thres - neg_thres) / 2 of v2e, float32 [H, W]",
            "model": "ON when log I rises by c + b, OFF when it falls by c - b",
            "log_offset": 0.0 if log_offset_ok else None,
            "log_offset_note": ("v2e's lin_log is ln(I) above 20 DN (linear below); every "
                                "input intensity was above 20 DN, so L = log(I + 0)"
                                if log_offset_ok else "some pixels were in lin_log's linear "
                                "part (<= 20 DN): offset map NaN"),
            "input_dn_min": seen["min"], "input_dn_max": seen["max"],
            "contrast_mean": float(truth_c.mean()), "contrast_std": float(truth_c.std()),
            "bias_mean": float(truth_b.mean()), "bias_std": float(truth_b.std()),
        },
        "sensor": {"width": WIDTH, "height": HEIGHT},
    }
    arrays = {
        "t_us": t_us,
        "x": x.astype(np.uint16),
        "y": y.astype(np.uint16),
        "p": p.astype(np.int8),
        "frame_t_us": aps_t_us,
        "frame_images": aps,
        "frame_exposure_us": np.zeros(aps_t_us.size, np.int64),
        "sensor": np.array([HEIGHT, WIDTH], np.int64),
        "metadata_json": np.array(json.dumps(meta, sort_keys=True)),
        "truth_contrast": truth_c,
        "truth_bias": truth_b,
        "truth_log_offset": truth_offset,
        **arrays_extra,
    }
    path = out / f"{name}.npz"
    write_npz_reproducible(path, arrays)
    entry = {
        "file": path.name, "case": case, "scene": scene_name,
        "emulator_seed": scene["emulator_seed"], "motion_seed": scene["motion_seed"],
        "params": params, "n_events": int(t_us.size), "n_on": n_on,
        "n_off": int(t_us.size - n_on), "events_at_frame_times": n_ties,
        "n_frames": int(aps.shape[0]),
        "duration_s": duration_s, "bytes": path.stat().st_size, "sha256": sha256(path),
    }
    log.info("%-22s %7d events (%5.1f%% ON) %3d frames %7.0f kB  v2e %.1f s", path.name,
             t_us.size, 100.0 * n_on / max(1, t_us.size), aps.shape[0],
             entry["bytes"] / 1e3, wall)
    return entry


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--v2e", default=os.environ.get("V2E_SRC", "/work/v2e-src"),
                    help="v2e checkout (default $V2E_SRC or /work/v2e-src)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[2]
                                         / "tests" / "data" / "v2e"))
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--scenes", nargs="*", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--duration", type=float, default=DURATION_S)
    ap.add_argument("--rate", type=int, default=RATE_HZ)
    ap.add_argument("--allow-other-commit", action="store_true",
                    help="run although the v2e checkout is not the pinned commit")
    ap.add_argument("--no-manifest", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    import torch
    torch.set_num_threads(1)
    commit = v2e_commit(args.v2e)
    if commit != PINNED_V2E_COMMIT and not args.allow_other_commit:
        log.error("v2e at %s is %s, not the pinned %s (--allow-other-commit to run anyway)",
                  args.v2e, commit, PINNED_V2E_COMMIT)
        return 2
    EventEmulator = import_v2e(args.v2e)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    entries = [generate_one(EventEmulator, case, scene, out, commit, args.duration, args.rate)
               for case in args.cases for scene in args.scenes]
    if not args.no_manifest:
        import cv2
        import skimage
        manifest = {
            "description": "v2e-simulated test recordings with truth maps; "
                           "see scripts/v2e_data/README.md",
            "generator": "scripts/v2e_data/generate.py",
            "generator_version": GENERATOR_VERSION,
            "v2e_commit": commit,
            "command": " ".join([Path(sys.executable).name, *sys.argv]),
            "versions": {"python": platform.python_version(), "numpy": np.__version__,
                         "torch": torch.__version__, "opencv": cv2.__version__,
                         "scikit-image": skimage.__version__},
            "sensor": {"width": WIDTH, "height": HEIGHT},
            "duration_s": args.duration, "input_rate_hz": args.rate,
            "aps_rate_hz": 1e6 / APS_PERIOD_US, "aps_phase_us": APS_PHASE_US,
            "segments": [list(s) for s in SEGMENTS],
            "cases": CASES, "scenes": SCENES,
            "recordings": entries,
            "total_bytes": int(sum(e["bytes"] for e in entries)),
        }
        (out / "manifest.json").write_text(json.dumps(manifest, indent=1, sort_keys=False)
                                           + "\n")
    log.info("total %.2f MB in %d recordings", sum(e["bytes"] for e in entries) / 1e6,
             len(entries))
    return 0


if __name__ == "__main__":
    sys.exit(main())
