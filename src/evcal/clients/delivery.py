"""What a replay sent and what the service says it took: the exit codes of ``evcal replay``
(with ``--ros2`` too), a run's account, its confirmation through the camera's status, and the
account as printed per camera.

Shared by :mod:`evcal.clients.replay` and :mod:`evcal.clients.rosreplay` (neither imports
the other for it).
"""

from __future__ import annotations

import json
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from evcal.service import keys
from evcal.service.transport import Transport

T = TypeVar("T")

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_NOBODY = 3
EXIT_LOST = 4
EXIT_REFUSED = 5
EXIT_DROPPED = 6
EXIT_UNCONFIRMED = 7
# (code, outcome, meaning), in the order they are judged; --help prints it
EXIT_CODES = (
    (EXIT_OK, "all taken", "the service confirmed it processed every message sent"),
    (EXIT_ERROR, "error", "the zenoh session failed (or a put raised)"),
    (EXIT_USAGE, "usage", "bad arguments or an unreadable recording"),
    (EXIT_NOBODY, "nobody there", "no subscriber after --wait-subscriber: nothing was sent"),
    (EXIT_REFUSED, "refused", "the service refused the camera (no slot: --max-cameras, or "
                              "its probation slot given to another camera) or rejected "
                              "messages"),
    (EXIT_DROPPED, "dropped", "the service's queue dropped messages (--on-full drop)"),
    (EXIT_LOST, "lost", "messages never reached the service: sent while nobody "
                        "subscribed, the service gone during the run, or missing from its "
                        "account"),
    (EXIT_UNCONFIRMED, "unconfirmed", "no service confirmed delivery within "
                                      "--confirm-timeout (only a recorder listens, the "
                                      "service is too busy, or the replay was stopped with a "
                                      "put still blocked)"),
)

CONFIRM_TIMEOUT_S = 60.0  # how long the status is asked for after the run
STOPPED_CONFIRM_S = 1.0  # the same after SIGINT/SIGTERM: the user wants out
STATUS_QUERY_S = 2.0  # one status query


@dataclass
class ReplayStats:
    """What was sent, and what the service says it received (``delivered``)."""

    events: int = 0
    event_messages: int = 0
    frames: int = 0
    bytes: int = 0
    seconds: float = 0.0
    subscribed: bool = True  # a subscriber matched before sending
    unmatched_messages: int = 0  # sent while nobody subscribed (lost)
    service_gone: bool = False  # the service answered before the run and not after
    # the service's account of this run (status differences), None when no service answered
    delivered: dict[str, int] | None = None
    # the account is complete: every message sent is in it, or the service had nothing of
    # this camera in flight when it last answered (the rest is not coming)
    confirmed: bool = False
    refusal: dict[str, Any] | None = None  # the service's refusal of the camera, if any
    displaced: int = 0  # times during the run the camera lost its slot to another camera
    stopped: bool = False  # SIGINT/SIGTERM (``stop``) ended the run early
    stuck_put: bool = False  # stopped while a put still waited for a stalled receiver
    send_error: str | None = None  # a put raised (the session failed)
    why_unconfirmed: str = ""

    @property
    def messages(self) -> int:
        return self.event_messages + self.frames

    @property
    def missing_messages(self) -> int | None:
        """Messages the service never saw (neither processed, dropped nor refused)."""
        if self.delivered is None:
            return None
        return self.messages - self.delivered["accounted_messages"]

    @property
    def events_per_s(self) -> float:
        return self.events / self.seconds if self.seconds > 0 else 0.0


def exit_code(stats: ReplayStats) -> int:
    """The exit code of a run (:data:`EXIT_CODES`, judged in that order)."""
    if stats.send_error is not None:
        return EXIT_ERROR
    if not stats.subscribed:
        return EXIT_NOBODY
    d = stats.delivered
    if stats.displaced or (d is not None and (d["refused_messages"]
                                              or d["rejected_messages"])):
        return EXIT_REFUSED
    if d is not None and d["dropped_messages"]:
        return EXIT_DROPPED
    if stats.unmatched_messages or stats.service_gone or (
            stats.confirmed and (stats.missing_messages or 0) > 0):
        return EXIT_LOST
    if not stats.confirmed:
        return EXIT_UNCONFIRMED
    return EXIT_OK


# ----------------------------------------------------------------------------- the account


@dataclass
class StatusProbe:
    """One status query: whether it finished in time, and the document (None: no reply)."""

    answered: bool
    doc: dict[str, Any] | None = None


def _bounded(fn: Callable[[], T], timeout_s: float) -> tuple[bool, T | None]:
    """``fn()`` on a daemon thread, waited for at most ``timeout_s``: ``(finished, value)``.

    A zenoh query is sent with congestion control BLOCK and waits behind a put that a
    stalled receiver holds, whatever its own timeout (zenoh 1.10): the caller must not.
    """
    box: dict[str, Any] = {}

    def call() -> None:
        try:
            box["value"] = fn()
        except Exception:  # noqa: BLE001 - a query that fails answers nothing
            box["value"] = None

    th = threading.Thread(target=call, name="evcal-replay-query", daemon=True)
    th.start()
    th.join(timeout_s)
    return ("value" in box), box.get("value")


