"""Thin Zenoh helpers shared by the ForceGrasp services.

Topology: every service opens a *peer* session without multicast scouting.  The learner listens on
a known endpoint; the others connect to it and also listen on an ephemeral port, so Zenoh's gossip
can connect them to each other (peers do not forward traffic between other peers: only direct
links carry data).  A peer whose connect target is down keeps retrying in the background and
reconnects by itself when the target returns; a failed connect is silent, hence
:func:`wait_for_peers`.

Zenoh runs subscriber, queryable and liveliness callbacks on its own receive path: the helpers here
only copy bytes into a queue or read a cached value there; decoding and training happen in the
caller's threads.

Always close sessions (``with open_session(...)`` or :func:`close_session`): a session that still
has Python callbacks keeps a non-daemon thread that would otherwise block interpreter exit.
:func:`open_session` registers a last-resort close at shutdown for the sessions a caller forgot.
"""

from __future__ import annotations

import json
import logging
import queue
import socket
import threading
import time
from typing import Any, Callable, Iterable, Mapping

import zenoh

log = logging.getLogger(__name__)

# Strong references (Zenoh sessions cannot be weakly referenced); closed ones are pruned on open.
_OPEN_SESSIONS: list[zenoh.Session] = []
_shutdown_hook_installed = False
_hook_lock = threading.Lock()


# --------------------------------------------------------------------------------------------
# Configuration and sessions
# --------------------------------------------------------------------------------------------

def make_config(listen: Iterable[str] = (), connect: Iterable[str] = (), *, mode: str = "peer",
                lease_ms: int | None = None, shared_memory: bool | None = None,
                config_file: str | None = None, extra: Mapping[str, Any] | None = None) -> zenoh.Config:
    """A Zenoh config with explicit endpoints and no multicast scouting.

    ``lease_ms`` bounds how long a hung (not killed) peer looks alive (Zenoh default 10 s).
    ``config_file`` (JSON5) is a base for settings this function does not cover (TLS, ACLs);
    ``extra`` maps config paths to JSON-able values applied last.
    """
    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    settings: dict[str, Any] = {
        "mode": mode,
        "scouting/multicast/enabled": False,
        "listen/endpoints": list(listen),
        "connect/endpoints": list(connect),
    }
    if lease_ms is not None:
        settings["transport/link/tx/lease"] = int(lease_ms)
    if shared_memory is not None:
        settings["transport/shared_memory/enabled"] = bool(shared_memory)
    settings.update(extra or {})
    for path, value in settings.items():
        config.insert_json5(path, json.dumps(value))
    return config


def open_session(listen: Iterable[str] = (), connect: Iterable[str] = (), **config_kwargs: Any) -> zenoh.Session:
    """Open a session (see :func:`make_config` for the arguments); usable as a context manager."""
    zenoh.try_init_log_from_env()
    session = zenoh.open(make_config(listen, connect, **config_kwargs))
    with _hook_lock:
        _OPEN_SESSIONS[:] = [s for s in _OPEN_SESSIONS if not s.is_closed()] + [session]
    _install_shutdown_hook()
    return session


def close_session(session: zenoh.Session | None) -> None:
    """Close without raising: used in ``finally`` blocks and at shutdown."""
    if session is None:
        return
    try:
        if not session.is_closed():
            session.close()
    except Exception as exc:  # closing is best effort; a failure must not mask the real error
        log.debug("closing zenoh session failed: %s", exc)


def _install_shutdown_hook() -> None:
    """Close forgotten sessions before Python joins its threads at exit.

    ``threading._register_atexit`` runs before the join of non-daemon threads, which is where a
    session with callbacks would otherwise hang; ``atexit`` would be too late.
    """
    global _shutdown_hook_installed
    with _hook_lock:
        if _shutdown_hook_installed:
            return
        register = getattr(threading, "_register_atexit", None)
        if register is not None:
            register(lambda: [close_session(s) for s in list(_OPEN_SESSIONS)])
        _shutdown_hook_installed = True


def connected_count(session: zenoh.Session) -> int:
    """Number of peers and routers this session has a live link to."""
    info = session.info
    return len(info.peers_zid()) + len(info.routers_zid())


def wait_for_peers(session: zenoh.Session, count: int = 1, timeout: float = 10.0, poll_s: float = 0.02) -> bool:
    """Poll until ``count`` peers/routers are linked; False on timeout (peer connects fail silently)."""
    deadline = time.monotonic() + timeout
    while True:
        if connected_count(session) >= count:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)


# --------------------------------------------------------------------------------------------
# Publishing and subscribing
# --------------------------------------------------------------------------------------------

def declare_publisher(session: zenoh.Session, key: str, *, express: bool = False,
                      priority: zenoh.Priority | None = None) -> zenoh.Publisher:
    """Reliable publisher that blocks (instead of dropping) when the link is congested.

    Transitions must not be lost silently: blocking slows the producer, which is the right
    back-pressure when the learner cannot keep up.
    """
    return session.declare_publisher(
        key, reliability=zenoh.Reliability.RELIABLE, congestion_control=zenoh.CongestionControl.BLOCK,
        express=express, priority=priority,
    )


def has_subscribers(publisher: zenoh.Publisher) -> bool:
    """Whether any subscriber matches: an actor keeps batches buffered while this is False."""
    status = publisher.matching_status
    return bool(getattr(status, "matching", status))


