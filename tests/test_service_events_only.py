"""Events-only cameras: streaming OffE (offe.StreamingOffE), the camera state machine's
events-only estimate and its move to OnEI, snapshots, and end to end on loopback."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from evcal.accumulate import Accumulator
from evcal.bench import random_events
from evcal.calibration import Special
from evcal.errors import CalibrationError, StateError
from evcal.events import SensorSize
from evcal.io.wire import (
    WireError,
    decode_calibration,
    decode_calibration_maps,
    decode_events,
    decode_frame,
    encode_calibration,
    encode_events,
    encode_frame,
)
from evcal.offe import OffEConfig, StreamingOffE, offe
from evcal.online import OnEIConfig
from evcal.recording import Frames, Recording
from evcal.service.camera import CalibrationUpdate, CameraState
from evcal.service.state import atomic_savez, read_snapshot
from evcal.sim.ideal import SimConfig, simulate_ideal
from evcal.stream import frame_cuts

# as the shared_data fixture (conftest.py), but needed at collection for the EVT 3.0 files
DATA = Path(os.environ.get("EVCAL_SHARED_DATA")
            or Path(__file__).resolve().parents[2] / "shared" / "data")
# the maps a stream gives as the offline OffE does; the errors (and the special pixels judged
# with them) come from the run's parts, halves offline, the stream's mark live
MAPS = ("contrast", "bias", "valid", "reason", "n_events")


def biased_events(sensor: SensorSize, n: int, duration_us: int, seed: int) -> np.ndarray:
    """Random events whose ON fraction differs per pixel (a bias map for OffE to find)."""
    rng = np.random.default_rng(seed)
    ev = random_events(sensor, n, duration_us, seed)
    on_fraction = rng.uniform(0.3, 0.7, sensor.n_pixels)
    pix = ev["y"].astype(np.int64) * sensor.width + ev["x"]
    ev["p"] = np.where(rng.random(n) < on_fraction[pix], 1, -1)
    ev["t_us"] += 1_000_123  # not on the step grid's origin
    return ev


def assert_same_maps(a, b) -> None:
    for k in MAPS:
        np.testing.assert_allclose(getattr(a, k), getattr(b, k), rtol=1e-12, atol=1e-12,
                                   err_msg=k)
    assert a.method == b.method == "offe"
    assert a.diagnostics.n_steps == b.diagnostics.n_steps


# ----------------------------------------------------------------------------- the estimator


@pytest.mark.parametrize("n_chunks", [1, 7, 333])
def test_streaming_equals_offline_offe_in_chunks(n_chunks: int) -> None:
    sensor = SensorSize(height=30, width=40)
    ev = biased_events(sensor, 200_000, 3_000_000, seed=n_chunks)
    # events exactly on a step (and on the last one): they belong after it, as offline
    ev["t_us"][-7:] = ev["t_us"][0] + 3_000_000
    ev["t_us"][1000:1010] = ev["t_us"][0] + 10_000 * 17
    ev.sort(order="t_us", kind="stable")
    ref = offe(Recording(sensor, ev, None))
    st = StreamingOffE(sensor)
    rng = np.random.default_rng(0)
    cuts = np.sort(rng.integers(0, ev.size, n_chunks - 1))
    for chunk in np.split(ev, cuts):  # some chunks empty
        st.feed_events(chunk)
    assert_same_maps(st.calibration(), ref)
    assert st.n_events == ev.size


SUMS = ("e", "p", "ee", "ep", "pp")


def sums_by_steps(rec: Recording, cfg: OffEConfig):
    """OffE's sums by their definition, one step at a time over all pixels (what offe()
    computes event by event): at each step ``t0 + k step_us`` the cumulative count ``E``
    and polarity ``P`` of each pixel (events before the step) and their products, summed;
    the two halves' sums split at the middle step."""
    t = rec.events["t_us"]
    t0 = int(t[0])
    m = -(-(int(t[-1]) - t0) // cfg.step_us)
    steps = t0 + cfg.step_us * np.arange(1, m + 1, dtype=np.int64)
    n = rec.sensor.n_pixels
    acc = Accumulator(rec.sensor)
    half = m // 2
    sums = [{k: np.zeros(n) for k in SUMS} for _ in range(2)]
    n_first = np.zeros(n, np.int64)
    pos = 0
    for i, cut in enumerate(frame_cuts(t, steps)):  # steps cut the stream as frames do
        if cut > pos:
            acc.add(rec.events[pos:cut])
            pos = int(cut)
        e = (acc.on + acc.off).astype(np.float64)
        p = (acc.on - acc.off).astype(np.float64)
        s = sums[int(i >= half)]
        s["e"] += e
        s["p"] += p
        s["ee"] += e * e
        s["ep"] += e * p
        s["pp"] += p * p
        if i == half - 1:
            n_first = (acc.on + acc.off).astype(np.int64)
    n_events = (acc.on + acc.off).astype(np.int64)
    whole = {k: sums[0][k] + sums[1][k] for k in SUMS}
    return whole, m, n_events, ((sums[0], half, n_first), (sums[1], m - half,
                                                          n_events - n_first))


@pytest.mark.parametrize("step_us", [10_000, 7_000])
def test_offline_sums_event_by_event_equal_the_step_definition(step_us: int) -> None:
    """offe() folds the events (each half from its own start, the whole from the halves);
    the sums' definition goes step by step over all pixels. The whole's sums are the same
    integers; a half's regression the same (its sums differ by the counts before it, which
    the intercept absorbs), to rounding. Events on the grid (on the middle step too), a
    short recording, a second half of one event."""
    sensor = SensorSize(height=20, width=30)
    ev = biased_events(sensor, 60_000, 2_345_678, seed=4)
    t0 = int(ev["t_us"][0])
    ev["t_us"][100:200] = t0 + step_us * 3  # on the grid
    ev.sort(order="t_us", kind="stable")
    m = -(-(int(ev["t_us"][-1]) - t0) // step_us)
    ev["t_us"][ev.size // 2: ev.size // 2 + 50] = t0 + step_us * (m // 2)  # the middle step
    ev.sort(order="t_us", kind="stable")
    recs = [Recording(sensor, ev, None),
            Recording(sensor, ev[ev["t_us"] < t0 + step_us * (m // 3)], None)]  # a short one
    first_only = ev[ev["t_us"] < t0 + step_us * (m // 2)].copy()
    first_only[-1]["t_us"] = t0 + step_us * m  # one late event: a second half of one event
    recs.append(Recording(sensor, first_only, None))
    for rec in recs:
        _check_sums(rec, OffEConfig(step_us=step_us))


def _check_sums(rec: Recording, cfg: OffEConfig) -> None:
    from evcal.offe import _sums_by_events  # noqa: PLC0415

    ref, fold = sums_by_steps(rec, cfg), _sums_by_events(rec, cfg)
    assert ref[1] == fold[1]
    for k in ref[0]:
        np.testing.assert_array_equal(ref[0][k], fold[0][k], err_msg=k)
    np.testing.assert_array_equal(ref[2], fold[2])
    for (sa, ma, na), (sb, mb, nb) in zip(ref[3], fold[3], strict=True):
        assert ma == mb
        np.testing.assert_array_equal(na, nb)
        for x, y in (("ee", "e"), ("pp", "p")):
            np.testing.assert_allclose(sa[x] - sa[y] ** 2 / ma, sb[x] - sb[y] ** 2 / mb,
                                       rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(sa["ep"] - sa["e"] * sa["p"] / ma,
                                   sb["ep"] - sb["e"] * sb["p"] / mb, rtol=1e-9, atol=1e-6)


def test_streaming_states_errors_from_its_mark() -> None:
    """A live OffE asked for maps every 0.25 s of sensor time: the first maps state no
    errors (no parts yet), later ones do, read on the run before and after the mark (or,
    while the part after it is short, the model read last); against the truth they spread
    as the offline errors do (4 s, 160x120) and are of the offline size."""
    from evcal.special import classify  # noqa: PLC0415

    sim = simulate_ideal(SimConfig(height=120, width=160, duration_s=4.0, seed=21,
                                   scene="coffee"))
    rec = sim.recording
    c0 = float(np.median(sim.truth["contrast"]))
    st = StreamingOffE(rec.sensor, OffEConfig(c0=c0))
    t = rec.events["t_us"]
    cuts = np.searchsorted(t, np.arange(250_000, int(t[-1]) + 250_000, 250_000))
    cals, pos = [], 0
    for cut in cuts:
        st.feed_events(rec.events[pos:cut])
        pos = int(cut)
        try:
            cals.append(st.calibration())
        except CalibrationError:  # too early: no pixel has enough events yet
            continue
    assert np.isinf(cals[0].stderr_contrast).all()
    stated = [bool(np.isfinite(c.stderr_contrast[c.valid]).any()) for c in cals]
    assert stated[-1]
    assert stated.index(True) <= len(cals) // 2
    assert all(stated[stated.index(True):])  # once read, always stated (the kept model)
    last = cals[-1]
    truth_cls = classify(sim.truth["contrast"], sim.truth["bias"],
                         np.zeros(rec.sensor.shape), np.zeros(rec.sensor.shape),
                         np.ones(rec.sensor.shape, bool))
    m = last.valid & (truth_cls == Special.NORMAL)
    off = offe(rec, OffEConfig(c0=c0))

    def z_spread(cal, key):
        return float(np.std((getattr(cal, key) - sim.truth[key])[m]
                            / getattr(cal, f"stderr_{key}")[m]))

    # here live 0.89 / 1.43, offline 0.93 / 1.57 (this scene's b errors are stated too small
    # offline as well: 0.84-1.56 over the benchmark's scenes)
    for key in ("contrast", "bias"):
        live, offline = z_spread(last, key), z_spread(off, key)
        assert 0.6 < live < 1.8, key
        assert 0.75 < live / offline < 1.33, key
    ratio = np.median(last.stderr_contrast[m]) / np.median(off.stderr_contrast[m])
    assert 0.6 < ratio < 1.6


def test_streaming_equals_offline_on_real_events() -> None:
    path = DATA / "davis346_road" / "road.aedat4"
    if not path.exists():
        pytest.skip(f"{path} is absent (shared real recordings)")
    from evcal.io import open_recording  # noqa: PLC0415

    rec = open_recording(path)
    ref = offe(rec, OffEConfig(step_us=5_000))
    st = StreamingOffE(rec.sensor, OffEConfig(step_us=5_000))
    for chunk in np.array_split(rec.events, 59):
        st.feed_events(chunk)
    assert_same_maps(st.calibration(), ref)


def test_streaming_state_round_trip_and_refusals() -> None:
    sensor = SensorSize(height=12, width=10)
    ev = biased_events(sensor, 40_000, 2_000_000, seed=3)
    a = StreamingOffE(sensor)
    a.feed_events(ev[:15_000])
    b = StreamingOffE.from_state({k: v.copy() for k, v in a.state_dict().items()})
    a.feed_events(ev[15_000:])
    b.feed_events(ev[15_000:])
    assert_same_maps(a.calibration(), b.calibration())
    bad = a.state_dict()
    bad["counts"] = bad["counts"][:-1]
    with pytest.raises(StateError, match=r"counts: int64\(119, 4\), expected "
                                         r"int64\(120, 4\)"):
        StreamingOffE.from_state(bad)
    with pytest.raises(CalibrationError, match="none yet"):
        StreamingOffE(sensor).calibration()


def test_streaming_state_keeps_the_mark_and_reads_a_v1_state() -> None:
    """The mark and the errors' model survive a round trip (the resumed stream states the
    same errors); a state of before the mark (v1: no mark arrays) resumes without one."""
    import json  # noqa: PLC0415

    sim = simulate_ideal(SimConfig(height=48, width=64, duration_s=3.0, seed=8))
    ev = sim.recording.events
    t = ev["t_us"]
    a = StreamingOffE(sim.recording.sensor)
    for cut in np.searchsorted(t, [1_000_000, 2_000_000]):
        a.feed_events(ev[: int(cut)] if a.n_events == 0 else ev[a.n_events: int(cut)])
        a.calibration()  # sets the mark
    state = {k: v.copy() for k, v in a.state_dict().items()}
    b = StreamingOffE.from_state(state)
    a.feed_events(ev[a.n_events:])
    b.feed_events(ev[b.n_events:])
    ca, cb = a.calibration(), b.calibration()
    assert np.isfinite(ca.stderr_contrast[ca.valid]).any()
    np.testing.assert_array_equal(ca.stderr_contrast, cb.stderr_contrast)
    v1 = {k: v for k, v in state.items() if not k.startswith("mark_")}
    sc = json.loads(str(v1["scalars"]))
    sc["format"] = "evcal.offe.streaming.v1"
    del sc["mark_k"], sc["error_model"]
    v1["scalars"] = np.array(json.dumps(sc))
    c = StreamingOffE.from_state(v1)
    c.feed_events(ev[c.n_events:])
    first = c.calibration()
    assert np.isinf(first.stderr_contrast).all()  # no mark yet: set now
    np.testing.assert_array_equal(first.contrast, ca.contrast)


# ----------------------------------------------------------------------------- the camera


def _events_msg(ev: np.ndarray, sensor: SensorSize, seq: int):
    return decode_events(encode_events(ev, height=sensor.height, width=sensor.width, seq=seq))


def test_camera_without_frames_publishes_offe_then_moves_to_onei() -> None:
    sensor = SensorSize(height=36, width=48)
    sim = simulate_ideal(SimConfig(height=36, width=48, duration_s=4.0, seed=2))
    rec = sim.recording
    t_frames_start = int(rec.events["t_us"][0]) + 2_000_000
    cam = CameraState("lab/cam", onei=OnEIConfig(n_small=15_000, n_large=10_000_000,
                                                 window_frames=5), offe_period_us=500_000)
    updates: list[CalibrationUpdate] = []
    seq_ev = seq_fr = 0
    ft = rec.frames.t_us
    chunks = np.split(rec.events, np.searchsorted(rec.events["t_us"], ft, side="left"))
    for i, chunk in enumerate(chunks):
        if chunk.size:
            out = cam.on_events(_events_msg(chunk, sensor, seq_ev), 100, now_s=0.0)
            seq_ev += 1
            updates += [o for o in out if isinstance(o, CalibrationUpdate)]
        if i < len(ft) and ft[i] >= t_frames_start:
            msg = encode_frame(int(ft[i]), rec.frames.images[i], exposure_us=0, seq=seq_fr)
            seq_fr += 1
            out = cam.on_frame(decode_frame(msg), len(msg), t_recv_s=0.0, t_start_s=0.0)
            updates += [o for o in out if isinstance(o, CalibrationUpdate)]
    methods = [u.calibration.method for u in updates]
    before = [u for u in updates if u.t_us < t_frames_start]
    assert before, "an events-only camera got no calibration"
    assert {u.calibration.method for u in before} == {"offe"}
    assert not any(u.from_frame for u in before)  # no frame latency for them
    # the first frame ends the events-only estimate; OnEI's updates follow
    assert cam.events_only is None
    assert "onei" in methods
    first_onei = methods.index("onei")
    assert set(methods[first_onei:]) == {"onei"}
    # what it published before frames is offline OffE of the events up to then
    last = before[-1]
    upto = rec.events[rec.events["t_us"] <= last.t_us]
    ref = offe(Recording(sensor, upto, None))
    np.testing.assert_allclose(last.calibration.bias, ref.bias, atol=1e-12)
    _, meta = decode_calibration(last.message)
    assert meta["method"] == "offe"


def test_camera_events_only_idle_update_and_snapshot(tmp_path: Path) -> None:
    sensor = SensorSize(height=20, width=16)
    ev = biased_events(sensor, 60_000, 800_000, seed=5)  # under one period: no update
    cam = CameraState("lab/eo", offe_period_us=1_000_000)
    out = []
    for seq, chunk in enumerate(np.array_split(ev, 8)):
        out += cam.on_events(_events_msg(chunk, sensor, seq), 100, now_s=0.0)
    assert not [o for o in out if isinstance(o, CalibrationUpdate)]
    # the stream stops: the worker's idle call publishes what came
    idle = cam.on_idle(now_s=1.0)
    assert len(idle) == 1
    assert isinstance(idle[0], CalibrationUpdate)
    assert idle[0].t_us == int(ev["t_us"][-1])
    assert_same_maps(idle[0].calibration, offe(Recording(sensor, ev, None)))
    assert cam.on_idle(now_s=2.0) == []  # nothing new
    # a snapshot keeps the events-only sums; the restored camera goes on from them
    path = atomic_savez(tmp_path / "cam.npz", cam.state_arrays() or {})
    with path.open("rb") as f:
        arrays = read_snapshot(f)
    assert any(k.startswith("offe__") for k in arrays)
    back = CameraState("lab/eo", offe_period_us=1_000_000)
    back.restore(arrays)
    assert back.events_only is not None
    more = biased_events(sensor, 5_000, 100_000, seed=6)
    more["t_us"] += int(ev["t_us"][-1]) - int(more["t_us"][0]) + 1
    for c in (cam, back):
        c.on_events(_events_msg(more, sensor, 8), 100, now_s=3.0)
    assert_same_maps(cam.on_idle(now_s=4.0)[0].calibration,
                     back.on_idle(now_s=4.0)[0].calibration)


def test_events_only_update_carries_the_noise_rate_map(tmp_path: Path) -> None:
    sensor = SensorSize(height=12, width=10)
    ev = biased_events(sensor, 30_000, 1_500_000, seed=8)
    cam = CameraState("lab/noise", offe_period_us=10_000_000)
    for seq, chunk in enumerate(np.array_split(ev, 5)):
        cam.on_events(_events_msg(chunk, sensor, seq), 100, now_s=0.0)
    (upd,) = cam.on_idle(now_s=1.0)
    assert isinstance(upd, CalibrationUpdate)
    # events/s per pixel over the stream so far
    counts = np.bincount(ev["y"].astype(np.int64) * sensor.width + ev["x"],
                         minlength=sensor.n_pixels).reshape(sensor.shape)
    span_s = (int(ev["t_us"][-1]) - int(ev["t_us"][0])) / 1e6
    np.testing.assert_allclose(upd.extra_maps["noise_rate_hz"], counts / span_s, rtol=1e-6)
    maps, meta = decode_calibration_maps(upd.message)
    assert meta["method"] == "offe"
    np.testing.assert_array_equal(maps["noise_rate_hz"], upd.extra_maps["noise_rate_hz"])
    cal, _ = decode_calibration(upd.message)  # a Calibration: the schema's maps only
    assert_same_maps(cal, upd.calibration)
    # a restored camera serves the same map from its stored message
    path = atomic_savez(tmp_path / "cam.npz", cam.state_arrays() or {})
    with path.open("rb") as f:
        arrays = read_snapshot(f)
    back = CameraState("lab/noise")
    back.restore(arrays)
    assert back.current_calibration() is not None
    np.testing.assert_array_equal(back.extra_maps["noise_rate_hz"],
                                  upd.extra_maps["noise_rate_hz"])


def test_extra_maps_on_the_wire_are_checked() -> None:
    sensor = SensorSize(height=4, width=6)
    cal = offe(Recording(sensor, biased_events(sensor, 20_000, 1_000_000, seed=3), None))
    ok = np.full(sensor.shape, 2.5, np.float32)
    maps, _ = decode_calibration_maps(encode_calibration(cal, t_us=1, seq=0,
                                                         extra_maps={"noise_rate_hz": ok}))
    assert maps["noise_rate_hz"].dtype == np.float32
    for name, values, match in (("noise", ok, "unknown map 'noise'"),
                                ("noise_rate_hz", ok[:2], r"shape \(2, 6\), expected \(4, 6\)"),
                                ("noise_rate_hz", -ok, "negative, NaN or infinite"),
                                ("noise_rate_hz", ok * np.nan, "negative, NaN or infinite")):
        with pytest.raises(WireError, match=match):
            encode_calibration(cal, t_us=1, seq=0, extra_maps={name: values})


def test_snapshot_with_a_wrong_events_only_field_is_refused(tmp_path: Path) -> None:
    sensor = SensorSize(height=8, width=8)
    cam = CameraState("lab/eo2")
    cam.on_events(_events_msg(biased_events(sensor, 500, 100_000, 1), sensor, 0), 1,
                  now_s=0.0)
    arrays = cam.state_arrays() or {}
    arrays["offe__sums"] = arrays["offe__sums"][:10]
    path = atomic_savez(tmp_path / "bad.npz", arrays)
    with path.open("rb") as f, pytest.raises(StateError, match=r"offe__sums is float64 "
                                                               r"\(10, 5\), expected float64"):
        read_snapshot(f)
    del arrays["offe__sums"]
    path = atomic_savez(tmp_path / "bad2.npz", arrays)
    with path.open("rb") as f, pytest.raises(StateError, match="events-only state has"):
        read_snapshot(f)


# ----------------------------------------------------------------------------- end to end


def write_evt3(path: Path, events: np.ndarray, sensor: SensorSize) -> Path:
    """A Prophesee RAW EVT 3.0 file (``encoding_formats/evt3``): per event TIME_HIGH (8),
    TIME_LOW (6), ADDR_Y (0), ADDR_X (2, polarity in bit 11); times from 0 µs, < 2^24."""
    t = events["t_us"] - events["t_us"][0]
    if t.size and int(t[-1]) >= 1 << 24:
        raise ValueError("this small writer does not wrap the 24-bit time")
    words = np.empty((events.size, 4), "<u2")
    words[:, 0] = (8 << 12) | ((t >> 12) & 0xFFF)
    words[:, 1] = (6 << 12) | (t & 0xFFF)
    words[:, 2] = events["y"]
    words[:, 3] = (2 << 12) | events["x"] | ((events["p"] > 0).astype(np.uint16) << 11)
    head = (f"% evt 3.0\n% format EVT3;width={sensor.width};height={sensor.height}\n"
            "% end\n").encode()
    path.write_bytes(head + words.tobytes())
    return path


def _evt3_files() -> list[Path]:
    if not DATA.exists():
        return []
    out = []
    for p in sorted(DATA.rglob("*.raw")):
        with p.open("rb") as f:
            head = f.read(4096)
        if b"EVT3" in head or b"evt 3.0" in head:
            out.append(p)
    return out


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    pytest.importorskip("zenoh")
    from evcal.service.transport import Transport, ZenohOptions  # noqa: PLC0415
    from evcal.testing import ServiceProcess, endpoint, free_port, wait_for  # noqa: PLC0415

    d = tmp_path_factory.mktemp("service")
    ep = endpoint(free_port())
    args = ["--listen", ep, "--no-multicast-scouting", "--on-full", "block",
            "--n-small", "15000", "--n-large", "10000000", "--log-offset", "30",
            "--status-period", "0.2", "-v"]
    with ServiceProcess(args, log_path=d / "service.log") as sp:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60,
                     what="the service's liveliness token")
            yield {"ep": ep, "t": t, "proc": sp, "dir": d}
        if sp.alive():
            assert sp.stop() == 0, sp.log_text()


def _replay(service, path: Path, camera: str, *extra: str) -> None:
    from evcal.testing import run_client  # noqa: PLC0415

    res = run_client("replay", [str(path), "--camera", camera, "--connect", service["ep"],
                                "--no-multicast-scouting", *extra])
    assert res.returncode == 0, res.stderr


def _live_calibration(service, camera: str, n_events: int):
    """The published calibration once it holds every replayed event (``evcal query``)."""
    from evcal.io import load_calibration  # noqa: PLC0415
    from evcal.testing import run_client, wait_for  # noqa: PLC0415

    out = service["dir"] / f"{camera.replace('/', '_')}.npz"

    def ready():
        res = run_client("query", ["--camera", camera, "--connect", service["ep"],
                                   "--no-multicast-scouting", "--out", str(out),
                                   "--timeout", "5"])
        if res.returncode != 0:
            return None
        cal = load_calibration(out)
        return cal if int(cal.n_events.sum()) >= n_events else None

    return wait_for(ready, timeout_s=90, interval_s=0.5,
                    what=f"{camera}'s events-only calibration of all {n_events} events")


def _check_against_offline(path: Path, live) -> None:
    from evcal.io import open_recording  # noqa: PLC0415

    # `evcal calibrate --method offe`, the offline reference
    out = path.with_suffix(".offe.npz")
    res = subprocess.run([sys.executable, "-m", "evcal", "calibrate", str(path), "--method",
                          "offe", "--out", str(out)], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    from evcal.io import load_calibration  # noqa: PLC0415

    ref = load_calibration(out)
    assert live.method == "offe"
    assert live.shape == open_recording(path).sensor.shape
    both = live.valid & ref.valid
    assert both.sum() > 100
    r = float(np.corrcoef(live.bias[both], ref.bias[both])[0, 1])
    assert r > 0.95, r
    # the same events, the same sums: the maps agree to float tolerance
    np.testing.assert_allclose(live.bias, ref.bias, atol=1e-6)
    np.testing.assert_array_equal(live.valid, ref.valid)


@pytest.mark.timeout(300)
def test_real_dvs_events_as_evt3_replayed_live_match_offline_offe(service, tmp_path: Path
                                                                  ) -> None:
    """Real sensor events (the shared DAVIS346 ROS 2 bag, 571 k events over 1 s, no
    frames) written as EVT 3.0, replayed live."""
    bag = DATA / "ros2_event_packet_mcap"
    if not bag.exists():
        pytest.skip(f"{bag} is absent (shared real recordings)")
    from evcal.io import open_recording  # noqa: PLC0415

    rec = open_recording(bag / "test_events_2_0.mcap")
    path = write_evt3(tmp_path / "davis346.raw", rec.events, rec.sensor)
    back = open_recording(path)
    assert back.n_events == rec.n_events
    _replay(service, path, "lab/evt3/cam0", "--max-rate")
    live = _live_calibration(service, "lab/evt3/cam0", int(offe(back).n_events.sum()))
    _check_against_offline(path, live)


@pytest.mark.timeout(600)
@pytest.mark.parametrize("path", _evt3_files() or [None])
def test_prophesee_evt3_recording_replayed_live_matches_offline_offe(service, path) -> None:
    if path is None:
        pytest.skip(f"no Prophesee EVT 3.0 recording (*.raw) under {DATA}")
    from evcal.io import open_recording  # noqa: PLC0415

    rec = open_recording(path)
    cam = "lab/prophesee/" + path.stem.replace(".", "_")
    _replay(service, path, cam, "--max-rate")
    live = _live_calibration(service, cam, int(offe(rec).n_events.sum()))
    _check_against_offline(path, live)


@pytest.mark.timeout(300)
def test_camera_whose_frames_start_later_moves_to_onei(service, tmp_path: Path) -> None:
    from evcal.io import write_recording  # noqa: PLC0415

    sim = simulate_ideal(SimConfig(height=36, width=48, duration_s=4.0, seed=4))
    rec = sim.recording
    late = rec.frames.t_us >= int(rec.events["t_us"][0]) + 2_000_000
    path = write_recording(Recording(rec.sensor, rec.events, Frames(
        rec.frames.t_us[late], rec.frames.images[late], rec.frames.exposure_us[late])),
        tmp_path / "late_frames.npz")
    cam = "lab/late/cam0"
    proc = subprocess.Popen([sys.executable, "-m", "evcal.clients.replay", str(path),
                             "--camera", cam, "--connect", service["ep"],
                             "--no-multicast-scouting", "--speed", "1"],
                            stderr=subprocess.PIPE, text=True)
    seen: list[tuple[str, int]] = []
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        replies = service["t"].get(f"evcal/{cam}/calibration", timeout_s=2.0)
        if replies and replies[0].ok:
            _, meta = decode_calibration(replies[0].payload)
            if not seen or seen[-1] != (meta["method"], meta["seq"]):
                seen.append((meta["method"], meta["seq"]))
            if meta["method"] == "onei" and proc.poll() is not None:
                break
        time.sleep(0.1)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    methods = [m for m, _ in seen]
    assert "offe" in methods, seen
    assert methods[-1] == "onei", seen
    assert methods.index("onei") > methods.index("offe"), seen



@pytest.mark.timeout(300)
def test_events_only_noise_rate_published_queried_and_recorded(tmp_path: Path) -> None:
    """Through real zenoh sessions: an events-only camera replayed live (EVT 3.0) gets the
    noise-rate map in its published calibration, in a ``fields=`` query, and in the
    service's ``.rrd``."""
    pytest.importorskip("zenoh")
    from evcal.service.rrdlog import read_entities  # noqa: PLC0415
    from evcal.service.transport import Transport, ZenohOptions  # noqa: PLC0415
    from evcal.testing import ServiceProcess, endpoint, free_port, wait_for  # noqa: PLC0415

    sensor = SensorSize(height=30, width=40)
    ev = biased_events(sensor, 120_000, 2_500_000, seed=11)
    path = write_evt3(tmp_path / "noise.raw", ev, sensor)
    cam = "lab/noise/cam0"
    ep = endpoint(free_port())
    rrd = tmp_path / "service.rrd"
    args = ["--listen", ep, "--no-multicast-scouting", "--on-full", "block", "--rrd",
            str(rrd), "--rrd-map-period", "0", "--status-period", "0.2", "-v"]
    with ServiceProcess(args, log_path=tmp_path / "service.log") as sp:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60,
                     what="the service's liveliness token")
            _replay({"ep": ep}, path, cam, "--max-rate")

            def complete():
                replies = t.get(f"evcal/{cam}/calibration", timeout_s=2.0)
                if not replies or not replies[0].ok:
                    return None
                maps, meta = decode_calibration_maps(replies[0].payload)
                return (maps, meta) if meta["n_events_used"] >= ev.size - 2_000 and int(
                    maps["n_events"].sum()) == meta["n_events_used"] and meta[
                    "t_us"] == int(ev["t_us"][-1] - ev["t_us"][0]) else None

            maps, meta = wait_for(complete, timeout_s=90, interval_s=0.3,
                                  what="the calibration of every replayed event")
            assert meta["method"] == "offe"
            counts = np.bincount(ev["y"].astype(np.int64) * sensor.width + ev["x"],
                                 minlength=sensor.n_pixels).reshape(sensor.shape)
            span_s = (int(ev["t_us"][-1]) - int(ev["t_us"][0])) / 1e6
            np.testing.assert_allclose(maps["noise_rate_hz"], counts / span_s, rtol=1e-5)
            (reply,) = t.get(f"evcal/{cam}/calibration?fields=noise_rate_hz,bias",
                             timeout_s=5.0)
            assert reply.ok
            sub, _ = decode_calibration_maps(reply.payload)
            assert sorted(sub) == ["bias", "noise_rate_hz"]
            np.testing.assert_array_equal(sub["noise_rate_hz"], maps["noise_rate_hz"])
        assert sp.stop() == 0, sp.log_text()
    ents = read_entities(rrd)
    for name in ("maps/noise_rate_hz", "events", "recon/calibrated", "recon/di"):
        assert ents.get(f"/cameras/{cam}/{name}", 0) >= 1, (name, sorted(ents))


def test_events_only_review_integrates_the_events_between_maps(tmp_path: Path) -> None:
    """The review of an events-only camera: between two map logs, its events' ON/OFF image
    and their integration with the calibration (c P + b E) and with DI (0.1 P), on one
    scale around mid-grey; a camera whose frames come stops counting for it."""
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader  # noqa: PLC0415

    from evcal.service.rrdlog import RrdLogger, read_entities  # noqa: PLC0415

    sensor = SensorSize(height=6, width=8)
    ev = biased_events(sensor, 20_000, 2_000_000, seed=9)
    cal = offe(Recording(sensor, ev, None))
    log = RrdLogger(tmp_path / "eo.rrd", map_period_s=0.0, scalar_period_s=0.0)
    status = {"method": "offe"}
    noise = {"noise_rate_hz": np.ones(sensor.shape, np.float32)}
    log.updated("eo", cal, 0, status, noise)  # starts counting
    half = ev[: ev.size // 2]
    log.events("eo", half)
    log.updated("eo", cal, 1_000_000, status, noise)  # logs what came since
    log.close()
    ents = read_entities(log.path)
    assert ents["/cameras/eo/recon/calibrated"] == ents["/cameras/eo/recon/di"] == 1
    assert ents["/cameras/eo/events"] == 1
    # the calibrated integration, as logged: c P + b E of the events, 128 where none
    reader = RrdReader(str(log.path))
    (store,) = reader.recordings()
    logged = None
    for chunk in reader.stream(store=store).collect().stream():
        if str(chunk.entity_path) == "/cameras/eo/recon/calibrated":
            batch = chunk.to_record_batch()
            col = next(c for c in batch.schema.names if c.endswith(":buffer"))
            logged = np.asarray(batch.column(col)[0].as_py()[0], np.uint8)
    assert logged is not None
    pix = half["y"].astype(np.int64) * sensor.width + half["x"]
    p = np.bincount(pix, weights=half["p"], minlength=sensor.n_pixels).reshape(sensor.shape)
    e = np.bincount(pix, minlength=sensor.n_pixels).reshape(sensor.shape)
    expected = cal.contrast * p + cal.bias * e
    order = np.argsort(expected.ravel())
    assert np.all(np.diff(logged.astype(int)[order]) >= 0)  # monotone in c P + b E
