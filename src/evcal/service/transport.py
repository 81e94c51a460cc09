"""Zenoh transport: the only module of evcal that imports :mod:`zenoh`.

Everything else talks to the network through :class:`Transport` (an open session) with plain
Python types: key strings, ``bytes`` payloads, encoding strings, and :class:`Request` for a
query. Connection options are a :class:`ZenohOptions` (no zenoh objects), built from the
command-line flags of zenoh's own examples by :func:`add_zenoh_arguments` /
:func:`options_from_args`.

Facts this module relies on (eclipse-zenoh 1.10):

- A callback handler with ``indirect=False`` runs in zenoh's receive thread; with the default
  (``indirect=True``) zenoh queues samples for a Python thread in an *unbounded* queue. We
  always use ``indirect=False`` and keep our own bounded queues (see ``core.CameraQueue``).
- Sessions must be closed: an open session holding callback subscribers keeps the process
  alive. :class:`Transport` is a context manager.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from ..errors import ConfigError

log = logging.getLogger("evcal.transport")

# sessions whose bounded close timed out: kept referenced until the process exits
_LEFT_OPEN: list[Any] = []

MODES = ("peer", "client", "router")


class TransportError(RuntimeError):
    """The session could not be opened or an operation on it failed."""


@dataclass(frozen=True, kw_only=True)
class ZenohOptions:
    """How to open a session; ``None`` keeps zenoh's default (or the config file's value)."""

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    multicast_scouting: bool | None = None
    extra: tuple[tuple[str, str], ...] = field(default=())  # (key, json5 value)

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in MODES:
            raise ConfigError(f"zenoh mode {self.mode!r} is not one of {MODES}")

    @classmethod
    def loopback(cls, *, listen: Iterable[str] = (), connect: Iterable[str] = (),
                 mode: str = "peer") -> ZenohOptions:
        """Options for tests and the embedded demo: explicit endpoints, no scouting."""
        return cls(mode=mode, listen=tuple(listen), connect=tuple(connect),
                   multicast_scouting=False)

    def to_config(self) -> zenoh.Config:
        try:
            conf: zenoh.Config = (zenoh.Config.from_file(self.config_file)
                                  if self.config_file else zenoh.Config())
            if self.mode is not None:
                conf.insert_json5("mode", json.dumps(self.mode))
            if self.connect:
                conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
            if self.listen:
                conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
            if self.multicast_scouting is not None:
                conf.insert_json5("scouting/multicast/enabled",
                                  json.dumps(bool(self.multicast_scouting)))
            for key, value in self.extra:
                conf.insert_json5(key, value)
        except Exception as exc:  # zenoh raises ZError for bad config values
            raise TransportError(f"invalid zenoh configuration: {exc}") from None
        return conf


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """The connection flags of zenoh's examples: --mode, --connect, --listen, --config."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", "-m", choices=MODES, help="zenoh session mode (default: peer)")
    g.add_argument("--connect", "-e", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", "-l", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to listen on (repeatable)")
    g.add_argument("--config", "-c", metavar="FILE", help="a zenoh JSON5 configuration file")
    g.add_argument("--no-multicast-scouting", action="store_true",
                   help="disable multicast scouting (find peers only through --connect); "
                        "the default whenever an endpoint is given (--connect, --listen, "
                        "EVCAL_CONNECT, EVCAL_LISTEN)")
    g.add_argument("--multicast-scouting", action="store_true",
                   help="find peers by multicast scouting even with endpoints given (it "
                        "joins every evcal process of the local network under the prefix)")
    g.add_argument("--cfg", metavar="KEY:VALUE", action="append", default=[],
                   help="any zenoh configuration change, VALUE in JSON5, e.g. "
                        "--cfg='transport/unicast/max_links:2' (repeatable)")


ENV_PREFIX = "EVCAL_"  # EVCAL_CONNECT, EVCAL_LISTEN, EVCAL_ZENOH_CONFIG, EVCAL_MODE


def _env_list(name: str) -> tuple[str, ...]:
    return tuple(e.strip() for e in os.environ.get(ENV_PREFIX + name, "").split(",")
                 if e.strip())