def wait_for_subscribers(publisher: zenoh.Publisher, timeout: float = 10.0, poll_s: float = 0.01) -> bool:
    """Poll until a subscriber matches ``publisher`` (declarations need a moment to propagate)."""
    deadline = time.monotonic() + timeout
    while not has_subscribers(publisher):
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)
    return True


class QueueSubscriber:
    """Subscriber whose callback only copies the payload into a bounded ``queue.Queue``.

    Items are ``bytes`` (or ``(key, bytes)`` with ``with_key=True``, so a receiver can check the
    sender's key against the payload).  When the queue is full the callback waits up to
    ``put_timeout`` seconds (``None``: forever, which back-pressures the sender through Zenoh's
    reliable channel) and then drops the message and counts it in :attr:`dropped`.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, *, maxsize: int = 1024,
                 put_timeout: float | None = 1.0, with_key: bool = False,
                 out: queue.Queue | None = None) -> None:
        self.queue: queue.Queue = out if out is not None else queue.Queue(maxsize=maxsize)
        self.key_expr = key_expr
        self.dropped = 0
        self.received = 0
        self._put_timeout = put_timeout
        self._with_key = with_key
        self._subscriber = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        item = (str(sample.key_expr), payload) if self._with_key else payload
        self.received += 1
        try:
            self.queue.put(item, timeout=self._put_timeout)
        except queue.Full:
            self.dropped += 1

    def get(self, timeout: float | None = None) -> Any:
        """Next item, or ``None`` after ``timeout`` seconds."""
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        try:
            self._subscriber.undeclare()
        except Exception as exc:  # session may already be closed
            log.debug("undeclare failed: %s", exc)

    def __enter__(self) -> "QueueSubscriber":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def subscribe_latest(session: zenoh.Session, key_expr: str) -> zenoh.Subscriber:
    """Subscriber keeping only the newest sample (``RingChannel(1)``): right for weights.

    A consumer that polls between env steps never processes outdated weights, and a slow
    consumer never stalls Zenoh.  Read it with :func:`take_latest` / :func:`wait_latest`.
    """
    return session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(1))


def take_latest(subscriber: zenoh.Subscriber) -> bytes | None:
    """The newest payload since the last call, or ``None`` (never blocks)."""
    sample = subscriber.try_recv()
    return None if sample is None else sample.payload.to_bytes()


def wait_latest(subscriber: zenoh.Subscriber, timeout: float, poll_s: float = 0.005) -> bytes | None:
    """Like :func:`take_latest` but waits up to ``timeout`` seconds (Zenoh's ``recv`` cannot time out)."""
    deadline = time.monotonic() + timeout
    while True:
        payload = take_latest(subscriber)
        if payload is not None or time.monotonic() >= deadline:
            return payload
        time.sleep(poll_s)


# --------------------------------------------------------------------------------------------
# Query / reply
# --------------------------------------------------------------------------------------------

def declare_queryable(session: zenoh.Session, key: str, reply: Callable[[], bytes | None]) -> zenoh.Queryable:
    """Answer every query on ``key`` with ``reply()`` (no answer when it returns ``None``).

    ``reply`` runs on Zenoh's receive path: return cached bytes (e.g. the last encoded weights),
    do not compute there.
    """

    def on_query(query: zenoh.Query) -> None:
        try:
            payload = reply()
        except Exception:  # a bug in reply() must not kill Zenoh's thread; the querier times out
            log.exception("queryable %s: reply() failed", key)
            return
        if payload is not None:
            query.reply(key, payload)

    return session.declare_queryable(key, on_query)


def query_bytes(session: zenoh.Session, selector: str, timeout: float = 2.0) -> bytes | None:
    """Payload of the first successful reply, or ``None`` if nobody answered within ``timeout``."""
    try:
        replies = session.get(selector, timeout=timeout)
        for reply in replies:
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
    except zenoh.ZError as exc:
        log.debug("query %s failed: %s", selector, exc)
    return None


# --------------------------------------------------------------------------------------------
# Liveliness
# --------------------------------------------------------------------------------------------

def declare_token(session: zenoh.Session, key: str) -> zenoh.LivelinessToken:
    """Announce this service as alive; the token vanishes when the session closes or dies."""
    return session.liveliness().declare_token(key)


def watch_liveliness(session: zenoh.Session, key_expr: str, on_change: Callable[[str, bool], None],
                     *, history: bool = True) -> zenoh.Subscriber:
    """Call ``on_change(key, alive)`` for each token appearing (True) or vanishing (False).

    With ``history=True`` tokens already alive are reported at once.  A SIGKILLed peer is seen
    within milliseconds (its TCP link drops); a hung one only after the lease.  A callback (not a
    ring buffer) is used on purpose: a dropped "gone" event would leave a dead service looking
    alive.  ``on_change`` runs on Zenoh's path: keep it to a queue put or a set update.
    """

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
        except Exception:
            log.exception("liveliness callback for %s failed", key_expr)

    return session.liveliness().declare_subscriber(key_expr, on_sample, history=history)


# --------------------------------------------------------------------------------------------
# Endpoints
# --------------------------------------------------------------------------------------------

def tcp_endpoint(host: str, port: int) -> str:
    """Zenoh endpoint string, e.g. ``tcp/127.0.0.1:7447`` (IPv6 hosts are bracketed)."""
    return f"tcp/[{host}]:{port}" if ":" in host else f"tcp/{host}:{port}"


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A port that was free a moment ago (bind port 0); for tests, benches and local launches."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]
