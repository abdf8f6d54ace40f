"""The few zenoh helpers every process needs: configuration, opening, receiving, presence, and
the life cycle of a process with a session. Zenoh is the distributed engine; this module only
fixes our conventions: one router (per host) and clients, loopback by default, multicast
scouting off (nothing is discovered by accident) and no scouting delay (a session opens in
milliseconds instead of half a second).
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import re
import signal
import socket
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from contextlib import nullcontext
from typing import Any, Literal, NamedTuple, TypeVar

import zenoh
import zenoh.ext

from shared.access import Guard, Login
from shared.compiled_core import CompiledCoreError
from shared.process_status import ProcessStatus
from shared.topics import Topics, uav_in_key
from shared.wire import Message, MessageError, decode, encode

M = TypeVar("M", bound=Message)

# How long a client keeps trying to reach its router at start: the supervisor starts every
# process at once, and a restarted router takes a moment to listen again.
CONNECT_TIMEOUT_MS = 15_000
CONNECT_RETRY_MS = 100


class BusError(RuntimeError):
    """The bus cannot be reached; the text is one line."""


class QueryRefused(BusError):
    """The queryable answered, with an error: asking again would not help."""


def config(mode: Literal["router", "client"], endpoint: str,
           connect_timeout_ms: int = CONNECT_TIMEOUT_MS,
           routers: tuple[str, ...] = (), security: dict[str, Any] | None = None,
           base_file: str | None = None, listeners: tuple[str, ...] = ()) -> zenoh.Config:
    """A router listens on ``endpoint`` and the other ``listeners`` (and links to other
    ``routers``, one per host); a client connects to ``endpoint``. ``security``: the settings
    of ``shared.access`` (a client's login; a router's logins and access rules).
    ``base_file``: a zenoh configuration file to start from (the TLS certificates of a link
    between hosts); ours override it."""
    try:
        cfg = zenoh.Config() if base_file is None else zenoh.Config.from_file(base_file)
    except zenoh.ZError as exc:  # bad input, not an absent system
        raise ValueError(f"zenoh configuration {base_file}: {_one_line(exc)}") from None
    settings = {
        "mode": mode,
        "scouting/multicast/enabled": False,
        "scouting/delay": 0,
        # Zenoh maps a 16 MiB shared-memory pool into every process and touches it whole; the
        # system's messages are small (weights: tens of kB), and loopback TCP carries them.
        "transport/shared_memory/enabled": False,
    }
    if mode == "router":
        settings["listen/endpoints"] = [endpoint, *listeners]
        # A router stamps every sample it forwards with its own clock, and an advanced
        # subscriber passes a stamped sample on only if it is newer than the last one stamped
        # by that clock: of two events put at once by two processes, it silently dropped the
        # one whose link the router served second. Unstamped, they all pass.
        settings["timestamping/enabled"] = {"router": False}
        if routers:
            settings["connect/endpoints"] = list(routers)
    else:
        settings["connect/endpoints"] = [endpoint]
        settings["connect/timeout_ms"] = connect_timeout_ms
        settings["connect/retry"] = {"period_init_ms": CONNECT_RETRY_MS, "period_max_ms": 1000,
                                     "period_increase_factor": 2}
    for key, value in {**settings, **(security or {})}.items():
        cfg.insert_json5(key, json.dumps(value))
    return cfg


def _one_line(exc: zenoh.ZError) -> str:
    """Zenoh's message on one line, without the source location it ends with."""
    return re.sub(r" at /\S+$", "", " ".join(str(exc).split()))


