"""``evcal replay``'s exit codes, one outcome per test, against a real service on loopback.

The table (``evcal.clients.replay.EXIT_CODES``, the module docstring, ``--help`` and
docs/SERVICE.md): 0 all taken, 3 nobody there, 4 lost, 5 refused, 6 dropped, 7 unconfirmed.
Each replay is a real ``evcal replay`` process; each service runs in a thread of this process
(so that a test can stall a camera), on its own free port with multicast scouting off.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_service_core import stream
from test_service_slots import ENC, serving

pytest.importorskip("zenoh")

from evcal.bench import random_recording  # noqa: E402
from evcal.clients import replay as replay_mod  # noqa: E402
from evcal.events import SensorSize  # noqa: E402
from evcal.io import write_recording  # noqa: E402
from evcal.online import OnEIConfig  # noqa: E402
from evcal.service import keys  # noqa: E402
from evcal.service.core import ServiceConfig  # noqa: E402
from evcal.service.transport import Transport, ZenohOptions  # noqa: E402
from evcal.testing import endpoint, free_port, python_env, run_client, wait_for  # noqa: E402

pytestmark = pytest.mark.timeout(120)

ZARGS = ["--no-multicast-scouting"]
N_FRAMES = 10
ONEI = OnEIConfig(n_small=2000, n_large=200_000)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A small recording: 48x36, 10 frames, 50 k events (10 frames + 10 event messages)."""
    rec = random_recording(SensorSize(36, 48), 50_000, N_FRAMES)
    return write_recording(rec, tmp_path_factory.mktemp("rec") / "rec.npz")


def _cfg(**kw) -> ServiceConfig:
    return ServiceConfig(**{"onei": ONEI, "error_rate_hz": 5.0, **kw})


def endpoint_of(t: Transport) -> str:
    return t.options.connect[0]


def run_replay(ep: str, path: Path, camera: str, *extra: str
               ) -> subprocess.CompletedProcess[str]:
    # one events message per frame interval: 10 frames and 10 events messages
    return run_client("replay", [str(path), "--camera", camera, "--connect", ep, *ZARGS,
                                 "--max-rate", "--chunk-ms", "40", *extra], timeout_s=90)


def test_all_taken_is_0(recording):
    with serving(_cfg(on_full="block")) as (svc, t):
        res = run_replay(endpoint_of(t), recording, "ok/cam0")
        assert res.returncode == 0, res.stderr
        assert "all taken (exit code 0)" in res.stderr
        assert svc.cameras["ok/cam0"].counters.frames == N_FRAMES


def test_a_refused_camera_is_5(recording):
    # every slot (1) held by a camera past its probation: the replay's camera is refused
    with serving(_cfg(max_cameras=1)) as (svc, t):
        for kind, payload in stream(n_frames=12):
            t.put(keys.camera_key("evcal", "busy/cam0", kind), payload, ENC[kind], block=True)
        wait_for(lambda: "busy/cam0" in svc.cameras
                 and svc.cameras["busy/cam0"].counters.frames == 12, timeout_s=10,
                 what="the slot taken")
        res = run_replay(endpoint_of(t), recording, "new/cam0")
        assert res.returncode == 5, res.stderr
        assert "refused the camera: too_many_cameras" in res.stderr
        assert "refused 20 messages" in res.stderr


def test_a_service_that_drops_is_6(recording, monkeypatch):
    # --on-full drop with a small queue and the camera's decoder held: the queue overflows
    import evcal.service.ingest as ingest

    release = threading.Event()
    real = ingest.decode_events

    def held_decode(payload):
        release.wait(60)
        return real(payload)

    monkeypatch.setattr(ingest, "decode_events", held_decode)
    cfg = _cfg(on_full="drop", queue_bytes=64 << 10, max_message_bytes=64 << 10)
    with serving(cfg) as (svc, t):
        proc = subprocess.Popen(
            [sys.executable, "-m", "evcal.clients.replay", str(recording), "--camera",
             "drop/cam0", "--connect", endpoint_of(t), *ZARGS, "--max-rate",
             "--chunk-events", "2000"],
            stderr=subprocess.PIPE, text=True, env=python_env())
        try:
            # (the replay's status queries move the receive thread's drop counts into the
            # camera's counters)
            wait_for(lambda: "drop/cam0" in svc.cameras
                     and sum(svc.status(svc.cameras["drop/cam0"])["dropped"].values()) > 0,
                     timeout_s=30, what="drops")
        except TimeoutError:
            proc.kill()
            pytest.fail(f"no drops: {proc.communicate()[1]}")
        finally:
            release.set()
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 6, err
        assert "dropped (exit code 6)" in err


def test_messages_sent_to_a_service_that_went_away_are_lost_4(recording, tmp_path):
    long_rec = write_recording(random_recording(SensorSize(36, 48), 20_000, 100),
                               tmp_path / "long.npz")  # 4 s of sensor time
    with serving(_cfg(on_full="block")) as (svc, t):
        ep = endpoint_of(t)
        proc = subprocess.Popen(
            [sys.executable, "-m", "evcal.clients.replay", str(long_rec), "--camera",
             "gone/cam0", "--connect", ep, *ZARGS, "--speed", "1"],
            stderr=subprocess.PIPE, text=True, env=python_env())
        wait_for(lambda: "gone/cam0" in svc.cameras
                 and svc.cameras["gone/cam0"].counters.frames >= 5, timeout_s=30,
                 what="the service taking the first frames")
    # the service is closed (its session with it): the rest of the run goes nowhere
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 4, err
    assert "sent while nobody subscribed (lost)" in err