def options_from_args(args: argparse.Namespace) -> ZenohOptions:
    """The session options of the flags, with ``EVCAL_CONNECT`` / ``EVCAL_LISTEN``
    (comma-separated endpoints), ``EVCAL_ZENOH_CONFIG`` (a JSON5 file) and ``EVCAL_MODE``
    as the defaults of ``--connect``, ``--listen``, ``--config`` and ``--mode``: a flag given
    on the command line wins over its variable."""
    mode = args.mode or os.environ.get(ENV_PREFIX + "MODE") or None
    if mode is not None and mode not in MODES:
        raise ValueError(f"{ENV_PREFIX}MODE={mode!r}: expected one of {', '.join(MODES)}")
    connect = tuple(args.connect) or _env_list("CONNECT")
    listen = tuple(args.listen) or _env_list("LISTEN")
    config = args.config or os.environ.get(ENV_PREFIX + "ZENOH_CONFIG") or None
    if config is not None and not os.path.isfile(config):
        raise ValueError(f"zenoh configuration file {config!r} does not exist"
                         + ("" if args.config else f" ({ENV_PREFIX}ZENOH_CONFIG)"))
    extra = []
    for item in args.cfg:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise ValueError(f"--cfg {item!r}: expected KEY:VALUE, e.g. "
                             "'transport/unicast/max_links:2'")
        extra.append((key, value))
    return ZenohOptions(
        mode=mode, connect=connect, listen=listen, config_file=config,
        # explicit endpoints make a deployment: scouting would join it to every other
        # evcal process of the host or network (zenoh's default, kept without endpoints)
        multicast_scouting=_scouting(args, bool(connect or listen)),
        extra=tuple(extra),
    )


def _scouting(args: argparse.Namespace, endpoints: bool) -> bool | None:
    """Multicast scouting of the flags: off with --no-multicast-scouting or with endpoints
    given, on with --multicast-scouting, else None (zenoh's default, or the config file's)."""
    if getattr(args, "multicast_scouting", False):
        if args.no_multicast_scouting:
            raise ValueError("--multicast-scouting and --no-multicast-scouting contradict "
                             "each other")
        return True
    return False if args.no_multicast_scouting or endpoints else None


# ----------------------------------------------------------------------------- key helpers


def check_key(key: str, what: str = "key expression") -> str:
    """``key`` if it is a valid zenoh key expression (canonical form), else ValueError."""
    try:
        zenoh.KeyExpr(key)
    except Exception as exc:
        raise ValueError(f"{what} {key!r} is not a valid zenoh key expression ({exc}); "
                         "chunks are separated by '/', may not be empty and may not contain "
                         "'?', '#' or '$' other than in '$*'") from None
    return key


def intersects(a: str, b: str) -> bool:
    """True when the key expressions ``a`` and ``b`` share at least one key."""
    return bool(zenoh.KeyExpr(a).intersects(b))


def includes(a: str, b: str) -> bool:
    """True when every key of ``b`` is a key of ``a``."""
    return bool(zenoh.KeyExpr(a).includes(b))


# ----------------------------------------------------------------------------- the session


class Request:
    """One query, handed to a queryable's callback."""

    def __init__(self, query: Any, queryable_key: str):
        self._query = query
        self.key = str(query.key_expr)
        self.queryable_key = queryable_key
        self.parameters: dict[str, str] = {k: v for k, v in query.parameters}

    def matches(self, key: str) -> bool:
        """Whether a reply on concrete ``key`` answers this query."""
        return intersects(self.key, key)

    def reply(self, key: str, payload: bytes, encoding: str, *,
              attachment: bytes | None = None) -> None:
        self._query.reply(key, payload, encoding=zenoh.Encoding(encoding),
                          attachment=attachment)

    def reply_err(self, message: str) -> None:
        self._query.reply_err(message.encode(), encoding=zenoh.Encoding.TEXT_PLAIN)



