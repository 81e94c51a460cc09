#!/usr/bin/env python3
"""Speed of evcal's event simulator beside v2e's EventEmulator, on the same input.

What it measures: for each sensor size, one sequence of input intensity images (a photo from
``skimage.data`` moved by a camera trajectory, rendered by ``evcal.sim.sources.MovingScene``
at ``--rate`` Hz, 25..235 DN) is rendered ONCE and written to an ``.npy`` in a temp dir. Both
simulators then read those same frames from memory:

- evcal: ``evcal.sim.nonideal.simulate`` driven by a source that copies the pre-rendered
  frames (numba kernel, one thread), case ``ideal`` (threshold mismatch only) and ``noisy``
  (refractory + shot noise + leak + bandwidth);
- v2e: ``v2ecore.emulator.EventEmulator.generate_events(frame, t)`` called frame by frame as
  scripts/v2e_data/generate.py does (CPU, no SuperSloMo, under ``torch.no_grad()`` as v2e.py
  does), with torch limited to 1 thread and to 2 threads, same two cases.

Rendering the input is timed on its own, and so is each side's feeding of the frames (copy
into evcal's step blocks; float64 conversion for v2e), so the "emu" figures compare emulator
with emulator. Figures per run: wall seconds (feed + emulation), emulation seconds, input
frames/s, megapixel-steps/s (pixels x input samples / emulation second), events, events/s,
and the evcal/v2e speed ratio (v2e emulation time / evcal emulation time). No pass/fail.
"emu cpu s" is the process CPU time of the emulation: on a busy machine it is steadier than
wall time (for v2e on 2 threads it includes OpenMP's spin-waiting). The machine's load
average is printed with the figures: on a busy machine they are noisy.

The v2e part runs in v2e's own venv as a subprocess of this same file (``--worker-v2e``);
v2e comes from a checkout outside the repository (see scripts/v2e_data/README.md). If v2e is
not available the script says so and prints evcal's figures only (exit 0).

Run with evcal's venv::

    . .venv/bin/activate
    python scripts/bench_sim_vs_v2e.py                                  # 346x260 and 240x180, 2 s
    python scripts/bench_sim_vs_v2e.py --sizes 346x260 --duration 2
    python scripts/bench_sim_vs_v2e.py --sizes 240x180 --duration 3 --json out.json
    python scripts/bench_sim_vs_v2e.py --v2e-python /work/v2e-venv/bin/python --v2e /work/v2e-src

``--v2e-python`` / ``--v2e`` default to ``$V2E_PYTHON`` / ``$V2E_SRC``, else
``/work/v2e-venv/bin/python`` / ``/work/v2e-src``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEFAULT_SIZES = ("346x260", "240x180")
DN_LO, DN_HI = 25.0, 235.0   # > 20 DN: v2e's lin_log is ln(I) there, evcal uses log(I + 0)

# Effects of the "noisy" case, in v2e's terms (mapped to evcal's effects in evcal_effects).
# The refractory period is > one input step (1 ms at 1 kHz) so that v2e applies it in every
# step (it does only when the period exceeds its timestamp step dt / N).
NOISY = dict(refractory_s=0.002, shot_noise_hz=5.0, leak_hz=0.1, cutoff_hz=100.0)
THRES, SIGMA_THRES = 0.2, 0.03   # v2e: ON and OFF thresholds drawn N(0.2, 0.03) each


# v2e side (runs in v2e's venv: numpy and the standard library only at module level) --------

def v2e_params(case: str) -> dict:
    """EventEmulator arguments for a case, every argument that shapes events explicit (the
    constructor's defaults are not "off": leak_rate_hz=0.1)."""
    p = dict(pos_thres=THRES, neg_thres=THRES, sigma_thres=SIGMA_THRES, cutoff_hz=0.0,
             leak_rate_hz=0.0, refractory_period_s=0.0, shot_noise_rate_hz=0.0,
             photoreceptor_noise=False, leak_jitter_fraction=0.1, noise_rate_cov_decades=0.1)
    if case == "noisy":
        p.update(cutoff_hz=NOISY["cutoff_hz"], leak_rate_hz=NOISY["leak_hz"],
                 refractory_period_s=NOISY["refractory_s"],
                 shot_noise_rate_hz=NOISY["shot_noise_hz"])
    return p


def _v2e_run(EventEmulator, torch, frames: np.ndarray, rate_hz: float, case: str,
             n_frames: int | None = None) -> dict:
    h, w = frames.shape[1:]
    n = frames.shape[0] if n_frames is None else min(n_frames, frames.shape[0])
    # the CPU time of feeding alone, from a pass that only converts (reading the process
    # clock per frame would itself cost more than a small frame's conversion)
    c0 = time.process_time()
    for k in range(n):
        np.asarray(frames[k], np.float64)
    feed_cpu = time.process_time() - c0
    feed = emu_s = 0.0
    n_ev = 0
    t_all = time.perf_counter()
    c_all = time.process_time()
    with torch.no_grad():
        t0 = time.perf_counter()
        emu = EventEmulator(**v2e_params(case), seed=1, device="cpu", output_width=w,
                            output_height=h)
        emu_s += time.perf_counter() - t0
        for k in range(n):
            t0 = time.perf_counter()
            img = np.asarray(frames[k], np.float64)   # as generate.py feeds it
            t1 = time.perf_counter()
            ev = emu.generate_events(img, k / rate_hz)
            if ev is not None:
                n_ev += len(ev)
            t2 = time.perf_counter()
            feed += t1 - t0
            emu_s += t2 - t1
    cpu = time.process_time() - c_all
    return dict(wall_s=time.perf_counter() - t_all, feed_s=feed, emu_s=emu_s,
                emu_cpu_s=cpu - feed_cpu, n_events=int(n_ev), n_frames=int(n))


def v2e_worker(args: argparse.Namespace) -> int:
    """Run v2e on the frames in ``args.frames``; write a JSON result to ``args.json_out``."""
    import logging
    import subprocess as sp

    threads = int(args.threads)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    import torch

    torch.set_num_threads(threads)
    sys.path.insert(0, args.v2e)
    from v2ecore.emulator import EventEmulator

    for name in ("v2ecore.emulator", "v2ecore.emulator_utils"):
        logging.getLogger(name).setLevel(logging.ERROR)   # per-step chatter
    try:
        commit = sp.run(["git", "-C", args.v2e, "rev-parse", "HEAD"], check=True,
                        capture_output=True, text=True).stdout.strip()
    except (OSError, sp.CalledProcessError):
        commit = "unknown"
    t0 = time.perf_counter()
    frames = np.load(args.frames)
    load_s = time.perf_counter() - t0
    warm = _v2e_run(EventEmulator, torch, frames, args.rate, "noisy", n_frames=50)
    runs = []
    for case in args.cases:
        best = None
        for _ in range(args.repeats):
            r = _v2e_run(EventEmulator, torch, frames, args.rate, case)
            if best is None or r["emu_s"] < best["emu_s"]:
                best = r
        assert best is not None
        runs.append(dict(best, side="v2e", case=case, threads=threads,
                         params=v2e_params(case)))
    out = dict(v2e_commit=commit, torch=torch.__version__, numpy=np.__version__,
               torch_threads=torch.get_num_threads(), load_s=load_s,
               warmup_s=warm["wall_s"], runs=runs)
    Path(args.json_out).write_text(json.dumps(out))
    return 0


# evcal side (evcal's venv) ----------------------------------------------------------------

def render_input(path: Path, width: int, height: int, duration_s: float, rate_hz: float,
                 scene: str, speed: float, seed: int) -> tuple[np.ndarray, dict]:
    """The input: ``scene`` moved by a trajectory, at ``k / rate_hz`` (k = 0..N), float32
    [N + 1, H, W] DN; written to ``path``. Returns the frames and the timing."""
    from evcal.sim.scene import Trajectory
    from evcal.sim.sources import MovingScene

    n = int(round(duration_s * rate_hz)) + 1
    src = MovingScene(scene, (height, width), Trajectory(pan_px=40.0, speed=speed, seed=seed),
                      min_dn=DN_LO, max_dn=DN_HI)
    src.render_block([0.0, 1.0 / rate_hz])            # JIT warm-up, not timed
    frames = np.empty((n, height, width), np.float32)
    t0 = time.perf_counter()
    for k in range(0, n, 64):
        kk = min(64, n - k)
        src.render_block(np.arange(k, k + kk) / rate_hz, out=frames[k:k + kk])
    render_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    np.save(path, frames)
    save_s = time.perf_counter() - t0
    return frames, dict(render_s=render_s, save_s=save_s, n_frames=n,
                        mb=frames.nbytes / 1e6)


class PrerenderedSource:
    """An evcal source over pre-rendered frames at ``k / rate_hz``; times the copying."""

    def __init__(self, frames: np.ndarray, rate_hz: float):
        self.frames = frames
        self.rate_hz = rate_hz
        self.feed_s = 0.0
        self.feed_cpu_s = 0.0

    def _index(self, t_s: np.ndarray) -> np.ndarray:
        return np.rint(np.asarray(t_s, np.float64) * self.rate_hz).astype(np.int64)

    def __call__(self, t_s: float) -> np.ndarray:
        result: np.ndarray = self.frames[int(self._index(np.array([t_s]))[0])]
        return result

    def render_block(self, t_s: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        t0, c0 = time.perf_counter(), time.process_time()
        idx = self._index(t_s)
        if out is None:
            out = self.frames[idx]
        else:
            np.take(self.frames, idx, axis=0, out=out)
        self.feed_s += time.perf_counter() - t0
        self.feed_cpu_s += time.process_time() - c0
        return out


def evcal_effects(case: str) -> list:
    """evcal effects comparable with v2e's ``noisy`` case (none for ``ideal``)."""
    from evcal.sim.effects import Bandwidth, Leak, Refractory, ShotNoise

    if case == "ideal":
        return []
    return [
        # v2e holds a blocked event back until the period is over: evcal's "delay" mode
        Refractory(period_us=NOISY["refractory_s"] * 1e6, mode="delay"),
        # v2e's rate falls about 4x from black to white (exponent ~0.6); rate at mid-gray
        ShotNoise(rate_hz=NOISY["shot_noise_hz"], ref_dn=128.0, light_exponent=0.6),
        # v2e: log-normal spread of 0.1 decade = 0.23 in ln
        Leak(rate_hz=NOISY["leak_hz"], spread_log=0.1 * np.log(10.0)),
        # v2e's cutoff is cutoff_hz * (I + 20) / 275; evcal's cutoff_hz * (I + offset) / ref
        Bandwidth(cutoff_hz=NOISY["cutoff_hz"], ref_dn=275.0),
    ]


def _evcal_config(height: int, width: int, duration_s: float, rate_hz: float):
    from evcal.sim.ideal import SimConfig

    # c = (on + off) / 2, b = (on - off) / 2 of two independent N(0.2, 0.03): std 0.03 / sqrt 2
    return SimConfig(height=height, width=width, duration_s=duration_s,
                     internal_rate_hz=rate_hz, frame_rate_hz=min(25.0, rate_hz),
                     contrast_mean=THRES, contrast_std=SIGMA_THRES / np.sqrt(2),
                     bias_mean=0.0, bias_std=SIGMA_THRES / np.sqrt(2), log_offset=0.0,
                     seed=1)


def _evcal_run(frames: np.ndarray, rate_hz: float, case: str) -> dict:
    from evcal.recording import Frames
    from evcal.sim.nonideal import simulate

    n, h, w = frames.shape
    cfg = _evcal_config(h, w, (n - 1) / rate_hz, rate_hz)
    times = np.rint(np.arange(n) * 1e6 / rate_hz).astype(np.int64)
    src = PrerenderedSource(frames, rate_hz)
    t0, c0 = time.perf_counter(), time.process_time()
    res = simulate(cfg, evcal_effects(case), source=src, times_us=times,
                   frames=Frames.empty(h, w))   # no APS frames: v2e makes none either
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    return dict(wall_s=wall, feed_s=src.feed_s, emu_s=wall - src.feed_s,
                emu_cpu_s=cpu - src.feed_cpu_s, n_events=int(res.recording.n_events),
                n_frames=int(n))


def run_evcal(frames: np.ndarray, rate_hz: float, cases: list[str], repeats: int) -> dict:
    t0 = time.perf_counter()
    for case in cases:   # JIT (numba caches on disk; the first call still loads it)
        _evcal_run(frames[:8], rate_hz, case)
    warm = time.perf_counter() - t0
    runs = []
    for case in cases:
        best = None
        for _ in range(repeats):
            r = _evcal_run(frames, rate_hz, case)
            if best is None or r["emu_s"] < best["emu_s"]:
                best = r
        assert best is not None
        runs.append(dict(best, side="evcal", case=case, threads=1,
                         effects=[type(e).__name__ for e in evcal_effects(case)]))
    return dict(warmup_s=warm, runs=runs)


def run_v2e(v2e_python: str, v2e_src: str, frames_path: Path, rate_hz: float,
            cases: list[str], threads: int, repeats: int, tmp: Path) -> tuple[dict | None, str]:
    """Run this file's v2e worker in v2e's venv; (result, "") or (None, why not)."""
    if not Path(v2e_python).exists():
        return None, f"no v2e python at {v2e_python}"
    if not (Path(v2e_src) / "v2ecore" / "emulator.py").exists():
        return None, f"no v2e checkout at {v2e_src} (v2ecore/emulator.py missing)"
    out = tmp / f"v2e_{frames_path.stem}_{threads}t.json"
    cmd = [v2e_python, str(Path(__file__).resolve()), "--worker-v2e", "--v2e", v2e_src,
           "--frames", str(frames_path), "--rate", str(rate_hz), "--threads", str(threads),
           "--cases", *cases, "--repeats", str(repeats), "--json-out", str(out)]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if proc.returncode != 0 or not out.exists():
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-8:])
        return None, f"v2e worker failed (exit {proc.returncode}):\n{tail}"
    return json.loads(out.read_text()), ""


