"""The ``jamnav`` commands that work with a running system: ``console``, ``record``,
``replay``, ``jammer {set,add,move,remove,off,show}`` and ``status``; and ``router``, a
router of one (what
``jamnav up`` starts, and what links the hosts of a system spread over several).

Every command finds the running system through its router: ``--endpoint``, else
$JAMNAV_ENDPOINT, else tcp/127.0.0.1:7447 (where ``jamnav up`` puts it). A mistake in the
arguments, or a jammer command the world refuses, ends with one line on stderr and exit 2; a
system that cannot be reached, with exit 1.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import threading
from pathlib import Path

from jamnav.arguments import (
    UsageError,
    check_range,
    jammer_command,
    new_recording,
    scenario_argument,
)
from shared.process_status import mapper_summary
from shared.scenario import MAX_JAMMERS, ScenarioError
from shared.topics import (
    DEFAULT_ENDPOINT,
    ENDPOINT_ENV,
    Topics,
    add_bus_arguments,
    endpoint_from,
)

AGENT_LINES = 8  # ``jamnav status`` sums up more agents than this in one line
_ROUTER_ID = re.compile(r"^[A-Za-z0-9_-]+$")


def _fail(message: str, code: int) -> int:
    print(f"jamnav: error: {message}", file=sys.stderr)
    return code


def guarded(handler):
    """One-line errors instead of tracebacks: exit 2 for bad input, 1 for an absent system."""

    def run(args: argparse.Namespace) -> int:
        from shared import bus

        try:
            return handler(args)
        except (UsageError, ScenarioError, ValueError) as exc:
            return _fail(str(exc), 2)
        except bus.BusError as exc:
            return _fail(str(exc), 1)

    return run


# -- jammer -------------------------------------------------------------------------------------
def cmd_jammer(args: argparse.Namespace) -> int:
    from shared import access, bus
    from shared.jammer_messages import JammerReply, jammer_numbers

    action, place = args.jammer_command, getattr(args, "jammer", None)
    numbers = None if place is None else jammer_numbers(place, placed_only=action == "move")
    command = jammer_command(action, numbers, place or "", getattr(args, "id", None))
    topics = Topics(args.prefix)
    login = access.login_for(args.credentials, access.OPERATOR)
    with bus.open_session("client", endpoint_from(args.endpoint), 2000, login=login) as session:
        reply = bus.query(session, topics.jammer_control, JammerReply, command)
    print(json.dumps(reply.model_dump(mode="json")))
    if not reply.accepted:
        raise UsageError(f"jammer {args.jammer_command} refused: {reply.reason}")
    return 0


# -- status -------------------------------------------------------------------------------------
def _describe(status) -> str:
    d = status.details
    if status.role == "world":
        return (f"episode {status.episode} step {status.step}, {d.get('clock')}, "
                f"{d.get('steps_per_second', 0):.0f} steps/s, {d.get('live_agents')} agents, "
                f"jammer {d.get('jammer')}, missed deadlines {d.get('missed_deadlines')}"
                + (", finished" if d.get("finished") else ""))
    if status.role == "cloud":
        accuracy = d.get("map_accuracy")
        text = (f"map {d.get('map')} v{status.sinr_version}"
                + (f" (held-out accuracy {accuracy:.1%})" if isinstance(accuracy, float) else "")
                + f", value net v{status.value_version}, {d.get('stored')} measurements stored")
        if "map_phase" in d:
            text += f"; mapper: {mapper_summary(status)}"
            if d.get("estimate"):
                text += f"; jammer estimate {d['estimate']}"
        return text
    if status.role == "agent":
        return (f"value net v{status.value_version}, map v{status.sinr_version}, "
                f"{d.get('decisions')} decisions (p99 {d.get('decision_p99_us', 0):.0f} us), "
                f"episode {status.episode} step {status.step}")
    return ""


STATUS_ROLES = ("world", "cloud", "agent")  # the processes that answer a status query


def cmd_status(args: argparse.Namespace) -> int:
    from shared import access, bus
    from shared.process_status import ProcessStatus
    from shared.wire import MessageError, decode

    topics = Topics(args.prefix)
    endpoint = endpoint_from(args.endpoint)
    login = access.login_for(args.credentials, access.OPERATOR)
    with bus.open_session("client", endpoint, 2000, login=login) as session:
        live = sorted(topics.role_and_id(str(r.ok.key_expr))
                      for r in session.liveliness().get(topics.alive(), timeout=2.0)
                      if r.ok is not None)
        statuses = {}
        for reply in session.get(topics.status(), timeout=2.0):
            if reply.ok is not None:
                try:
                    status = decode(ProcessStatus, reply.ok.payload.to_bytes())
                except MessageError:
                    continue
                statuses[(status.role, status.ident)] = status
    if not live:
        raise bus.BusError(f"no live process of {topics.prefix!r} at {endpoint}")
    # A process whose token is live but that does not answer is frozen or swamped: said, as
    # it would otherwise read as healthy.
    silent = {(role, ident) for role, ident in live
              if role in STATUS_ROLES and (role, ident) not in statuses}
    if args.json:
        print(json.dumps([{"role": role, "id": ident, **(
            statuses[(role, ident)].model_dump(mode="json", exclude={"role", "ident"})
            if (role, ident) in statuses else {}),
            **({"answering": (role, ident) not in silent} if role in STATUS_ROLES else {})}
            for role, ident in live]))
        return 0
    order = {"router": 0, "world": 1, "cloud": 2, "agent": 3}
    live = sorted(live, key=lambda k: (order.get(k[0], 9), k[0], int(k[1])
                                       if k[1].isdigit() else 0))
    agents = [ident for role, ident in live if role == "agent"]
    for role, ident in live:
        if role == "agent" and len(agents) > AGENT_LINES:
            continue
        status = statuses.get((role, ident))
        pid = status.pid if status else ""
        about = (_describe(status) if status else "not answering its status query (frozen "
                 "or swamped)" if (role, ident) in silent else "")
        print(f"{role + '-' + ident:<12} {pid!s:>7}  live  {about}".rstrip())
    if len(agents) > AGENT_LINES:
        print(_describe_agents(agents, statuses))
    return 0


def _versions(numbers: list[int | None]) -> str:
    known = sorted({n for n in numbers if n is not None})
    if not known:
        return "?"
    return f"v{known[0]}" if len(known) == 1 else f"v{known[0]}..v{known[-1]}"


def _describe_agents(agents: list[str], statuses: dict) -> str:
    """One line for many agents: what they fly on, their total work, and the worst of them
    (``--json`` has every one)."""
    answered = [statuses[("agent", ident)] for ident in agents if ("agent", ident) in statuses]
    text = f"{'agents':<12} {len(agents):>7}  live"
    if len(answered) < len(agents):
        text += f" ({len(agents) - len(answered)} not answering)"
    if not answered:
        return text
    worst = max(answered, key=lambda s: s.details.get("decision_p99_us") or 0)
    behind = min(answered, key=lambda s: (s.episode or 0, s.step or 0))
    return (f"{text}  value net {_versions([s.value_version for s in answered])}, map "
            f"{_versions([s.sinr_version for s in answered])}, "
            f"{sum(int(s.details.get('decisions') or 0) for s in answered)} decisions, "
            f"decision p99 worst {worst.details.get('decision_p99_us') or 0:.0f} us "
            f"(agent-{worst.ident}), furthest behind agent-{behind.ident} at episode "
            f"{behind.episode} step {behind.step}")


# -- record and replay --------------------------------------------------------------------------
SPEED_RANGE = (0.01, 1000)  # of a replay: beyond it, hours of silence or no pace at all


def cmd_record(args: argparse.Namespace) -> int:
    from jamnav.recording import RECORDER_NICENESS, record
    from shared import access, bus

    check_range("--duration", args.duration, 0, above=True)
    out = new_recording("--out", args.out)
    topics = Topics(args.prefix)
    endpoint = endpoint_from(args.endpoint)
    login = access.login_for(args.credentials, access.RECORDER)
    log = bus.setup_logging("recorder")
    stop = threading.Event()
    bus.stop_on_signals(stop)
    bus.say_connecting(log, endpoint)
    with bus.open_session("client", endpoint, login=login) as session:
        # Linux sets it per thread: this one, which writes, yields; zenoh's, which receive
        # and only queue, keep up.
        os.nice(RECORDER_NICENESS)
        summary = record(session, topics, out, stop, args.duration, log)
    refused = sum(summary.refused.values())
    print(f"recorded {summary.messages} messages on {summary.keys} keys to {summary.path} "
          f"({summary.cpu_s:.2f} s CPU" + (f", {refused} refused: {summary.refused})"
                                          if refused else ")"), file=sys.stderr)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from jamnav.recording import Recording, replay
    from shared import bus

    check_range("--speed", args.speed, *SPEED_RANGE)
    if args.prefix is not None:
        Topics(args.prefix)
    endpoint = endpoint_from(args.endpoint)
    with Recording(args.file) as recording:
        stop = threading.Event()
        bus.stop_on_signals(stop)
        with bus.open_session("client", endpoint) as session:
            count = replay(session, recording, args.prefix, args.speed, stop)
        root = args.prefix or recording.prefix
    print(f"replayed {count} messages of {args.file} under {root}/ at {endpoint}",
          file=sys.stderr)
    return 0


# -- console ------------------------------------------------------------------------------------
def cmd_console(args: argparse.Namespace) -> int:
    from jamnav.console import listen
    from jamnav.console.server import serve
    from shared import access

    scenario = scenario_argument(args)
    topics = Topics(args.prefix)
    endpoint = endpoint_from(args.endpoint)
    login = access.login_for(args.credentials, access.OPERATOR)
    if login is None and args.token_file is not None:
        raise UsageError("--token-file: only a secure system's console (--credentials) "
                         "takes a token")
    token = None if login is None else listen.token_for(Path(
        args.token_file or Path(args.credentials).parent / listen.TOKEN_FILE))
    if args.listen_fd is None:
        listener, address = listen.open_listener(args.web)
    else:
        listener, address = listen.inherited_listener(args.listen_fd), listen.parse_web(args.web)
    return serve(listener, address, endpoint, topics, scenario, login, token)


# -- router -------------------------------------------------------------------------------------
def _router_guard(args: argparse.Namespace):
    """What a secure router enforces (the logins of ``--roles`` and their rules) and the login
    it presents to the routers it connects to. A router linked to others (``--connect``,
    ``--listen``) also accepts the routers' login, and relays for a router that presents a
    certificate of the system's authority (its zenoh configuration demands one)."""
    from shared import access

    if args.credentials is None:
        if args.roles is not None:
            raise UsageError("--roles says whose logins of --credentials the router accepts: "
                             "give both")
        return None, None
    linked = bool(args.connect or args.listen)
    credentials = access.load(args.credentials, (access.ROUTER,) if linked else ())
    if args.roles is not None:
        credentials = credentials.only(
            [*args.roles.split(","), *([access.ROUTER] if linked else [])])
    login = credentials.login(access.ROUTER) if args.connect else None
    return access.Guard(credentials, args.prefix, linked), login


