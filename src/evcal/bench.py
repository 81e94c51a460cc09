"""``evcal bench``: speed and memory figures of the core (printed, never asserted).

Synthetic data with realistic shapes: uniformly random events (a worst case for caches) and
random 8-bit frames. Each figure is the best of a few repeats, wall clock, one thread.
"""

from __future__ import annotations

import resource
import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from .accumulate import Accumulator
from .events import EVENTS_DTYPE, SensorSize
from .recording import Frames, Recording

if TYPE_CHECKING:
    from .online import OnEIConfig
from .stream import frame_cuts, frame_intervals


def _best(fn: Callable[[], Any], repeat: int = 3) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return float(best)


def random_events(sensor: SensorSize, n: int, duration_us: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENTS_DTYPE)
    ev["t_us"] = np.sort(rng.integers(0, duration_us, n))
    ev["x"] = rng.integers(0, sensor.width, n)
    ev["y"] = rng.integers(0, sensor.height, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


def random_recording(sensor: SensorSize, n_events: int, n_frames: int, frame_rate_hz: float = 25.0,
                     seed: int = 0) -> Recording:
    rng = np.random.default_rng(seed)
    dur = int(n_frames / frame_rate_hz * 1e6)
    t_f = np.rint(np.arange(n_frames) * 1e6 / frame_rate_hz).astype(np.int64)
    base = rng.integers(20, 230, sensor.shape).astype(np.int16)
    imgs = np.clip(base[None] + rng.integers(-15, 16, (n_frames, *sensor.shape)), 1, 254)
    frames = Frames(t_f, imgs.astype(np.uint8), np.zeros(n_frames, np.int64))
    return Recording(sensor, random_events(sensor, n_events, dur, seed), frames)


def bench_accumulation(sensor: SensorSize, n: int) -> dict[str, float]:
    ev = random_events(sensor, n, 10_000_000)
    acc = Accumulator(sensor)
    acc.add(ev[:1000])  # compile
    t_acc = _best(lambda: acc.add(ev))
    idx = ev["y"].astype(np.int64) * sensor.width + ev["x"]

    def floor() -> None:
        np.bincount(ev["y"].astype(np.int64) * sensor.width + ev["x"], minlength=sensor.n_pixels)

    t_floor = _best(floor)
    t_floor_idx = _best(lambda: np.bincount(idx, minlength=sensor.n_pixels))
    return {
        "accumulate_events_per_s": n / t_acc,
        "bincount_floor_events_per_s": n / t_floor,
        "bincount_precomputed_index_events_per_s": n / t_floor_idx,
    }


def bench_offei(sensor: SensorSize, n_frames: int, n_events: int) -> dict[str, float]:
    """OffEI's time beside its floor in the same run: the least data movement any OffEI
    needs -- one bincount over the events (their per-pixel counts), and per frame one read of
    the frame and one write of the per-pixel state a window needs later (counts, last
    polarity, log intensity, usable: 18 bytes a pixel), and one pass over the 16 sums per
    batch of 16 windows."""
    from .offline import OffEIConfig, offei  # noqa: PLC0415

    rec = random_recording(sensor, n_events, n_frames)
    t = _best(lambda: offei(rec, OffEIConfig(log_offset=30.0)), repeat=1)
    n = sensor.n_pixels
    ev = rec.events
    state = np.empty(18 * n, np.uint8)
    src = np.ones(18 * n, np.uint8)
    sums = np.zeros((16, n))

    def floor() -> None:
        np.bincount(ev["y"].astype(np.int64) * sensor.width + ev["x"], minlength=n)
        for k in range(n_frames):
            np.copyto(state, src)
            rec.frames.images[k].sum()
            if k % 16 == 0:
                np.add(sums, 1.0, out=sums)

    t_floor = _best(floor, repeat=1)
    return {"offei_s": t, "floor_s": t_floor}


def bench_event_timing(sensor: SensorSize, n_frames: int, n_events: int) -> dict[str, Any]:
    """``calibrate --event-timing``'s cost beside OffEI's: OffEI of a random recording, then
    its fusion with OffE of the same events (:func:`evcal.fusion.with_event_timing`, OffE
    included), each timed once; and how many pixels were fused (none: the timing is that of
    OffE failing, not of a fusion)."""
    from .fusion import with_event_timing  # noqa: PLC0415
    from .offline import OffEIConfig, offei  # noqa: PLC0415

    rec = random_recording(sensor, n_events, n_frames)
    cfg = OffEIConfig(log_offset=30.0)
    t0 = time.perf_counter()
    cal = offei(rec, cfg)
    t1 = time.perf_counter()
    fused = with_event_timing(rec, cal)
    t2 = time.perf_counter()
    return {"offei_s": t1 - t0, "fusion_s": t2 - t1,
            "fused_pixels": int(fused.diagnostics.extra["fusion"]["pixels"])}


def bench_onei(sensor: SensorSize, n_frames: int, events_per_frame: int,
               config: OnEIConfig | None = None) -> dict[str, float]:
    """Per-frame cost of :meth:`OnlineCalibrator.feed_frame` at the paper's buffer sizes, and
    its floor measured on the same data.

    The frames fed while the large buffer fills are not timed; then every frame closes a small
    buffer and drops the oldest interval, and every ``n_small`` events the system is re-solved.
    ``frame_s_mean`` is the mean over all timed frames, updates included, of the frame's whole
    cost: its interval's events fed (already validated: counted as they come up to the
    horizon of :meth:`evcal.onei.intake.EventIntake.fold_ahead`) and the frame;
    ``path_s_mean`` the mean of the frame's call alone (what a service waits for after a
    frame), ``update_s_median`` the median of that call at the frames that re-solved. The floor of a
    frame is what any implementation must at least do: count the frame's events per pixel
    (``np.bincount`` of their pixel indices, computed from x and y) and move one frame's worth
    of per-pixel state, a copy of the normal equations (16 float64 per pixel).
    """
    from .online import OnEIConfig, OnlineCalibrator  # noqa: PLC0415

    cfg = config or OnEIConfig()
    n_small, n_large = cfg.sizes(sensor)
    warm = int(np.ceil(n_large / events_per_frame)) + 2
    total = warm + n_frames
    rec = random_recording(sensor, events_per_frame * total, total)
    cal = OnlineCalibrator(sensor, cfg)
    frame_s: list[float] = []
    path_s: list[float] = []
    update_s: list[float] = []
    for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
        t0 = time.perf_counter()
        cal.feed_events(chunk, checked=True)
        t1 = time.perf_counter()
        updated = cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        t2 = time.perf_counter()
        if k >= warm:
            frame_s.append(t2 - t0)
            path_s.append(t2 - t1)
            if updated:
                update_s.append(t2 - t1)
    cuts = frame_cuts(rec.events["t_us"], rec.frames.t_us)
    def feed() -> None:  # validate and fold every event (feed_events alone only queues)
        fresh = OnlineCalibrator(sensor, cfg)
        fresh.feed_events(rec.events[: cuts[-1]])
        fresh.feed_frame(int(rec.events["t_us"][cuts[-1] - 1]) + 1, rec.frames.images[0])

    t_feed = _best(feed, 1)
    ev = rec.events[cuts[warm] : cuts[warm + 1]]  # one timed frame's events
    width, n = sensor.width, sensor.n_pixels
    t_count = _best(lambda: np.bincount(ev["y"].astype(np.int64) * width + ev["x"], minlength=n))
    state = np.ones((16, n))
    copy = np.empty_like(state)
    t_copy = _best(lambda: np.copyto(copy, state))
    return {"frame_s_mean": float(np.mean(frame_s)),
            "path_s_mean": float(np.mean(path_s)),
            "floor_s": t_count + t_copy,
            "update_s_median": float(np.median(update_s)) if update_s else float("nan"),
            "updates": len(update_s), "n_small": n_small, "n_large": n_large,
            "buffer_frames": cal.status()["buffer_frames"],
            "buffer_MiB": cal.buffer_bytes / 2**20,
            "state_MiB_per_Mpx": cal.state_bytes / 2**20 / (sensor.n_pixels / 1e6),
            "feed_events_per_s": float(cuts[-1] / t_feed)}


def bench_streaming_offe(sensor: SensorSize, n_events: int, chunk_events: int = 100_000
                         ) -> dict[str, float]:
    """The events-only estimator of the service (:class:`evcal.offe.StreamingOffE`): events
    per second fed in chunks of ``chunk_events`` (a service message's size), and the time of
    one set of maps (:meth:`~evcal.offe.StreamingOffE.calibration`), over 10 s of random
    events."""
    from .offe import StreamingOffE  # noqa: PLC0415

    ev = random_events(sensor, n_events, 10_000_000)
    chunks = [ev[i : i + chunk_events] for i in range(0, ev.size, chunk_events)]
    est = StreamingOffE(sensor)

    def feed() -> None:
        fresh = StreamingOffE(sensor)
        for c in chunks:
            fresh.feed_events(c)
        nonlocal est
        est = fresh

    t_feed = _best(feed, 2)
    t_maps = _best(est.calibration, 2)
    return {"events_per_s": n_events / t_feed, "maps_s": t_maps,
            "state_MiB": sum(a.nbytes for a in est.state_dict().values()) / 2**20}


def run_bench(*, quick: bool = False, progress: bool = True) -> dict[str, Any]:
    """All figures; ``quick`` shrinks the sizes for smoke runs."""
    out: dict[str, Any] = {}

    def say(msg: str) -> None:
        if progress:
            print(f"... {msg}", file=sys.stderr, flush=True)

    from .online import OnEIConfig  # noqa: PLC0415

    davis = SensorSize(260, 346)
    hd = SensorSize(720, 1280)
    n_acc = 2_000_000 if quick else 20_000_000
    say(f"accumulation, {n_acc} events at {davis}")
    acc = bench_accumulation(davis, n_acc)
    out["accumulate_Mev_per_s (346x260)"] = round(acc["accumulate_events_per_s"] / 1e6, 1)
    out["bincount_floor_Mev_per_s (346x260)"] = round(acc["bincount_floor_events_per_s"] / 1e6, 1)
    out["bincount_precomputed_idx_Mev_per_s"] = round(
        acc["bincount_precomputed_index_events_per_s"] / 1e6, 1)
    out["accumulate_vs_floor"] = round(acc["accumulate_events_per_s"]
                                       / acc["bincount_floor_events_per_s"], 2)
    n_frames = 20 if quick else 200
    say(f"OffEI solve at {hd}, {n_frames} frames")
    n_ev = 1_000_000 if quick else 10_000_000
    r_off = bench_offei(hd, n_frames, n_ev)
    out[f"offei_s_vs_floor (1280x720, {n_frames} frames, {n_ev // 1_000_000}M events)"] = (
        f"{r_off['offei_s']:.2f} / {r_off['floor_s']:.2f} = "
        f"{r_off['offei_s'] / r_off['floor_s']:.1f}")
    # OffE needs about 20 events a pixel on most pixels (below): 20 M at 1280x720, the quick
    # run too
    n_et = 20_000_000
    say(f"OffEI and calibrate --event-timing at {hd}, {n_frames} frames, {n_et} events")
    r_et = bench_event_timing(hd, n_frames, n_et)
    out[f"event_timing_vs_offei (1280x720, {n_frames} frames, {n_et // 1_000_000}M events)"] = (
        f"({r_et['offei_s']:.2f} + {r_et['fusion_s']:.2f}) / {r_et['offei_s']:.2f} = "
        f"{(r_et['offei_s'] + r_et['fusion_s']) / r_et['offei_s']:.2f}x, "
        f"{r_et['fused_pixels']} pixels fused")
    for sensor in (davis, hd):
        # a busy scene: each pixel fires about 2 events per frame interval
        epf = 2 * sensor.n_pixels
        say(f"OnEI at {sensor}, paper buffer sizes, {epf} events per frame, one thread")
        r = bench_onei(sensor, 10 if quick else 40, epf, OnEIConfig(threads=1))
        ms, floor = r["frame_s_mean"] * 1e3, r["floor_s"] * 1e3
        out[f"onei_ms_per_frame_vs_floor ({sensor}, one core)"] = (
            f"{ms:.2f} / {floor:.2f} = {ms / floor:.1f}")
        out[f"onei_ms_frame_path ({sensor}, one core)"] = round(r["path_s_mean"] * 1e3, 2)
        out[f"onei_ms_per_update ({sensor}, one core)"] = round(r["update_s_median"] * 1e3, 1)
        n_threads = OnEIConfig().n_threads()
        if n_threads > 1:
            say(f"OnEI at {sensor}, re-solve on {n_threads} threads")
            rt = bench_onei(sensor, 10 if quick else 40, epf)
            out[f"onei_ms_per_frame ({sensor}, {n_threads} threads)"] = round(
                rt["frame_s_mean"] * 1e3, 2)
            out[f"onei_ms_frame_path ({sensor}, {n_threads} threads)"] = round(
                rt["path_s_mean"] * 1e3, 2)
            out[f"onei_ms_per_update ({sensor}, {n_threads} threads)"] = round(
                rt["update_s_median"] * 1e3, 1)
        out[f"onei_buffer_MiB ({sensor}, {r['buffer_frames']} frames)"] = round(
            r["buffer_MiB"], 1)
        out[f"onei_memory_MiB_per_megapixel ({sensor}, buffer and state)"] = round(
            r["state_MiB_per_Mpx"], 1)
        out[f"onei_feed_Mev_per_s ({sensor})"] = round(r["feed_events_per_s"] / 1e6, 1)
    # enough events for OffE's 20 per pixel on about 40 % of the pixels (22 a pixel on
    # average), so that most pixels have the 8 such neighbours OffE compares a pixel with:
    # the quick run too (with 11 a pixel no pixel has)
    n_eo = 20_000_000
    say(f"streaming OffE (events-only cameras) at {hd}, {n_eo} events")
    r_eo = bench_streaming_offe(hd, n_eo)
    out[f"offe_streaming_Mev_per_s ({hd}, 100k-event chunks)"] = round(
        r_eo["events_per_s"] / 1e6, 2)
    out[f"offe_streaming_ms_per_update ({hd})"] = round(r_eo["maps_s"] * 1e3, 1)
    out[f"offe_streaming_state_MiB ({hd})"] = round(r_eo["state_MiB"], 1)
    from .sim.bench import bench_simulator  # noqa: PLC0415

    for effects in (False, True):
        name = "simulator_with_effects" if effects else "simulator_ideal"
        say(f"{name.replace('_', ' ')} at 346x260")
        sim = bench_simulator(duration_s=0.25 if quick else 1.0, with_effects=effects)
        out[f"{name}_Mev_per_s (346x260)"] = round(sim["events_per_s"] / 1e6, 2)
    out["peak_rss_MiB"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return out