def probe_status(t: Transport, key: str, timeout_s: float = STATUS_QUERY_S) -> StatusProbe:
    """Ask the service for ``key`` once. ``answered`` False: the query did not finish in
    time (a busy or stalled service), so no reply says nothing about the camera."""
    t_start = time.monotonic()
    done, replies = _bounded(lambda: t.get(key, timeout_s=timeout_s), timeout_s + 0.5)
    ok = [r for r in (replies or []) if r.ok]
    # zenoh's own timeout ends a query with the replies so far: not an answer either
    answered = done and (bool(ok) or time.monotonic() - t_start < 0.95 * timeout_s)
    doc = None
    if ok:
        try:
            doc = json.loads(ok[0].payload)
        except ValueError:
            doc = None
    return StatusProbe(answered, doc if isinstance(doc, dict) else None)


def _service_alive(t: Transport, prefix: str) -> bool:
    """Whether an evcal service's liveliness token is up (asked once, at most 1.5 s)."""
    _, alive = _bounded(lambda: t.alive(keys.service_token_key(prefix), timeout_s=1.0), 1.5)
    return bool(alive)


def _refusal_counts(doc: dict[str, Any] | None) -> tuple[int, int]:
    ref = (doc or {}).get("refused") or {}
    return int(ref.get("messages", 0)), int(ref.get("displaced", 0))


def _account(st: dict[str, Any], before: dict[str, Any]) -> dict[str, int]:
    """This run's share of the camera's counters: ``st`` less ``before``."""
    def diff(name: str) -> int:
        v, b = st.get(name, 0), before.get(name, 0)
        if isinstance(v, dict):
            return int(sum(v.values()) - sum((b or {}).values()))
        return int((v or 0) - (b or 0))

    refused_now, _ = _refusal_counts(st)
    refused_before, _ = _refusal_counts(before)
    out = {"event_messages": diff("event_messages"), "events": diff("events"),
           "frames": diff("frames"), "dropped_messages": diff("dropped_messages"),
           "rejected_messages": diff("errors"),
           "refused_messages": refused_now - refused_before,
           # reached a service process that died after its last snapshot: processed, then
           # forgotten (the counters above went back with the snapshot)
           "rolled_back_messages": diff("rolled_back_messages")}
    out["accounted_messages"] = (out["event_messages"] + out["frames"]
                                 + out["dropped_messages"] + out["rejected_messages"]
                                 + out["refused_messages"] + out["rolled_back_messages"])
    return out


def _baseline(before: StatusProbe, after: dict[str, Any], since_s: float | None
              ) -> dict[str, Any] | None:
    """The counters this run's account starts from (None: unknown).

    A camera that came into the service's memory during the run (``serving_s`` shorter than
    the run, which began at ``since_s``, monotonic) started from zero, whatever was asked
    before: it is new, or it lost its slot and came back. Otherwise the status read before
    the run, if that query was answered.
    """
    serving_s = after.get("serving_s")
    refusal_only = {"refused": before.doc.get("refused")} if before.doc else {}
    if (since_s is not None and isinstance(serving_s, int | float)
            and serving_s < time.monotonic() - since_s):
        return refusal_only  # its counters began during the run
    if before.doc is not None:
        return before.doc
    return {} if before.answered else None


