"""Minimal reproduction (zenoh only, no evcal): a router whose receive threads are all held
by pushes to one slow subscriber reads no other link, so another client's replies stall
and its lease expires.

    python scripts/zenoh_router_starvation.py [--rx-threads N] [--seconds 30]

Five processes on ``tcp/127.0.0.1`` (multicast scouting off): a router; a slow subscriber
(its callback sleeps 20 ms per sample); two publishers putting 64 KiB samples as fast as
they may with congestion control BLOCK; a queryable that answers with 2.4 MB; and, in this
process, a client that queries it every 0.3 s. zenoh runs every link's receive loop on one
thread pool (``ZENOH_RUNTIME``'s ``rx``, 2 threads by default on 2 cores); a loop routing a
sample to the slow subscriber waits in ``StageIn::push_network_message`` for room in its
queue, holding its thread. With both publishers' loops waiting, no thread is left to read
the queryable's link: its reply waits, then its 10 s lease expires and the router closes it.

Measured with eclipse-zenoh 1.10.2 (2 cores, 25 s): ``--rx-threads 2`` (the default
here): 3 of 8 queries not answered within 5 s, the others after up to 4.5 s; ``--rx-threads
16``: 56 of 56 answered. Prints one line per query and a summary; exits 1 when a query was
not answered.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import socket
import sys
import time

PAYLOAD = 64 * 1024
REPLY = 2_400_000


def _config(mode: str, *, listen: str | None = None, connect: str | None = None):  # noqa: ANN202
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", f'"{mode}"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        conf.insert_json5("listen/endpoints", f'["{listen}"]')
    if connect:
        conf.insert_json5("connect/endpoints", f'["{connect}"]')
    return conf


def _router(ep: str, rx_threads: int, stop: mp.Event) -> None:  # type: ignore[valid-type]
    os.environ["ZENOH_RUNTIME"] = f"(rx: (worker_threads: {rx_threads}))"
    import zenoh

    with zenoh.open(_config("router", listen=ep)):
        stop.wait()  # type: ignore[attr-defined]


def _slow_subscriber(ep: str, stop: mp.Event) -> None:  # type: ignore[valid-type]
    import zenoh

    with zenoh.open(_config("client", connect=ep)) as s:
        s.declare_subscriber("demo/data", lambda _sample: time.sleep(0.02))
        stop.wait()  # type: ignore[attr-defined]


def _publisher(ep: str, stop: mp.Event) -> None:  # type: ignore[valid-type]
    import zenoh

    with zenoh.open(_config("client", connect=ep)) as s:
        pub = s.declare_publisher("demo/data", congestion_control=zenoh.CongestionControl.BLOCK)
        data = bytes(PAYLOAD)
        while not stop.is_set():  # type: ignore[attr-defined]
            pub.put(data)


def _queryable(ep: str, stop: mp.Event) -> None:  # type: ignore[valid-type]
    import zenoh

    reply = bytes(REPLY)
    with zenoh.open(_config("client", connect=ep)) as s:
        s.declare_queryable("demo/q", lambda q: q.reply("demo/q", reply))
        stop.wait()  # type: ignore[attr-defined]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rx-threads", type=int, default=2)
    p.add_argument("--seconds", type=float, default=30.0)
    args = p.parse_args(argv)
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{sock.getsockname()[1]}"
    ctx = mp.get_context("spawn")
    stop = ctx.Event()
    procs = [ctx.Process(target=_router, args=(ep, args.rx_threads, stop), daemon=True)]
    procs[0].start()
    time.sleep(1.0)
    procs += [ctx.Process(target=f, args=(ep, stop), daemon=True)
              for f in (_queryable, _slow_subscriber, _publisher, _publisher)]
    for proc in procs[1:]:
        proc.start()
    time.sleep(2.0)
    import zenoh

    answered = failed = 0
    try:
        with zenoh.open(_config("client", connect=ep)) as s:
            t_end = time.monotonic() + args.seconds
            while time.monotonic() < t_end:
                t0 = time.monotonic()
                n = sum(1 for r in s.get("demo/q", timeout=5.0) if r.ok is not None)
                dt = time.monotonic() - t0
                answered += n > 0
                failed += n == 0
                print(f"query: {'answered' if n else 'NOT answered'} in {dt:.2f} s", flush=True)
                time.sleep(0.3)
    finally:
        stop.set()
        for proc in procs:
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
    print(f"router rx threads {args.rx_threads}: {answered} answered, {failed} not")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