# report -----------------------------------------------------------------------------------

def _figures(r: dict, h: int, w: int) -> dict:
    steps = r["n_frames"] - 1   # the first frame only initialises both simulators
    return dict(r, frames_per_s=steps / r["emu_s"],
                mpx_steps_per_s=h * w * steps / r["emu_s"] / 1e6,
                events_per_s=r["n_events"] / r["emu_s"])


def print_size_report(size: dict) -> None:
    h, w = size["height"], size["width"]
    inp = size["input"]
    print(f"\n== {w}x{h}, {size['duration_s']:g} s at {size['rate_hz']:g} Hz: "
          f"{inp['n_frames']} input frames ({inp['mb']:.0f} MB float32), "
          f"scene '{size['scene']}' ==")
    print(f"input rendering (evcal MovingScene, done once, not in the figures below): "
          f"{inp['render_s']:.2f} s = {(inp['n_frames']) / inp['render_s']:.0f} frames/s "
          f"(+ {inp['save_s']:.2f} s writing the .npy)")
    hdr = (f"{'simulator':<10} {'case':<6} {'thr':>3} {'wall s':>8} {'feed s':>7} {'emu s':>8} "
           f"{'emu cpu s':>9} {'frames/s':>9} {'Mpx-step/s':>10} {'events':>10} {'Mev/s':>7} "
           f"{'ev/px/s':>8}")
    print(hdr)
    print("-" * len(hdr))
    for r in size["runs"]:
        print(f"{r['side']:<10} {r['case']:<6} {r['threads']:>3} {r['wall_s']:8.2f} "
              f"{r['feed_s']:7.2f} {r['emu_s']:8.2f} {r.get('emu_cpu_s', float('nan')):9.2f} "
              f"{r['frames_per_s']:9.0f} "
              f"{r['mpx_steps_per_s']:10.1f} {r['n_events']:10d} "
              f"{r['events_per_s'] / 1e6:7.2f} "
              f"{r['n_events'] / (h * w * size['duration_s']):8.1f}")
    ev = {r["case"]: r for r in size["runs"] if r["side"] == "evcal"}
    v2 = [r for r in size["runs"] if r["side"] == "v2e"]
    if v2:
        print("speed ratio evcal/v2e (v2e emu s / evcal emu s; > 1: evcal faster):")
        for r in v2:
            e = ev.get(r["case"])
            if e:
                cpu = (r.get("emu_cpu_s", np.nan) / e["emu_cpu_s"]) if e.get("emu_cpu_s") \
                    else np.nan
                print(f"  {r['case']:<6} v2e {r['threads']} thread(s): "
                      f"{r['emu_s'] / e['emu_s']:6.1f}x wall   {cpu:6.1f}x cpu   "
                      f"(events v2e/evcal {r['n_events'] / max(1, e['n_events']):.2f})")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size {text!r} is not WIDTHxHEIGHT") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size {text!r} is too small")
    return w, h


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", type=_size,
                    default=[_size(s) for s in DEFAULT_SIZES], help="WIDTHxHEIGHT ...")
    ap.add_argument("--duration", nargs="+", type=float, default=[2.0],
                    help="seconds of input: one value, or one per size (default 2)")
    ap.add_argument("--rate", type=float, default=1000.0, help="input frames/s (default 1000)")
    ap.add_argument("--scene", default="astronaut", help="skimage.data photo (default astronaut)")
    ap.add_argument("--speed", type=float, default=2.0,
                    help="trajectory speed (evcal Trajectory, pan 40 px; default 2)")
    ap.add_argument("--cases", nargs="+", default=["ideal", "noisy"],
                    choices=["ideal", "noisy"])
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2],
                    help="torch thread counts for v2e (default 1 2)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per figure, best kept")
    ap.add_argument("--v2e-python", default=os.environ.get("V2E_PYTHON",
                                                           "/work/v2e-venv/bin/python"))
    ap.add_argument("--v2e", default=os.environ.get("V2E_SRC", "/work/v2e-src"),
                    help="v2e checkout (default $V2E_SRC or /work/v2e-src)")
    ap.add_argument("--no-v2e", action="store_true", help="evcal's figures only")
    ap.add_argument("--json", help="also write all figures to this JSON file")
    # internal: the v2e worker (run in v2e's venv by the parent)
    ap.add_argument("--worker-v2e", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--frames", help=argparse.SUPPRESS)
    ap.add_argument("--json-out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.repeats = max(1, args.repeats)

    if args.worker_v2e:
        args.threads = args.threads[0]
        return v2e_worker(args)

    if len(args.duration) not in (1, len(args.sizes)):
        ap.error("--duration takes one value or one per size")
    durations = args.duration * len(args.sizes) if len(args.duration) == 1 else args.duration
    load0 = os.getloadavg()
    print(f"evcal simulator vs v2e EventEmulator; {os.cpu_count()} CPUs, "
          f"load average {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}")
    print(f"cases: ideal (threshold mismatch only); noisy (+ refractory "
          f"{NOISY['refractory_s'] * 1e3:g} ms, shot noise {NOISY['shot_noise_hz']:g} Hz, "
          f"leak {NOISY['leak_hz']:g} Hz, cutoff {NOISY['cutoff_hz']:g} Hz)")
    report: dict = dict(load_avg_start=load0, cpus=os.cpu_count(), sizes=[])
    v2e_note = "" if not args.no_v2e else "--no-v2e given"
    v2e_info: dict = {}
    with tempfile.TemporaryDirectory(prefix="bench_sim_vs_v2e_") as td:
        tmp = Path(td)
        for (w, h), dur in zip(args.sizes, durations, strict=True):
            path = tmp / f"frames_{w}x{h}.npy"
            frames, inp = render_input(path, w, h, dur, args.rate, args.scene, args.speed, 0)
            ev = run_evcal(frames, args.rate, args.cases, args.repeats)
            runs = ev["runs"]
            if not v2e_note:
                for thr in args.threads:
                    res, why = run_v2e(args.v2e_python, args.v2e, path, args.rate, args.cases,
                                       thr, args.repeats, tmp)
                    if res is None:
                        v2e_note = why
                        break
                    v2e_info = {k: v for k, v in res.items() if k != "runs"}
                    runs += res["runs"]
            size = dict(width=w, height=h, duration_s=dur, rate_hz=args.rate,
                        scene=args.scene, input=inp, evcal_warmup_s=ev["warmup_s"],
                        runs=[_figures(r, h, w) for r in runs])
            report["sizes"].append(size)
            print_size_report(size)
            del frames
            path.unlink()
    load1 = os.getloadavg()
    report.update(load_avg_end=load1, v2e=v2e_info, v2e_unavailable=v2e_note or None)
    print(f"\nload average at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f} "
          f"({os.cpu_count()} CPUs)")
    if v2e_info:
        print(f"v2e {v2e_info.get('v2e_commit', '?')[:12]} (torch {v2e_info.get('torch')}, "
              f"numpy {v2e_info.get('numpy')}) from {args.v2e}")
    if v2e_note:
        print(f"v2e not run: {v2e_note}\n(evcal's figures only)")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