def test_nobody_there_is_3(recording):
    res = run_replay(endpoint(free_port()), recording, "none/cam0", "--wait-subscriber", "0.3")
    assert res.returncode == 3, res.stderr
    assert "nothing was sent" in res.stderr


def test_a_subscriber_that_is_no_service_is_unconfirmed_7(recording):
    # a plain subscriber (as `evcal record`): the messages go out, nobody confirms them
    ep = endpoint(free_port())
    got: list[str] = []
    with Transport(ZenohOptions.loopback(listen=[ep])) as t:
        t.subscribe("evcal/**", lambda key, payload, enc: got.append(key))
        t0 = time.monotonic()
        res = run_replay(ep, recording, "rec/cam0")
        took_s = time.monotonic() - t0
    assert res.returncode == 7, res.stderr
    assert "delivery not confirmed: no evcal service is up" in res.stderr
    assert len(got) == 2 * N_FRAMES
    assert took_s < 15  # no service token: it does not wait --confirm-timeout for one


def test_a_slow_service_is_waited_for_and_confirms_0(recording, monkeypatch):
    # the camera's decoder stalls for 4 s after the run: the counters stand still for longer
    # than the 2 s after which the replay used to give up and call the rest lost
    import evcal.service.ingest as ingest

    real = ingest.decode_events
    calls = [0]

    def slow_decode(payload):
        calls[0] += 1
        if calls[0] == N_FRAMES:  # the last events message
            time.sleep(4.0)
        return real(payload)

    monkeypatch.setattr(ingest, "decode_events", slow_decode)
    with serving(_cfg(on_full="block")) as (svc, t):
        res = run_replay(endpoint_of(t), recording, "slow/cam0")
        assert res.returncode == 0, res.stderr
        assert svc.cameras["slow/cam0"].counters.event_messages == N_FRAMES


def test_sigint_stops_a_replay_blocked_in_put_within_2_s(recording):
    # --on-full block, a small queue and the camera's worker held: the service's receive
    # path stalls and the replay's puts block (shared memory off, so bytes fill the link)
    cfg = _cfg(on_full="block", queue_bytes=256 << 10, max_message_bytes=256 << 10)
    with serving(cfg) as (svc, t):
        release = threading.Event()
        held = threading.Event()

        def hold() -> None:
            cam = wait_for(lambda: svc.cameras.get("stall/cam0"), timeout_s=30,
                           what="the camera", interval_s=0.005)
            with cam.lock:
                held.set()
                release.wait(60)

        holder = threading.Thread(target=hold)
        holder.start()
        proc = subprocess.Popen(
            [sys.executable, "-m", "evcal.clients.replay", str(recording), "--camera",
             "stall/cam0", "--connect", endpoint_of(t), *ZARGS, "--max-rate", "--loop",
             "--cfg", "transport/shared_memory/enabled:false"],
            stderr=subprocess.PIPE, text=True, env=python_env())
        try:
            assert held.wait(30)
            cam = svc.cameras["stall/cam0"]

            def stalled() -> bool:  # the queue full and nothing moving for 1 s
                n = cam.in_flight
                time.sleep(1.0)
                return cam.in_flight == n and cam.queue.nbytes > 0

            wait_for(stalled, timeout_s=30, what="the receive path stalled")
            time.sleep(1.0)  # the replay's puts fill the link and block
            assert proc.poll() is None
            t_sig = time.monotonic()
            proc.send_signal(signal.SIGINT)
            try:
                _, err = proc.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
                pytest.fail(f"replay still running 10 s after SIGINT:\n{err}")
            took_s = time.monotonic() - t_sig
        finally:
            release.set()
            holder.join(10)
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        print(f"replay exited {took_s:.2f} s after SIGINT, blocked in put")
        assert took_s < 2.5, (took_s, err)
        assert proc.returncode == 7, err
        assert "stopped while a put waited" in err


def test_the_exit_code_table_is_written_where_users_read_it():
    doc = replay_mod.__doc__ or ""
    service_md = (Path(__file__).parents[1] / "docs" / "SERVICE.md").read_text()
    help_text = replay_mod.build_parser().format_help()
    for code, outcome, _ in replay_mod.EXIT_CODES:
        assert f"{code}      {outcome}" in doc
        assert f"| {code} | {outcome} |" in service_md
        assert f"{code}  {outcome}" in help_text


def test_the_account_counts_rolled_back_messages_and_says_so(capsys):
    """Issue 40: messages a killed service process had processed after its last snapshot are
    delivered, not missing, and the account says they were rolled back."""
    from evcal.clients.delivery import ReplayStats, _account, print_account

    before = {"event_messages": 100, "events": 10_000, "frames": 10,
              "rolled_back_messages": {"events": 0, "frames": 0}}
    after = {"event_messages": 150, "events": 15_000, "frames": 15,  # back from a snapshot
             "rolled_back_messages": {"events": 40, "frames": 5}}
    acc = _account(after, before)
    assert acc["rolled_back_messages"] == 45
    stats = ReplayStats(event_messages=90, frames=10, delivered=acc, confirmed=True)
    assert stats.missing_messages == 0
    print_account("evcal replay", stats)
    err = capsys.readouterr().err
    assert "45 messages were rolled back" in err
    assert "never reached" not in err