def cmd_router(args: argparse.Namespace) -> int:
    from shared import bus

    endpoint = endpoint_from(args.endpoint)
    for other in args.connect + args.listen:
        endpoint_from(other)
    topics = Topics(args.prefix)
    if not _ROUTER_ID.match(args.id):
        raise UsageError(f"--id {args.id!r}: use letters, digits, _ and - (it is a key chunk)")
    guard, login = _router_guard(args)
    stop = threading.Event()
    bus.stop_on_signals(stop)
    with bus.open_session("router", endpoint, routers=tuple(args.connect), login=login,
                          guard=guard, base_file=args.zenoh_config,
                          listeners=tuple(args.listen)) as session:
        token = bus.declare_alive(session, topics, "router", args.id)
        print(f"jamnav router listening on {', '.join([endpoint, *args.listen])}",
              file=sys.stderr, flush=True)
        stop.wait()
        token.undeclare()
    return 0


# -- parsers ------------------------------------------------------------------------------------
def add_console_command(commands) -> None:
    console = commands.add_parser("console", help="the operator's console in a browser, "
                                                  "against a running system")
    add_bus_arguments(console)
    console.add_argument("--scenario", default=None, metavar="NAME|PATH",
                         help="the running system's scenario, for the true map (default: "
                              "icc2021)")
    console.add_argument("--web", default=None, metavar="HOST:PORT",
                         help="where to serve the page (default 127.0.0.1:8470, or a free "
                              "port if that one is taken)")
    console.add_argument("--token-file", default=None, metavar="FILE",
                         help="with --credentials: the token the page and the API demand, "
                              "made there if absent (default: console_token beside the "
                              "credentials file)")
    # `jamnav up` hands its console the socket it listens on (listen.inherited_listener).
    console.add_argument("--listen-fd", type=int, default=None, help=argparse.SUPPRESS)
    console.set_defaults(handler=guarded(cmd_console))