@dataclass(frozen=True)
class Reply:
    """One answer to :meth:`Transport.get`: ``ok`` False for a queryable's error reply."""

    ok: bool
    key: str
    payload: bytes
    encoding: str
    attachment: bytes | None = None


class Publisher:
    """A declared publisher: one key, one encoding."""

    def __init__(self, pub: Any):
        self._pub = pub

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        self._pub.put(payload, attachment=attachment)

    @property
    def has_subscribers(self) -> bool:
        status = self._pub.matching_status
        return bool(getattr(status, "matching", status))


class Declared:
    """A token or queryable of a :class:`Transport`: ``undeclare()`` ends it before the
    session closes (which ends it anyway)."""

    def __init__(self, transport: Transport, entity: Any) -> None:
        self._transport = transport
        self._entity = entity

    def undeclare(self) -> None:
        self._transport._forget(self._entity)
        try:
            self._entity.undeclare()
        except Exception:  # already gone with the session
            pass


class LatchedPublisher(Declared):
    """A publisher whose last ``depth`` samples also reach subscribers that join later:
    zenoh's advanced publisher with a cache and publisher detection (a liveliness token under
    ``<key>/@adv/pub/...``), answered by an advanced subscriber with history
    (:meth:`Transport.subscribe` ``history=True``; rmw_zenoh's TRANSIENT_LOCAL subscriptions
    are such subscribers). A plain subscriber gets its samples as from a plain put. The cached
    sample keeps its payload, encoding and attachment; ``undeclare()`` stops serving it.
    """

    def __init__(self, transport: Transport, pub: Any, key: str) -> None:
        super().__init__(transport, pub)
        self.key = key

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        self._entity.put(self._transport.shm.payload(payload), attachment=attachment)