def open_session(mode: Literal["router", "client"], endpoint: str,
                 connect_timeout_ms: int = CONNECT_TIMEOUT_MS,
                 routers: tuple[str, ...] = (), login: Login | None = None,
                 guard: Guard | None = None, base_file: str | None = None,
                 listeners: tuple[str, ...] = ()) -> zenoh.Session:
    """Open a session; close it (``with`` or ``close()``): a process with callback subscribers
    that exits without closing its session never exits. A client presents ``login``; a
    router with a ``guard`` accepts only its logins and enforces its access rules."""
    presented = {} if login is None else login.zenoh_settings()
    with nullcontext({}) if guard is None else guard.zenoh_settings() as enforced:
        cfg = config(mode, endpoint, connect_timeout_ms, routers, {**presented, **enforced},
                     base_file, listeners)
        try:
            return zenoh.open(cfg)
        except zenoh.ZError as exc:
            if mode == "router":
                raise BusError(f"cannot listen on {endpoint}: {_one_line(exc)}") from None
            raise BusError(_unreachable(endpoint, login, exc)) from None


def _unreachable(endpoint: str, login: Login | None, exc: zenoh.ZError) -> str:
    """Why a client session did not open. A router refuses a login the way an absent router
    does, by never answering; a port that takes a connection tells the two apart."""
    if not _listening(endpoint):
        return f"cannot reach a router at {endpoint}: {_one_line(exc)}"
    if login is not None:
        return (f"the router at {endpoint} refused the login of {login.user!r}: check "
                f"--credentials (the file `jamnav up --secure` wrote for this system)")
    return (f"the router at {endpoint} did not let this session in: a secure system needs "
            f"--credentials FILE (`jamnav up --secure` writes RUN_DIR/credentials.json)")


def _listening(endpoint: str) -> bool:
    """Whether something takes a TCP connection at ``endpoint`` (tcp/ and tls/ endpoints)."""
    found = re.match(r"^(?:tcp|tls)/\[?([^\]]+?)\]?:(\d+)$", endpoint)
    if found is None:
        return False
    try:
        with socket.create_connection((found.group(1), int(found.group(2))), timeout=0.5):
            return True
    except OSError:
        return False


def reliable_publisher(session: zenoh.Session, key: str, express: bool = False
                       ) -> zenoh.Publisher:
    """A publisher that blocks rather than drops under congestion: every step, action,
    upload and event must arrive. ``express`` skips batching, for the lockstep's round trip."""
    return session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK, express=express)


def publish_event(session: zenoh.Session, topics: Topics, event: Message) -> None:
    """Publish an event on its own key (``<prefix>/event/<type>``), never dropped."""
    session.put(topics.event(event.type), encode(event),
                congestion_control=zenoh.CongestionControl.BLOCK)


# A put while the router restarts reaches no one. Zenoh's advanced publisher numbers its
# samples, keeps the last ones and says every second how far it got, so that an advanced
# subscriber that missed some asks for them again.
RECOVERY_HEARTBEAT_S = 1.0


def recoverable_publisher(session: zenoh.Session, key: str, kept: int
                          ) -> zenoh.ext.AdvancedPublisher:
    """A publisher whose last ``kept`` samples a ``recovering_subscriber`` gets even if it
    missed them; never dropped under congestion."""
    return zenoh.ext.declare_advanced_publisher(
        session, key, congestion_control=zenoh.CongestionControl.BLOCK,
        cache=zenoh.ext.CacheConfig(kept), publisher_detection=True,
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=RECOVERY_HEARTBEAT_S))


def recovering_subscriber(session: zenoh.Session, key: str,
                          callback: Callable[[zenoh.Sample], None]
                          ) -> zenoh.ext.AdvancedSubscriber:
    """A subscriber that fetches what it missed of a ``recoverable_publisher``, once each,
    and takes other publishers' samples as they come."""
    return zenoh.ext.declare_advanced_subscriber(
        session, key, callback, history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
        recovery=zenoh.ext.RecoveryConfig(heartbeat=True))


# A put sent right when the match becomes known can still be lost (1 of 6 tries); a moment
# later it never was.
MATCH_SETTLE_S = 0.05


def wait_matching(publishers: Sequence[zenoh.Publisher], timeout: float) -> list[bool]:
    """Wait until someone subscribes to each of ``publishers``' keys, and a moment more, once
    for all of them: a put sent before the subscription has reached us may be lost. Which
    ones matched within ``timeout``."""
    deadline = time.monotonic() + timeout
    unmatched = set(range(len(publishers)))
    while unmatched := {i for i in unmatched if not publishers[i].matching_status.matching}:
        if time.monotonic() >= deadline:
            break
        time.sleep(0.002)
    if len(unmatched) < len(publishers):
        time.sleep(MATCH_SETTLE_S)
    return [i not in unmatched for i in range(len(publishers))]


