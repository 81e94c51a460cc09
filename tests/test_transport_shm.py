"""Large payloads through zenoh shared memory (``Transport.put`` and its ``ShmPool``): real
sessions on tcp/127.0.0.1, scouting off; what arrives is checked byte for byte."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from evcal.service.transport import ShmPool, Transport, ZenohOptions
from evcal.testing import endpoint, free_port, wait_for

KEY = "test/shm/payload"


def _payload(n: int, seed: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 255, n, np.uint8).tobytes()


def _exchange(tx_opts: ZenohOptions, rx_opts: ZenohOptions, payloads: list[bytes], *,
              shm_pool_mb: float | None = 64.0) -> tuple[list[bytes], dict[str, int]]:
    got: list[bytes] = []
    lock = threading.Lock()

    def on_msg(key: str, data: bytes, enc: str) -> None:
        with lock:
            got.append(bytes(data))

    with Transport(rx_opts) as rx, Transport(tx_opts, shm_pool_mb=shm_pool_mb) as tx:
        rx.subscribe(KEY, on_msg)
        pub_probe = tx.publisher(KEY, "application/octet-stream")
        wait_for(lambda: pub_probe.has_subscribers, timeout_s=10, what="the subscriber")
        for p in payloads:
            tx.put(KEY, p, "application/octet-stream", block=True)
        wait_for(lambda: len(got) == len(payloads), timeout_s=20, what="every payload")
        stats = tx.shm.stats()
    return got, stats


def _pair(extra: tuple[tuple[str, str], ...] = ()) -> tuple[ZenohOptions, ZenohOptions]:
    ep = endpoint(free_port())
    return (ZenohOptions(mode="peer", connect=(ep,), multicast_scouting=False, extra=extra),
            ZenohOptions(mode="peer", listen=(ep,), multicast_scouting=False, extra=extra))


def test_large_payloads_go_through_shared_memory_and_arrive_intact():
    tx, rx = _pair()
    small, large = _payload(1000, 1), _payload(3 << 20, 2)
    too_large = _payload(9 << 20, 3)  # larger than the 8 MiB pool below: sent as bytes
    got, stats = _exchange(tx, rx, [small, large, large[::-1], too_large], shm_pool_mb=8.0)
    assert got == [small, large, large[::-1], too_large]
    assert stats == {"pool_bytes": 8 << 20, "puts": 2, "fallbacks": 1}


def test_shared_memory_turned_off_in_the_zenoh_config_sends_bytes():
    tx, rx = _pair(extra=(("transport/shared_memory/enabled", "false"),))
    large = _payload(2 << 20, 4)
    got, stats = _exchange(tx, rx, [large])
    assert got == [large]
    assert stats == {"pool_bytes": 0, "puts": 0, "fallbacks": 0}


def test_a_pool_that_cannot_be_created_falls_back_to_bytes(monkeypatch):
    """A container's small /dev/shm: the provider cannot be made; every large payload then
    goes as bytes, counted, with one warning."""
    import zenoh.shm

    class Broken:
        @staticmethod
        def default_backend(size: int) -> None:
            raise zenoh.ZError("cannot create a shared memory segment")

    monkeypatch.setattr(zenoh.shm, "ShmProvider", Broken)
    pool = ShmPool(8 << 20)
    data = _payload(2 << 20, 5)
    assert pool.payload(data) is data
    assert pool.payload(data) is data
    assert pool.stats() == {"pool_bytes": 0, "puts": 0, "fallbacks": 1}
    assert pool.payload(b"small") == b"small"


@pytest.mark.parametrize("size", [0, -1])
def test_a_pool_of_no_size_is_off(size):
    pool = ShmPool(size)
    data = _payload(2 << 20, 6)
    assert pool.payload(data) is data
    assert pool.stats()["puts"] == 0


def test_a_pool_of_no_given_size_is_sized_by_its_first_large_payload(monkeypatch):
    """Room for AUTO_MESSAGES of the first large payload, at least AUTO_MIN_BYTES, at most half
    the free space of /dev/shm; the payloads arrive intact through a pool of that size."""
    monkeypatch.setattr(ShmPool, "AUTO_MIN_BYTES", 1 << 20)
    monkeypatch.setattr(ShmPool, "AUTO_MESSAGES", 4)
    tx, rx = _pair()
    large = [_payload(3 << 20, 7), _payload(3 << 20, 8), _payload((3 << 20) - 5, 9)]
    got, stats = _exchange(tx, rx, large, shm_pool_mb=None)
    assert got == large
    assert stats == {"pool_bytes": 4 * (3 << 20), "puts": 3, "fallbacks": 0}

    monkeypatch.setattr(ShmPool, "AUTO_MIN_BYTES", 64 << 20)
    pool = ShmPool(None)
    assert pool._auto_size(1 << 20) == min(64 << 20, _half_free_shm())
    monkeypatch.setattr(ShmPool, "SHM_DIR", "/no/such/dir")  # nothing to ask: the minimum
    assert ShmPool(None)._auto_size(30 << 20) == 64 << 20


def test_an_automatic_pool_is_capped_by_the_free_shared_memory(monkeypatch):
    import os

    class Small:
        f_bavail, f_frsize = 10, 1 << 20  # 10 MiB free: a pool of 5 MiB at most

    monkeypatch.setattr(os, "statvfs", lambda path: Small())
    pool = ShmPool(None)
    assert pool._auto_size(2 << 20) == 5 << 20
    data = _payload(6 << 20, 10)  # larger than that pool: sent as bytes, counted
    assert pool.payload(data) is data
    assert pool.stats() == {"pool_bytes": 5 << 20, "puts": 0, "fallbacks": 1}


def _half_free_shm() -> int:
    import os

    st = os.statvfs("/dev/shm")
    return st.f_bavail * st.f_frsize // 2


class _StuckSession:
    """A zenoh session whose close hangs (a stuck router) or fails."""

    def __init__(self, hang_s: float = 0.0, error: Exception | None = None) -> None:
        self.hang_s, self.error, self.closed = hang_s, error, threading.Event()

    def close(self) -> None:
        time.sleep(self.hang_s)
        if self.error is not None:
            raise self.error
        self.closed.set()


def test_a_bounded_close_returns_in_time_and_says_why():
    import zenoh

    t = Transport(ZenohOptions.loopback())
    t._session = stuck = _StuckSession(hang_s=30.0)
    t0 = time.monotonic()
    assert t.close(timeout_s=0.3) is False
    assert time.monotonic() - t0 < 2.0
    assert t.close_error == "the zenoh session did not close within 0.3 s"
    assert not stuck.closed.is_set()

    t = Transport(ZenohOptions.loopback())
    t._session = _StuckSession(error=zenoh.ZError("close operation timed out!"))
    assert t.close(timeout_s=2.0) is False  # not raised: reported
    assert t.close_error == ("closing the zenoh session failed: ZError: close operation "
                             "timed out!")

    t = Transport(ZenohOptions.loopback())
    t._session = fine = _StuckSession()
    assert t.close(timeout_s=2.0) is True
    assert t.close_error is None
    assert fine.closed.is_set()
    t._session = _StuckSession(error=zenoh.ZError("close operation timed out!"))
    with pytest.raises(zenoh.ZError):  # unbounded, as before: zenoh's error is raised
        t.close()