def confirm(t: Transport, stats: ReplayStats, key: str, before: StatusProbe, *,
             prefix: str, since_s: float | None, deadline: float,
             stop_now: threading.Event) -> None:
    """Ask the camera's status until the service's account of the run is complete or
    ``deadline`` (monotonic) passes; fills ``stats.delivered``, ``confirmed``, ``refusal``.

    A reply comes after every message put before the query (they share the link), so once
    one says nothing of this camera is in flight at the service, twice in a row with the
    same counts, the rest is not coming. A service that never answered for the camera is
    asked until the deadline only while its liveliness token is up and its queries do not
    finish empty: a service takes a camera (or refuses it) as its first message arrives,
    before the query behind it, so a busy one answers late, while one that answers nothing
    in time, twice, does not serve the camera (another instance's claim or shard, or access
    control hides it); with no token up, nobody will answer.
    """
    sent = stats.messages
    _, displaced_before = _refusal_counts(before.doc)
    alive: bool | None = None
    last: dict[str, int] | None = None
    stable = 0
    answered_once = False
    empty_answers = 0
    while not stop_now.is_set():
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        probe = probe_status(t, key, min(STATUS_QUERY_S, max(remaining, 0.2)))
        doc = probe.doc
        if doc is not None:
            answered_once = True
            if doc.get("refused"):
                stats.refusal = doc["refused"]
                stats.displaced = _refusal_counts(doc)[1] - displaced_before
            base = _baseline(before, doc, since_s)
            if base is None:
                stats.why_unconfirmed = ("the service did not answer for the camera before "
                                         "the run and the camera is older than the run: "
                                         "its counters cannot be split")
                break
            acc = _account(doc, base)
            stats.delivered = acc
            if acc["accounted_messages"] >= sent:
                stats.confirmed = True
                break
            # a refused camera's messages are counted as they arrive: none in flight;
            # a service before in_flight_messages: its queue, and 2 s without a change
            exact = "in_flight_messages" in doc or doc.get("state") == "refused"
            in_flight = (doc.get("in_flight_messages", 0) if exact
                         else doc.get("queue_messages"))
            stable = stable + 1 if acc == last and in_flight == 0 else 0
            if stable >= (1 if exact else 10):
                stats.confirmed = True  # nothing of it in flight: the rest never arrived
                break
            last = acc
        elif not answered_once:
            if alive is None:
                alive = _service_alive(t, prefix)
            if not alive:
                time.sleep(0.5)  # what was put leaves before the session closes
                stats.why_unconfirmed = "no evcal service is up (its liveliness token)"
                break
            empty_answers = empty_answers + 1 if probe.answered else 0
            if empty_answers >= 2:
                stats.why_unconfirmed = ("the service answers nothing for the camera: it "
                                         "does not serve it (another instance's --cameras "
                                         "claim or shard?) or access control hides it")
                break
        stop_now.wait(0.2)
    if stats.delivered is None and before.doc is not None and not stop_now.is_set() \
            and not _service_alive(t, prefix):
        stats.service_gone = True  # it answered before the run, not after: link lost?
    if not stats.confirmed and not stats.why_unconfirmed:
        stats.why_unconfirmed = ("the service's account was not complete within the wait"
                                 if stats.delivered is not None else
                                 "no evcal service answered for the camera within the wait")


def exit_code_table() -> str:
    """The exit codes as text (``--help``)."""
    rows = [textwrap.fill(meaning, 79, initial_indent=f"  {code}  {outcome:<14}",
                          subsequent_indent=" " * 19)
            for code, outcome, meaning in (*EXIT_CODES[1:], EXIT_CODES[0])]
    return "exit codes (judged in this order; 0 when none applies):\n" + "\n".join(rows)


def print_account(prog: str, acc: ReplayStats, *, target: str = "",
                  camera: str | None = None) -> None:
    """Print, on stderr, what the service says of one camera's messages: gone, refused,
    processed (with what it dropped, rejected and refused), missing, unconfirmed. ``camera``
    names it (``evcal replay --ros2``: one account per camera); else ``target`` is the
    camera's key prefix."""
    who = "" if camera is None else f"camera {camera}: "
    if acc.service_gone:
        where, hint = ((f"on {target}/status", " (a stall longer than --block-timeout?)")
                       if camera is None else ("for it", ""))
        print(f"{prog}: {who}the service answered {where} before the run but not after it, "
              f"and is gone: the link was lost{hint} and messages may be lost",
              file=sys.stderr)
    d = acc.delivered
    if acc.refusal is not None and (acc.displaced or (d or {}).get("refused_messages")):
        it = "the camera" if camera is None else "it"
        print(f"{prog}: {who}the service refused {it}: {acc.refusal.get('reason')}: "
              f"{acc.refusal.get('message')}", file=sys.stderr)
    if d is not None:
        print(f"{prog}: {who}the service processed {d['event_messages']} event messages "
              f"({d['events']} events) and {d['frames']} frames, dropped "
              f"{d['dropped_messages']}, rejected {d['rejected_messages']} and refused "
              f"{d['refused_messages']} "
              + ("messages" if camera is None else f"of {acc.messages}"), file=sys.stderr)
        rolled = d.get("rolled_back_messages", 0)
        if rolled > 0:
            print(f"{prog}: {who}{rolled} messages were rolled back: the service restarted "
                  "and resumed the camera from its last snapshot, so what they brought is "
                  "not in its calibration (status: restored)", file=sys.stderr)
        missing = acc.missing_messages or 0
        if acc.confirmed and missing > 0:
            print(f"{prog}: {who}{missing} of {acc.messages} messages never reached the "
                  "service", file=sys.stderr)
    if not acc.confirmed and acc.send_error is None:
        print(f"{prog}: {who}delivery not confirmed: {acc.why_unconfirmed}", file=sys.stderr)


def print_outcome(prog: str, code: int) -> int:
    """Print the outcome of exit code ``code`` (:data:`EXIT_CODES`) on stderr; return it."""
    outcome = {c: o for c, o, _ in EXIT_CODES}[code]
    print(f"{prog}: {outcome} (exit code {code})", file=sys.stderr)
    return code