class ShmPool:
    """Large payloads put through a zenoh shared-memory provider, for subscribers on this host.

    zenoh copies an ordinary payload of a local put into its own shared memory anyway (its
    transport optimisation, above 3 KiB) but only after the put has handed it through its
    pipeline in batches, several times slower for a 1280x720 camera's calibration message
    than writing it into the provider's memory first (``bench_service.py shm``; figures in
    docs/MEASUREMENTS.md). Remote
    subscribers get the bytes as usual. The pool is created on the first payload of at least
    ``threshold_bytes`` (small sensors never create it); when it cannot be (a container's
    small /dev/shm) or is full (subscribers still hold its buffers), the payload goes as
    ordinary bytes and :attr:`fallbacks` counts it.

    ``size_bytes`` None sizes the pool by that first payload: room for ``AUTO_MESSAGES`` of
    it, at least ``AUTO_MIN_BYTES``, at most half the space free in /dev/shm (a pool larger
    than its file system would fail on the first write past it). A buffer returns to the
    pool only once every subscriber has dropped it, which takes more than one update
    interval: with room for 3 messages of 16.7 MiB (a 64 MiB pool, 1280x720 at 20 M
    events/s, an update every 0.24 s) 27 of 259 went as bytes, each put then taking 10-25
    ms instead of 1.7 (the slowest updates); with room for 9, 2 of 260; with room for 12 (this
    default), 1 of about 250 in each of two runs (2026-11-25).
    """

    AUTO_MESSAGES = 12
    AUTO_MIN_BYTES = 64 << 20
    SHM_DIR = "/dev/shm"

    def __init__(self, size_bytes: int | None, threshold_bytes: int = 1 << 20) -> None:
        self.size_bytes = int(size_bytes) if size_bytes is not None else None
        self.threshold_bytes = int(threshold_bytes)
        self._provider: Any = None
        self._broken = self.size_bytes is not None and self.size_bytes <= 0
        self._lock = threading.Lock()
        self.puts = 0  # payloads sent from shared memory
        self.fallbacks = 0  # large payloads sent as bytes (no pool, or it was full)

    def payload(self, data: bytes) -> Any:
        """``data`` in shared memory when large and possible, else ``data``."""
        n = len(data)
        if n < self.threshold_bytes or self._broken:
            return data
        if self.size_bytes is None:
            with self._lock:
                if self.size_bytes is None:
                    self.size_bytes = self._auto_size(n)
        if n > self.size_bytes:
            self.fallbacks += 1
            return data
        try:
            from zenoh.shm import GarbageCollect, ShmProvider  # noqa: PLC0415

            with self._lock:
                if self._provider is None:
                    self._provider = ShmProvider.default_backend(self.size_bytes)
            buf = self._provider.alloc(n, policy=GarbageCollect())
        except Exception as exc:  # ZError: no shared memory here, or the pool is full
            self.fallbacks += 1
            if self._provider is None:
                self._broken = True
                log.warning("zenoh shared memory unavailable (%s): large payloads go as "
                            "bytes", exc)
            return data
        buf[0:n] = data
        self.puts += 1
        return buf

    def _auto_size(self, n: int) -> int:
        """The pool's size for payloads of ``n`` bytes (see the class)."""
        want = max(self.AUTO_MIN_BYTES, self.AUTO_MESSAGES * n)
        try:
            st = os.statvfs(self.SHM_DIR)
            want = min(want, st.f_bavail * st.f_frsize // 2)
        except OSError:  # no /dev/shm to ask: the minimum
            want = self.AUTO_MIN_BYTES
        return int(want)

    def stats(self) -> dict[str, int]:
        return {"pool_bytes": (self.size_bytes or 0) if not self._broken else 0,
                "puts": self.puts, "fallbacks": self.fallbacks}


class Transport:
    """An open zenoh session; use as ``with Transport(options) as t: ...``.

    Callbacks run in zenoh's receive threads (``indirect=False``): they must be quick and must
    not raise (exceptions are logged and swallowed so a bad message never kills a thread).
    Payloads of :meth:`put` from 1 MiB go through shared memory (:class:`ShmPool`, sized by
    the first of them unless ``shm_pool_mb`` is given) unless the zenoh configuration turns
    shared memory off (``transport/shared_memory/enabled``) or ``shm_pool_mb`` is 0.
    """

    def __init__(self, options: ZenohOptions, *, shm_pool_mb: float | None = None):
        self.options = options
        self._session: Any = None
        self._entities: list[Any] = []
        self._lock = threading.Lock()
        self._latched: dict[str, LatchedPublisher] = {}  # put(..., latest=True) by key
        self.shm = ShmPool(None if shm_pool_mb is None else int(shm_pool_mb * (1 << 20)))
        self.close_error: str | None = None  # why a bounded close did not finish

    def __enter__(self) -> Transport:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        try:
            conf = self.options.to_config()
            if str(conf.get_json("transport/shared_memory/enabled")).strip() == "false":
                self.shm = ShmPool(0)
            self._session = zenoh.open(conf)
        except TransportError:
            raise
        except Exception as exc:
            raise TransportError(f"cannot open a zenoh session ({self.options}): {exc}") \
                from None

    def close(self, timeout_s: float | None = None) -> bool:
        """Undeclare what was declared and close the session; True when it closed.

        ``timeout_s`` None waits for zenoh (its errors raised). Otherwise the close is
        bounded: zenoh's own gives up after 10 s (``ZError: close operation timed out``)
        and an undeclaration waits without bound behind a stuck router (seen with zenoh
        1.10.2, docs/SERVICE.md "Scale-out"). After ``timeout_s`` the session is left open
        for the process's exit, which ends it at once; False, and :attr:`close_error`
        says why.
        """
        if timeout_s is None:
            self._close_now()
            return True
        box: dict[str, BaseException] = {}

        def run() -> None:
            try:
                self._close_now()
            except BaseException as exc:  # reported by the caller's thread, never raised here
                box["error"] = exc

        th = threading.Thread(target=run, name="evcal-zenoh-close", daemon=True)
        th.start()
        th.join(timeout_s)
        if th.is_alive():
            self.close_error = f"the zenoh session did not close within {timeout_s:g} s"
            _LEFT_OPEN.append(self)  # dropping the last reference would wait as well
            return False
        if "error" in box:
            exc = box["error"]
            self.close_error = f"closing the zenoh session failed: {type(exc).__name__}: {exc}"
            return False
        return True

    def _close_now(self) -> None:
        with self._lock:
            entities, self._entities = self._entities, []
            self._latched.clear()
        for e in reversed(entities):
            try:
                e.undeclare()
            except Exception:  # already gone with the session
                pass
        session, self._session = self._session, None
        if session is not None:
            session.close()

    @property
    def session(self) -> Any:
        if self._session is None:
            raise TransportError("the zenoh session is not open")
        return self._session

    @property
    def zid(self) -> str:
        return str(self.session.zid())

    def _keep(self, entity: Any) -> Any:
        with self._lock:
            self._entities.append(entity)
        return entity

    def _forget(self, entity: Any) -> None:
        with self._lock:
            self._entities = [e for e in self._entities if e is not entity]

    def subscribe(self, key: str, callback: Callable[..., None], *,
                  attachment: bool = False, accept: Callable[[str], bool] | None = None,
                  history: bool = False) -> None:
        """Call ``callback(key, payload, encoding)`` for every sample on ``key`` (a glob);
        with ``attachment``, ``callback(key, payload, encoding, attachment)`` (the sample's
        attachment bytes, or None). ``accept(sample_key)`` False skips a sample before its
        payload is copied (another shard's camera costs a key comparison, not a copy).

        ``history``: also the last sample of every key of ``key`` that a
        :class:`LatchedPublisher` published before this subscriber joined (zenoh's advanced
        subscriber, detecting publishers that come later too), then live samples as usual.
        """

        def on_sample(sample: Any) -> None:
            try:
                sample_key = str(sample.key_expr)
                if accept is not None and not accept(sample_key):
                    return
                args = [sample_key, sample.payload.to_bytes(), str(sample.encoding)]
                if attachment:
                    att = sample.attachment
                    args.append(att.to_bytes() if att is not None else None)
                callback(*args)
            except Exception:
                log.exception("subscriber callback on %s failed", key)

        handler = zenoh.handlers.Callback(on_sample, indirect=False)
        if history:
            from zenoh import ext  # noqa: PLC0415

            self._keep(ext.declare_advanced_subscriber(
                self.session, key, handler,
                history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1)))
            return
        self._keep(self.session.declare_subscriber(key, handler))

    def queryable(self, key: str, callback: Callable[[Request], None], *,
                  complete: bool = True) -> Declared:
        """Call ``callback(request)`` for every query intersecting ``key``. ``complete``
        says this queryable has every answer for ``key``: a query with zenoh's default target
        (best matching) is then sent to it alone; a shard holds only some cameras of ``key``
        and declares ``complete=False``, so that such a query reaches every shard."""

        def on_query(query: Any) -> None:
            # ``with query`` drops it at the end: the querier stops waiting once every
            # matched queryable dropped its query (finalisers are not reliable).
            with query:
                try:
                    callback(Request(query, key))
                except Exception as exc:
                    log.exception("queryable callback on %s failed", key)
                    try:
                        query.reply_err(f"internal error: {exc}".encode())
                    except Exception:
                        pass

        return Declared(self, self._keep(self.session.declare_queryable(
            key, zenoh.handlers.Callback(on_query, indirect=False), complete=complete)))

    def publisher(self, key: str, encoding: str, *, block: bool = False,
                  express: bool = False) -> Publisher:
        """Declare a publisher; ``block`` waits when the link is congested instead of dropping."""
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        return Publisher(self._keep(self.session.declare_publisher(
            key, encoding=zenoh.Encoding(encoding), congestion_control=cc, express=express)))

    def put(self, key: str, payload: bytes, encoding: str, *, block: bool = False,
            attachment: bytes | None = None, latest: bool = False) -> None:
        """Put one sample on ``key``. ``latest``: through the key's :class:`LatchedPublisher`
        (declared on its first such put, with this ``encoding`` and ``block``), so that a
        subscriber with history that joins later still gets the last sample."""
        if latest:
            with self._lock:
                pub = self._latched.get(key)
            if pub is None:
                pub = self.latched(key, encoding, block=block)
                with self._lock:
                    pub = self._latched.setdefault(key, pub)
            pub.put(payload, attachment=attachment)
            return
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self.session.put(key, self.shm.payload(payload), encoding=zenoh.Encoding(encoding),
                         congestion_control=cc, attachment=attachment)

    def latched(self, key: str, encoding: str, *, depth: int = 1, block: bool = False,
                heartbeat_s: float | None = None) -> LatchedPublisher:
        """Declare a :class:`LatchedPublisher` on the concrete ``key`` keeping its last
        ``depth`` samples for late joiners. ``heartbeat_s``: also announce the last sequence
        number every so often when it changed (zenoh's sporadic heartbeat), so that a
        subscriber with recovery asks for a last sample it missed (rmw_zenoh's RELIABLE,
        TRANSIENT_LOCAL publishers do, every 0.5 s)."""
        from zenoh import ext  # noqa: PLC0415

        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        # miss detection numbers the samples: without it the cache needs zenoh's timestamping
        # (off by default; zenoh refuses the publisher then)
        miss = ext.MissDetectionConfig(
            heartbeat=None, sporadic_heartbeat=float(heartbeat_s) if heartbeat_s else None)
        pub = ext.declare_advanced_publisher(
            self.session, key, encoding=zenoh.Encoding(encoding), congestion_control=cc,
            cache=ext.CacheConfig(max_samples=int(depth)), publisher_detection=True,
            sample_miss_detection=miss)
        return LatchedPublisher(self, self._keep(pub), key)

    def drop_latest(self, key: str) -> bool:
        """Undeclare the :class:`LatchedPublisher` of ``put(key, ..., latest=True)``: late
        joiners no longer get its last sample (a camera forgotten). True when there was one."""
        with self._lock:
            pub = self._latched.pop(key, None)
        if pub is None:
            return False
        pub.undeclare()
        return True

    def wait_route(self, key: str, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until this session knows a queryable matching ``key``
        (a querier's matching status); True when it does.

        A session that has just opened learns the queryables of the network as their
        declarations reach it: a peer behind a router that queries at once can get "no
        reply" from a service that was there all along. Queried after this, it is answered.
        """
        deadline = time.monotonic() + max(0.0, timeout_s)
        try:
            querier = self.session.declare_querier(key, target=zenoh.QueryTarget.ALL)
        except Exception as exc:  # noqa: BLE001 - no matching status here: query anyway
            log.debug("no querier for %s: %s", key, exc)
            return False
        try:
            while True:
                status = querier.matching_status
                if bool(getattr(status, "matching", status)):
                    return True
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.02)
        finally:
            with contextlib.suppress(Exception):
                querier.undeclare()

    def get(self, selector: str, *, timeout_s: float = 5.0, all_replies: bool = True,
            wait_route: bool = False) -> list[Reply]:
        """Query ``selector`` (``key?params``); every reply until all queryables finished.

        ``all_replies`` sends the query to every matching queryable (not only the "best
        matching" complete one a router would pick) and turns reply consolidation off, so
        several instances answering on the same key are all seen. ``wait_route``: first
        wait (within ``timeout_s``) until a matching queryable is known (:meth:`wait_route`),
        as a client that has just connected must; a key nobody serves then costs the whole
        timeout instead of returning at once.
        """
        if wait_route:
            t0 = time.monotonic()
            self.wait_route(selector.partition("?")[0], timeout_s)
            timeout_s = max(0.5, timeout_s - (time.monotonic() - t0))
        # Queries travel at a higher priority than the data: each priority has its own queue
        # (and lock) on every zenoh link, so a query to a service whose link is full of
        # events (`--on-full block`, serve --workers) does not wait behind them; the replies
        # take the query's priority.
        kwargs: dict[str, Any] = {"timeout": float(timeout_s),
                                  "priority": zenoh.Priority.INTERACTIVE_HIGH}
        if all_replies:
            kwargs["consolidation"] = zenoh.ConsolidationMode.NONE
            kwargs["target"] = zenoh.QueryTarget.ALL
        out = []
        for r in self.session.get(selector, **kwargs):
            if r.ok is not None:
                s = r.ok
                att = s.attachment.to_bytes() if s.attachment is not None else None
                out.append(Reply(True, str(s.key_expr), s.payload.to_bytes(), str(s.encoding),
                                 att))
            else:
                e = r.err
                out.append(Reply(False, "", e.payload.to_bytes(), str(e.encoding)))
        return out

    def flush(self, via_key: str | None = None, *, timeout_s: float = 5.0,
              linger_s: float = 0.5) -> bool:
        """Wait until what was put so far has left this session; call before closing it.

        Closing a session drops messages still queued for sending (seen: the last ~5 % of a
        burst of puts). A query travels behind the data on the same link, so a reply from the
        receiver's queryable on ``via_key`` means the data arrived; without one, wait
        ``linger_s``. Returns True when a reply confirmed it.
        """
        if via_key is not None and any(r.ok for r in self.get(via_key, timeout_s=timeout_s)):
            return True
        time.sleep(linger_s)
        return False

    def token(self, key: str) -> Declared:
        """Declare a liveliness token (gone when undeclared, the session closes or the
        process dies)."""
        return Declared(self, self._keep(self.session.liveliness().declare_token(key)))

    def alive(self, key: str, *, timeout_s: float = 2.0) -> list[str]:
        """Keys of the liveliness tokens matching ``key``."""
        return [str(r.ok.key_expr) for r in
                self.session.liveliness().get(key, timeout=float(timeout_s)) if r.ok is not None]

    def watch_alive(self, key: str, callback: Callable[[str, bool], None]) -> None:
        """``callback(token_key, alive)`` when a matching token appears or disappears."""

        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
            except Exception:
                log.exception("liveliness callback on %s failed", key)

        self._keep(self.session.liveliness().declare_subscriber(
            key, zenoh.handlers.Callback(on_sample, indirect=False), history=True))


# where zenoh listens when nothing says (its default configuration, per mode)
DEFAULT_LISTEN = {"router": ("tcp/[::]:7447",), "peer": ("tcp/[::]:0",), "client": ()}


def as_router(options: ZenohOptions, local_endpoint: str) -> ZenohOptions:
    """Options for a router that stands where a session opened with ``options`` would have
    stood (``evcal serve --workers N``: the supervisor routes for its workers).

    It listens where that session would have listened -- the endpoints of ``--listen``,
    ``--cfg`` or the configuration file, else zenoh's default for the session's mode (a peer
    on a free TCP port, found by scouting; a router on 7447; a client nowhere) -- and also on
    ``local_endpoint`` (the workers'); it connects where that session would have connected.
    Everything else (TLS, scouting, shared memory, ...) is the user's.
    """
    conf = options.to_config()
    try:
        mode = json.loads(conf.get_json("mode")) or "peer"
        endpoints = {section: json.loads(conf.get_json(f"{section}/endpoints"))
                     for section in ("listen", "connect")}
    except Exception as exc:
        raise TransportError(f"cannot read the zenoh configuration: {exc}") from None

    def of_mode(value: Any, default: tuple[str, ...]) -> tuple[str, ...]:
        if isinstance(value, dict):  # {"router": [...], "peer": [...]}
            value = value.get(mode)
        return tuple(value) if value is not None else default

    listen = of_mode(endpoints["listen"], DEFAULT_LISTEN.get(mode, ()))
    connect = of_mode(endpoints["connect"], ())
    own = {"mode", "listen/endpoints", "connect/endpoints"}
    return ZenohOptions(
        mode="router", listen=(*listen, local_endpoint), connect=connect,
        config_file=options.config_file, multicast_scouting=options.multicast_scouting,
        extra=tuple((k, v) for k, v in options.extra if k.strip("/") not in own))


def router_session(listen: Iterable[str]) -> Transport:
    """A Python session in router mode (tests of routed set-ups; no zenohd here)."""
    return Transport(ZenohOptions(mode="router", listen=tuple(listen), multicast_scouting=False))
