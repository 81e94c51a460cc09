"""Large payloads through zenoh shared memory (``Transport.put`` and its ``ShmPool``): real
sessions on tcp/127.0.0.1, scouting off; what arrives is checked byte for byte."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from evcal.service.transport import ShmPool, Transport, ZenohOptions
from evcal.testing import endpoint, free_port, wait_for

KEY = "test/shm/payload"


def _payload(n: int, seed: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 255, n, np.uint8).tobytes()


def _exchange(tx_opts: ZenohOptions, rx_opts: ZenohOptions, payloads: list[bytes], *,
              shm_pool_mb: float = 64.0) -> tuple[list[bytes], dict[str, int]]:
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