def declare_alive(session: zenoh.Session, topics: Topics, role: str, ident: int | str
                  ) -> zenoh.LivelinessToken:
    """Presence of a process; keep the returned token referenced for as long as it lives."""
    return session.liveliness().declare_token(topics.alive(role, ident))


# -- receiving ----------------------------------------------------------------------------------
class Dropped:
    """Invalid messages refused, per topic (key expression of the subscription)."""

    def __init__(self, log: logging.Logger):
        self._counts: Counter = Counter()
        self._lock = threading.Lock()
        self._log = log

    def add(self, topic: str, reason: str) -> bool:
        """Count a refusal; True when it is worth telling (logged: the first few, then one in
        a thousand, so that a flood does not flood the log)."""
        with self._lock:
            self._counts[topic] += 1
            count = self._counts[topic]
        tell = count <= 3 or count % 1000 == 0
        if tell:
            self._log.warning("refused message #%d on %s: %s", count, topic, reason)
        return tell

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


def receive(kind: type[M], key, payload: zenoh.ZBytes | None) -> M:
    """The ``kind`` message that arrived on ``key`` (a put or a query), validated; a message
    about a UAV must come on that UAV's key (``.../uav/<id>/...``): with access control, the
    key is what says who sent it. MessageError otherwise."""
    if payload is None:
        raise MessageError(f"{kind.__name__}: no payload")
    message = decode(kind, payload.to_bytes())
    uav = getattr(message, "uav", None)
    if uav is not None and uav_in_key(key) not in (None, str(uav)):
        raise MessageError(f"a message about uav {uav} on {key}")
    return message


def subscribe(session: zenoh.Session, key: str, kind: type[M], on_message: Callable[[M], None],
              dropped: Dropped, on_refused: Callable[[str], None] | None = None
              ) -> zenoh.Subscriber:
    """Subscribe to ``key`` and hand each valid ``kind`` message to ``on_message``, which runs
    on zenoh's delivery thread and must return at once (store it or queue it). Messages are
    checked by ``receive``; refusals are counted, and ``on_refused`` hears those worth
    telling."""

    def callback(sample: zenoh.Sample) -> None:
        try:
            message = receive(kind, sample.key_expr, sample.payload)
        except MessageError as exc:
            if dropped.add(key, str(exc)) and on_refused is not None:
                on_refused(str(exc))
            return
        on_message(message)

    return session.declare_subscriber(key, callback)


# Error replies of our queryables start with this; zenoh's own (a "Timeout" from the router
# or from this session) do not, and mean that the question may be asked again.
REFUSAL = b"jamnav refused: "


def refuse(query: zenoh.Query, reason: str) -> None:
    """Answer ``query`` with an error that asking again will not change."""
    query.reply_err(REFUSAL + reason.encode())


def query(session: zenoh.Session, key: str, kind: type[M],
          payload: Message | bytes | None = None, timeout: float = 2.0) -> M:
    """The first valid reply of a query with ``payload`` (a message, or one encoded already);
    QueryRefused if the only answers were errors, BusError (one line) if none came."""
    if isinstance(payload, Message):
        payload = encode(payload)
    replies = session.get(key, payload=payload, timeout=timeout)
    problem, refused = "no reply (is the system running?)", False
    for reply in replies:
        if reply.ok is None:
            text = reply.err.payload.to_bytes()
            if not text.startswith(REFUSAL):  # zenoh's own errors, such as "Timeout"
                problem = f"no answer ({text[:100].decode(errors='replace')})"
                continue
            problem = f"refused: {text[len(REFUSAL):].decode(errors='replace')}"
            refused = True
            continue
        try:
            return decode(kind, reply.ok.payload.to_bytes())
        except MessageError as exc:
            problem = f"invalid reply: {exc}"
    raise (QueryRefused if refused else BusError)(f"{key}: {problem}")


