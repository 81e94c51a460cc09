"""``evcal record``: zenoh -> MCAP that ``open_recording`` (replay, calibrate) reads back."""

from __future__ import annotations

import threading

import numpy as np
import pytest

pytest.importorskip("zenoh")

from evcal.clients.record import Recorder  # noqa: E402
from evcal.clients.replay import replay  # noqa: E402
from evcal.io import open_recording  # noqa: E402
from evcal.io.wire import decode_calibration  # noqa: E402
from evcal.online import OnEIConfig  # noqa: E402
from evcal.service.core import ServiceConfig  # noqa: E402
from evcal.service.server import run  # noqa: E402
from evcal.service.transport import Transport, ZenohOptions  # noqa: E402
from evcal.sim.ideal import SimConfig, simulate_ideal  # noqa: E402
from evcal.testing import endpoint, free_port, run_client, wait_for  # noqa: E402

pytestmark = pytest.mark.timeout(120)


def test_record_replay_roundtrip_with_calibrations(tmp_path):
    sim = simulate_ideal(SimConfig(height=36, width=48, duration_s=2.0, seed=5))
    rec = sim.recording
    ep = endpoint(free_port())
    stop, ready = threading.Event(), threading.Event()
    th = threading.Thread(target=run, args=(
        ZenohOptions.loopback(listen=[ep]),
        ServiceConfig(on_full="block", onei=OnEIConfig(n_small=3000, n_large=10**6))),
        kwargs={"stop": stop, "ready": lambda s: ready.set()})
    th.start()
    try:
        assert ready.wait(30)
        out = tmp_path / "rec.mcap"
        recorder = Recorder(str(out), ["rig/cam0"])
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            recorder.subscribe(t)
            replay(t, rec, "rig/cam0", speed=None)
            wait_for(lambda: recorder.writers.get("rig/cam0") is not None
                     and recorder.writers["rig/cam0"].counts["frames"] >= len(rec.frames)
                     and recorder.writers["rig/cam0"].counts["calibrations"] >= 1,
                     timeout_s=30, what="everything recorded")
        counts = recorder.close()
    finally:
        stop.set()
        th.join(60)
    assert counts["rig/cam0"]["lost"] == 0
    assert counts["rig/cam0"]["rejected"] == 0
    back = open_recording(out)
    assert back.sensor == rec.sensor
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.frames.t_us, rec.frames.t_us)
    np.testing.assert_array_equal(back.frames.images, rec.frames.images)
    # the calibrations are in the file too, as the service published them
    from mcap.reader import make_reader

    with open(out, "rb") as f:
        cals = [decode_calibration(m.data)[0] for _, _, m in
                make_reader(f).iter_messages(topics=["/calibration"])]
    assert cals
    assert cals[-1].shape == (36, 48)
    # the file replays, but the service is gone: replay says so and sends nothing
    res = run_client("replay", [str(out), "--camera", "x", "--no-multicast-scouting",
                                "--connect", ep, "--max-rate", "--wait-subscriber", "0.5"])
    assert res.returncode == 3, res.stderr
    assert "nobody subscribes" in res.stderr
    assert "nothing was sent" in res.stderr


def test_record_cli_needs_a_template_for_several_cameras(tmp_path):
    res = run_client("record", ["--out", str(tmp_path / "x.mcap"), "--camera", "lab/**",
                                "--no-multicast-scouting", "--duration", "0.1"])
    assert res.returncode == 2
    assert "{camera}" in res.stderr
    res = run_client("record", ["--out", str(tmp_path / "x-{camera}.mcap"), "--camera",
                                "lab/**", "--no-multicast-scouting", "--duration", "0.5"])
    assert res.returncode == 3, res.stderr  # nothing heard is a failure, not a success
    assert "nothing received" in res.stderr


def test_record_file_names_are_safe_and_distinct(tmp_path):
    rec = Recorder(str(tmp_path / "r-{camera}.mcap"), ["**"], max_cameras=2)
    names = {c: rec.path_for(c) for c in ("lab/good", "lab_good", "a/b%2Fc")}
    assert len(set(names.values())) == 3
    for p in names.values():
        assert p.parent == tmp_path  # never a separator or '..' out of the folder
    long_id = "/".join(["x" * 60] * 3)
    assert len(rec.path_for(long_id).name) < 120
    # ids that are not camera ids are refused, and at most max_cameras files are open
    rec.on_sample("evcal/../events", b"", "")
    for cam in ("c1", "c2", "c3"):
        rec.on_sample(f"evcal/{cam}/events", b"junk", "")
    assert sorted(rec.writers) == ["c1", "c2"]
    assert rec.refused == {"..": 1, "c3": 1}
    rec.close()


def _events_msg(seq: int, t0: int, n: int = 5) -> bytes:
    """An 8x6 camera's events message: ``n`` events from ``t0`` µs, one per µs."""
    from evcal.events import make_events
    from evcal.io.wire import encode_events

    ev = make_events(np.arange(t0, t0 + n), np.zeros(n, int), np.zeros(n, int), np.ones(n, int))
    return encode_events(ev, height=6, width=8, seq=seq)


def test_record_counts_loss_as_the_service_does(tmp_path):
    """`evcal record`'s counts follow the service's StreamGuard semantics: a late message
    comes off `lost` whether it is placed (its time fits) or refused (it does not); a copy
    is a duplicate, not loss; an empty message and one refused before its number was read
    leave no gap. Before, the late (placed or refused), empty and undecodable messages each
    left one message counted lost."""
    from evcal.clients.record import CameraWriter

    w = CameraWriter(tmp_path / "c.mcap", "c")
    # a swapped pair whose late message still fits (events may share a time): placed
    for seq, t0 in ((0, 0), (2, 100), (1, 104), (3, 200)):
        w.add("events", _events_msg(seq, t0))
    assert (w.counts["lost"], w.counts["rejected"]) == (0, 0), w.counts
    # a swapped pair whose late message does not fit: refused, and no longer lost
    for seq, t0 in ((5, 300), (4, 250)):
        w.add("events", _events_msg(seq, t0))
    assert (w.counts["lost"], w.counts["rejected"]) == (0, 1), (w.counts, w.errors)
    assert "time_backwards" in w.errors[-1]
    # an exact copy: a duplicate, refused, not loss
    w.add("events", _events_msg(5, 300))
    assert (w.counts["lost"], w.counts["rejected"]) == (0, 2), (w.counts, w.errors)
    assert w.errors[-1].startswith("events: duplicate:"), w.errors
    # an empty message and an undecodable one take their numbers: no gap follows
    w.add("events", _events_msg(6, 400, n=0))
    w.add("events", b"\xc1 not msgpack")
    w.add("events", _events_msg(8, 500))
    assert (w.counts["lost"], w.counts["rejected"]) == (0, 3), (w.counts, w.errors)
    # a real gap is still loss
    w.add("events", _events_msg(11, 600))
    assert w.counts["lost"] == 2, w.counts
    w.close()
    back = open_recording(tmp_path / "c.mcap", sensor=None)
    assert back.n_events == 7 * 5  # seq 0, 2, 1, 3, 5, 8 and 11; 4 and the copy refused
    assert np.all(np.diff(back.events["t_us"]) >= 0)
