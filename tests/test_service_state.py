"""Snapshots: never half-written (kill -9 of a writer), and a killed service resumes from them."""

from __future__ import annotations

import json
import random
import subprocess
import sys
import time

import numpy as np
import pytest

from evcal.service.state import StateStore, load_npz

pytestmark = pytest.mark.timeout(240)

WRITER = r"""
import sys, numpy as np
from evcal.service.state import StateStore
store = StateStore(sys.argv[1])
rng = np.random.default_rng(int(sys.argv[2]))
i = 0
while True:
    n = int(rng.integers(1, 400_000))
    a = rng.random(n)
    for cam in ("lab/cam0", "cam1"):
        store.save(cam, {"data": a, "n": np.int64(n), "sum": np.float64(a.sum()),
                         "i": np.int64(i)})
    i += 1
"""


def test_snapshots_survive_kill_9_of_the_writer(tmp_path):
    seen = set()
    start_s = 0.0
    for k in range(8):
        t0 = time.monotonic()
        p = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(k)])
        if k == 0:
            # the writer's imports take about a second (more on a busy machine): the kills
            # must come while it writes, so they wait that long first
            deadline = t0 + 60
            while len([f for f in tmp_path.iterdir() if ".tmp-" not in f.name]) < 2:
                assert time.monotonic() < deadline, "the writer wrote no snapshot in 60 s"
                assert p.poll() is None, "the writer exited"
                time.sleep(0.05)
            start_s = time.monotonic() - t0
        # seeded: a repeatable run
        time.sleep(max(0.0, start_s - (time.monotonic() - t0))
                   + 0.4 + random.Random(k).random() * 0.4)
        p.kill()
        p.wait(10)
        for f in tmp_path.iterdir():
            if ".tmp-" in f.name:
                continue  # a killed writer's temporary file: never read as state
            z = load_npz(f)
            assert z["data"].shape == (int(z["n"]),)
            assert float(z["data"].sum()) == pytest.approx(float(z["sum"]))
            seen.add(f.name)
    assert seen == {"lab%2Fcam0.npz", "cam1.npz"}
    loaded = StateStore(tmp_path).load_all()
    assert sorted(loaded) == ["cam1", "lab/cam0"]
    assert not list(tmp_path.glob("*.bad"))


def test_kill_9_service_then_restart_answers_with_last_snapshot(tmp_path):
    pytest.importorskip("zenoh")
    from evcal.io import write_recording
    from evcal.testing import ServiceProcess, endpoint, free_port, wait_for
    from evcal.service.transport import Transport, ZenohOptions
    from evcal.sim.ideal import SimConfig, simulate_ideal

    sim = simulate_ideal(SimConfig(height=48, width=64, duration_s=4.0, seed=3))
    path = write_recording(sim.recording, tmp_path / "sim.npz")
    state = tmp_path / "state"
    common = ["--no-multicast-scouting", "--state-dir", str(state), "--snapshot-period",
              "0.2", "--n-small", "5000", "--n-large", "1000000", "--on-full", "block"]
    ep = endpoint(free_port())
    snap = state / "kill%2Fcam0.npz"
    with ServiceProcess(["--listen", ep, *common], log_path=tmp_path / "s1.log") as s1, \
            Transport(ZenohOptions.loopback(connect=[ep])) as t:
        wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60,
                 what="service 1")
        # real time: the kill lands mid-stream
        replay = subprocess.Popen([sys.executable, "-m", "evcal.clients.replay", str(path),
                                   "--camera", "kill/cam0", "--connect", ep,
                                   "--no-multicast-scouting", "--speed", "1"],
                                  stderr=subprocess.DEVNULL)
        try:
            def updated_twice():
                r = t.get("evcal/kill/cam0/status", timeout_s=1.0)
                if not (r and json.loads(r[0].payload)["updates"] >= 2 and snap.exists()):
                    return False
                # a snapshot written after an update (it holds a calibration)
                try:
                    return load_npz(snap)["calibration_msg"].size > 0
                except Exception:  # noqa: BLE001 - replaced while read: look again
                    return False

            wait_for(updated_twice, timeout_s=60,
                     what="two updates and a snapshot holding a calibration")
            s1.kill()  # SIGKILL: no clean-up, no final snapshot
        finally:
            replay.kill()
            replay.wait(10)
    assert not list(state.glob("*.bad"))
    stored = load_npz(snap)  # complete and readable
    last_msg = stored["calibration_msg"].tobytes()
    assert last_msg
    meta = json.loads(str(stored["service_json"]))
    assert 0 < meta["counters"]["frames"] < len(sim.recording.frames)  # mid-stream

    ep2 = endpoint(free_port())
    with ServiceProcess(["--listen", ep2, *common], log_path=tmp_path / "s2.log") as s2, \
            Transport(ZenohOptions.loopback(connect=[ep2])) as t2:
        wait_for(lambda: t2.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60,
                 what="service 2")
        t_query = time.monotonic()
        r = t2.get("evcal/kill/cam0/calibration", timeout_s=5.0)
        assert r and r[0].ok, s2.log_text()
        assert time.monotonic() - t_query < 2.0
        assert r[0].payload == last_msg
        st = json.loads(t2.get("evcal/kill/cam0/status", timeout_s=2.0)[0].payload)
        assert st["frames"] == meta["counters"]["frames"]
        assert s2.stop() == 0
    assert np.isfinite(stored["est__c"]).all()