def serve_status(session: zenoh.Session, topics: Topics, role: str, ident: int | str,
                 snapshot: Callable[[], ProcessStatus]) -> zenoh.Queryable:
    """Answer status queries with ``snapshot()`` (must be quick: it runs on zenoh's thread)."""
    key = topics.status(role, ident)

    def reply(q: zenoh.Query) -> None:
        q.reply(key, encode(snapshot()))

    return session.declare_queryable(key, reply)


# -- process lifecycle --------------------------------------------------------------------------
def setup_logging(name: str) -> logging.Logger:
    logging.basicConfig(stream=sys.stderr, level=logging.INFO,
                        format=f"%(asctime)s {name} %(levelname)s %(message)s")
    return logging.getLogger(name)


def stop_on_signals(stop: threading.Event) -> None:
    """SIGTERM and SIGINT ask the process to stop; the main loop sees ``stop`` and closes its
    session on the way out. If the parent goes away (a supervisor killed with SIGKILL), stop
    too, so that no child outlives it."""
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    parent = os.getppid()

    def watch_parent() -> None:
        while not stop.wait(0.5):
            if os.getppid() != parent:
                stop.set()

    if parent > 1:
        threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()


def say_connecting(log: logging.Logger, endpoint: str) -> None:
    """Say at once what a process's connect may wait for: the long wait is for processes
    restarted while their router restarts too, and a console or recorder started by hand
    against no system would otherwise wait it out in silence."""
    log.info("connecting to the router at %s (giving up after %g s)", endpoint,
             CONNECT_TIMEOUT_MS / 1000)


def service_session(role: str, endpoint: str, login: Login | None = None
                    ) -> tuple[zenoh.Session | None, threading.Event]:
    """What every process shell starts with: a stop event wired to signals and a client
    session to the router (logged in with ``login`` on a secure system). When the router
    cannot be reached, one line on stderr and no session (the caller exits 1)."""
    stop = threading.Event()
    stop_on_signals(stop)
    say_connecting(logging.getLogger(role), endpoint)
    try:
        return open_session("client", endpoint, login=login), stop
    except BusError as exc:
        print(f"{role}: error: {exc}", file=sys.stderr)
        return None, stop


class ServiceSetup(NamedTuple):
    """What a process of the system runs once its arguments are checked."""

    endpoint: str
    login: Login | None
    # Runs the process on its session until ``stop`` is set, logging to the logger given, and
    # gives its exit code.
    run: Callable[[zenoh.Session, threading.Event, logging.Logger], int]
    log_name: str | None = None  # how the log names the process, where not by its role


def run_service(role: str, parser: argparse.ArgumentParser,
                setup: Callable[[argparse.Namespace], ServiceSetup], argv: list[str] | None
                ) -> int:
    """The shell of the world, the cloud and an agent: ``parser`` reads the command line
    ``argv``; ``setup`` checks what it says, and a mistake in it (a ValueError, a BusError or
    a compiled core that cannot run) ends in one line and exit 2; then logging on stderr and a
    session to the router that SIGTERM, SIGINT or the parent's end stop, or exit 1 where the
    router cannot be reached; then the process runs, and its exit code is the shell's."""
    args = parser.parse_args(argv)
    try:
        service = setup(args)
    except (ValueError, BusError, CompiledCoreError) as exc:
        return bad_arguments(role, exc)
    log = setup_logging(service.log_name or role)
    session, stop = service_session(role, service.endpoint, service.login)
    if session is None:
        return 1
    # What start-up made (modules, scenario, parsers) lives as long as the process: kept from
    # the collector, a full collection scans only what flying makes, where the first one cost
    # each of a fleet's agents 20-30 ms at about the same early step.
    gc.collect()
    gc.freeze()
    with session:
        return service.run(session, stop, log)


def bad_arguments(role: str, error: Exception) -> int:
    """One line on stderr for a mistake in what ``role`` was asked to run: exit 2."""
    print(f"{role}: error: {error}", file=sys.stderr)
    return 2