def add_record_command(commands) -> None:
    record = commands.add_parser("record", help="record a running system's messages to MCAP")
    add_bus_arguments(record)
    record.add_argument("--out", required=True, metavar="FILE.mcap")
    record.add_argument("--duration", type=float, default=None, metavar="SEC",
                        help="stop after SEC seconds (default: on Ctrl-C)")
    record.set_defaults(handler=guarded(cmd_record))


def add_replay_command(commands) -> None:
    replay = commands.add_parser("replay", help="publish a recording again on a router")
    replay.add_argument("file", metavar="FILE.mcap")
    replay.add_argument("--endpoint", default=None,
                        help=f"the router to publish on (default ${ENDPOINT_ENV} or "
                             f"{DEFAULT_ENDPOINT}; a replay starts none)")
    replay.add_argument("--prefix", default=None,
                        help="publish under this prefix (default: the recorded one)")
    replay.add_argument("--speed", type=float, default=1.0,
                        help=f"times the recorded pace, {SPEED_RANGE[0]:g} to "
                             f"{SPEED_RANGE[1]:g} (default 1)")
    replay.set_defaults(handler=guarded(cmd_replay))


def add_jammer_command(commands) -> None:
    jammer = commands.add_parser("jammer", help="place, move, remove or show the running jammers")
    jammer_commands = jammer.add_subparsers(dest="jammer_command", required=True)
    place_help = ("position (m), nominal power (W) and height (m, default: the scenario's), as "
                  "every command takes a jammer; e.g. -25,15,1")
    jam_set = jammer_commands.add_parser(
        "set", help="one jammer in place of all (applied between steps)")
    jam_set.add_argument("jammer", metavar="X,Y,P[,H]", help=place_help)
    jam_add = jammer_commands.add_parser(
        "add", help=f"one jammer more, up to {MAX_JAMMERS} (the reply gives its id)")
    jam_add.add_argument("jammer", metavar="X,Y,P[,H]", help=place_help)
    jam_move = jammer_commands.add_parser(
        "move", help="put jammer ID at X,Y, standing still (power and height kept unless given)")
    jam_move.add_argument("id", type=int, metavar="ID")
    jam_move.add_argument("jammer", metavar="X,Y[,P[,H]]", help=place_help)
    jam_remove = jammer_commands.add_parser("remove", help="switch jammer ID off for good")
    jam_remove.add_argument("id", type=int, metavar="ID")
    jam_off = jammer_commands.add_parser("off", help="switch every jammer off, or jammer ID")
    jam_off.add_argument("id", type=int, metavar="ID", nargs="?")
    jammer_commands.add_parser("show", help="the jammers in force")
    for sub in jammer_commands.choices.values():
        add_bus_arguments(sub)
        sub.set_defaults(handler=guarded(cmd_jammer))


def add_status_command(commands) -> None:
    status = commands.add_parser("status", help="live processes, weight versions, step")
    add_bus_arguments(status)
    status.add_argument("--json", action="store_true", help="print JSON")
    status.set_defaults(handler=guarded(cmd_status))


def add_router_command(commands) -> None:
    router = commands.add_parser("router", help="a zenoh router (what `jamnav up` starts)")
    add_bus_arguments(router)
    router.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="another host's router to link with (repeatable)")
    router.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="another endpoint to listen on, e.g. tls/0.0.0.0:7448 for the "
                             "routers of other hosts (repeatable)")
    router.add_argument("--id", default="0", help="name in `jamnav status`")
    router.add_argument("--roles", default=None, metavar="ROLE,...",
                        help="with --credentials: accept only these roles' logins (shell "
                             "patterns, e.g. 'agent-*'; default: every role of the file)")
    router.add_argument("--zenoh-config", default=None, metavar="FILE",
                        help="zenoh configuration to start from, e.g. TLS certificates for "
                             "links between hosts (docs/security.md)")
    router.set_defaults(handler=guarded(cmd_router))
