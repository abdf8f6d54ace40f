"""The commands that start the whole system: ``jamnav up`` (router, world, cloud and one agent
per UAV as separate processes, ``jamnav.supervisor``) and ``jamnav chaos`` (the same system
while its processes are killed and frozen, then a ledger of what was lost)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from jamnav.arguments import (
    UsageError,
    add_scenario,
    check_fleet,
    check_range,
    comma_numbers,
    new_recording,
    output_path,
    scenario_argument,
    scenario_with_jammer,
    survey_map_argument,
)
from jamnav.cli_runtime import guarded
from shared.scenario import MAX_UAVS, SEED_MAX, Scenario
from shared.shipped import VALUE_NET_HELP, value_net_for, value_net_path
from shared.topics import (
    DEFAULT_ENDPOINT,
    DEFAULT_PREFIX,
    ENDPOINT_ENV,
    Topics,
    add_bus_arguments,
    endpoint_from,
)

DEFAULT_SWAP_TO = "25,-10,1"  # Table I's second setting
DEFAULT_RATE = 10.0


def _check_value_network(path: str, scenario) -> None:
    """The file must be a value network this scenario's agents can fly with: found out now,
    not by a cloud that refuses to start once everything runs."""
    from cloud_service.evaluation import EvaluationError, load_policy

    try:
        load_policy(scenario, value_net_path(path))
    except EvaluationError as exc:
        raise UsageError(f"--model: {exc}") from None


def _survey_map(args: argparse.Namespace, scenario) -> Path | None:
    """The survey map the cloud starts the online map from: ``--sinr-map``, checked now, or
    the shipped one of the scenario's radio world; None for the other maps."""
    from shared.survey_maps import NoSurveyMapError, sinr_map_for

    if args.map != "online":
        if args.sinr_map is not None:
            raise UsageError("--sinr-map is where the online map starts: it needs --map online")
        return None
    if args.sinr_map is not None:
        return survey_map_argument("--sinr-map", args.sinr_map, scenario)
    try:
        return sinr_map_for(scenario)
    except NoSurveyMapError as exc:
        raise UsageError(str(exc)) from None


def _second_router(args: argparse.Namespace, endpoint: str) -> tuple[str | None, str | None]:
    """``--routers 2``: the agents' router and the TLS link between the routers, by default
    on the two ports after ``endpoint``."""
    from jamnav.routers import next_endpoint

    if args.routers == 1:
        if args.agent_endpoint or args.link_endpoint:
            raise UsageError("--agent-endpoint and --link-endpoint place the second router: "
                             "add --routers 2")
        return None, None
    agents = endpoint_from(args.agent_endpoint or next_endpoint(endpoint, 1))
    link = endpoint_from(args.link_endpoint or next_endpoint(endpoint, 2, "tls"))
    if not link.startswith("tls/"):
        raise UsageError(f"--link-endpoint {link!r}: the routers link over TLS (tls/HOST:PORT)")
    ports = [e.partition("/")[2] for e in (endpoint, agents, link)]
    if len(set(ports)) < len(ports):
        raise UsageError("--endpoint, --agent-endpoint and --link-endpoint need three "
                         "different ports")
    return agents, link


def _new_recording_of_up(text: str) -> Path:
    """``new_recording`` for ``jamnav up --record``, whose restarted recorder writes beside
    it (``recording.recording_path``): such a file left by an earlier run is refused now,
    not by the recorder in the middle of the run."""
    from jamnav.recording import restarted_recordings

    path = new_recording("--record", text)
    if earlier := restarted_recordings(path):
        raise UsageError(f"--record {text}: {earlier[0]} exists, where a restarted recorder "
                         "would write; choose another name or remove it")
    return path


def _check_run_options(args: argparse.Namespace, scenario: Scenario, uavs: int
                       ) -> tuple[str, Path | None]:
    """The fleet, the run's length and clock, the jammer and its swap, the networks and the
    online map's options, each checked before anything starts; the swap's target and the
    survey map the online map starts from."""
    from shared.jammer_messages import JammerInfo, initial_jammers

    check_range("--uavs", uavs, 1, MAX_UAVS)
    check_range("--episodes", args.episodes, 1)
    check_range("--seed", args.seed, 0, SEED_MAX)
    check_fleet("--uavs", uavs, scenario, args.seed)
    for name in ("duration", "rate", "deadline", "swap_jammer_at"):
        check_range(f"--{name.replace('_', '-')}", getattr(args, name), 0, above=True)
    if args.rate is not None and not args.realtime:
        raise UsageError("--rate sets the pace of --realtime; a lockstep run goes as fast as "
                         "its agents (see --deadline)")
    jammers = initial_jammers(scenario, args.jammer, None, args.no_jammer)
    if args.map == "perfect" and any(not jammer.as_jammer(scenario).still for jammer in jammers):
        raise UsageError(f"--map perfect serves the true map of still jammers, and a jammer of "
                         f"scenario {scenario.name} moves or switches: fly --map online or "
                         "outdated (jamnav eval --method perfect flies it in-process)")
    if args.swap_to is not None and args.swap_jammer_at is None:
        raise UsageError("--swap-to says where --swap-jammer-at moves the jammer: give both")
    swap_to = args.swap_to or DEFAULT_SWAP_TO
    if swap_to != "off":
        swap = JammerInfo.parse(swap_to, scenario.jammer.height_m)
        if not scenario.area.contains(swap.x, swap.y):
            raise UsageError(f"--swap-to {swap_to!r}: position outside the area")
    if args.model is not None:
        _check_value_network(args.model, scenario)
    survey = _survey_map(args, scenario)
    check_range("--retrain-samples", args.retrain_samples, 2)
    check_range("--swap-every", args.swap_every, 1)
    check_range("--cloud-latency", args.cloud_latency, 0, 3600)
    if args.cloud_latency is not None and (args.realtime or args.map != "online"):
        raise UsageError("--cloud-latency is the online map's on the lockstep clock; "
                         + ("a --realtime cloud runs on the wall clock" if args.realtime else
                            f"--map {args.map} follows the world's jammer at once"))
    return swap_to, survey


def _check_places(args: argparse.Namespace, uavs: int
                  ) -> tuple[Path, str, str | None, str | None]:
    """Where the run writes (its directory, the report, the recording) and where its routers
    listen, checked; the run directory and the endpoints of the routers and of their link."""
    from shared import access

    run_dir = output_path("--run-dir", args.run_dir or time.strftime("runs/up-%Y%m%d-%H%M%S"),
                          directory=True)
    if args.report:
        output_path("--report", args.report)
    if args.record:
        _new_recording_of_up(args.record)
    Topics(args.prefix)  # refuses a malformed prefix before anything starts
    if args.credentials is not None:  # refuses a file without every role's login, too
        access.load(args.credentials, access.roles(uavs, linked=args.routers > 1,
                                                   recorder=args.record is not None))
    endpoint = endpoint_from(args.endpoint)
    return (run_dir, endpoint, *_second_router(args, endpoint))


def cmd_up(args: argparse.Namespace) -> int:
    from jamnav.console import listen
    from jamnav.supervisor import UpConfig, up

    scenario = scenario_argument(args)
    uavs = scenario.missions.uav_count if args.uavs is None else args.uavs
    swap_to, survey = _check_run_options(args, scenario, uavs)
    run_dir, endpoint, agent_endpoint, link_endpoint = _check_places(args, uavs)
    web_listener, web = (None, None) if args.no_web else listen.open_listener(args.web)
    config = UpConfig(
        endpoint=endpoint, run_dir=run_dir, prefix=args.prefix,
        scenario=args.scenario, uavs=uavs, episodes=args.episodes, duration=args.duration,
        clock="realtime" if args.realtime else "lockstep", rate=args.rate or DEFAULT_RATE,
        deadline=args.deadline, map=args.map, jammer=args.jammer, no_jammer=args.no_jammer,
        seed=args.seed, report=Path(args.report) if args.report else None,
        swap_at=args.swap_jammer_at, swap_to=swap_to, swap_every=args.swap_every,
        cloud_latency=args.cloud_latency, retrain_samples=args.retrain_samples,
        figures=not args.no_figures,
        model=value_net_for(args.model, scenario_with_jammer(args), uavs), sinr_map=survey,
        secure=args.secure or args.credentials is not None,
        credentials=Path(args.credentials) if args.credentials else None,
        routers=args.routers, agent_endpoint=agent_endpoint, link_endpoint=link_endpoint,
        web=web, web_listener=web_listener,
        record=Path(args.record) if args.record else None,
        command="jamnav " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["up"] else "jamnav up",
    )
    return up(config, scenario)


def cmd_chaos(args: argparse.Namespace) -> int:
    from jamnav.chaos import QUIET_S, chaos, fault_schedule
    from jamnav.supervisor import UpConfig

    scenario = scenario_argument(args)
    check_range("--uavs", args.uavs, 1, 64)
    check_range("--rate", args.rate, 0, above=True)
    check_range("--seed", args.seed, 0, SEED_MAX)
    interval = comma_numbers(args.interval, 2, "--interval")
    freeze = comma_numbers(args.freeze, 2, "--freeze")
    if not 0 < interval[0] <= interval[1]:
        raise UsageError(f"--interval {args.interval}: expected MIN,MAX with 0 < MIN <= MAX")
    if not 0 < freeze[0] <= freeze[1] < interval[0]:
        raise UsageError(f"--freeze {args.freeze}: expected MIN,MAX with 0 < MIN <= MAX and "
                         "MAX below the --interval's MIN (a freeze ends before the next fault)")
    check_range("--duration", args.duration, QUIET_S + interval[1])
    run_dir = output_path("--run-dir", args.run_dir or time.strftime("runs/chaos-%Y%m%d-%H%M%S"),
                          directory=True)
    if run_dir.exists() and any(run_dir.iterdir()):
        raise UsageError(f"--run-dir {args.run_dir}: not empty; the ledger needs a fresh "
                         "directory (an earlier run's memory and outboxes would count)")
    Topics(args.prefix)  # refuses a malformed prefix before anything starts
    config = UpConfig(endpoint=endpoint_from(args.endpoint), run_dir=run_dir, prefix=args.prefix,
                      scenario=args.scenario, uavs=args.uavs, duration=args.duration,
                      clock="realtime", rate=args.rate, map=args.map, seed=args.seed,
                      figures=False, command="jamnav " + " ".join(sys.argv[1:]))
    faults = fault_schedule(args.seed, args.duration, (interval[0], interval[1]),
                            (freeze[0], freeze[1]), args.uavs)
    return chaos(config, scenario, faults)


# -- parsers ------------------------------------------------------------------------------------
def add_chaos_command(commands) -> None:
    soak = commands.add_parser(
        "chaos", help="run the system while killing and freezing its processes, then check "
                      "that nothing was lost")
    add_scenario(soak)
    soak.add_argument("--endpoint", default=None,
                      help=f"its router (default ${ENDPOINT_ENV} or {DEFAULT_ENDPOINT})")
    soak.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix of the system")
    soak.add_argument("--duration", type=float, required=True, metavar="SEC",
                      help="seconds of flight, the last 20 s without faults: at least 20 s "
                           "more than --interval's MAX")
    soak.add_argument("--interval", default="10,30", metavar="MIN,MAX",
                      help="seconds between faults, drawn uniformly (default 10,30)")
    soak.add_argument("--freeze", default="2,6", metavar="MIN,MAX",
                      help="seconds a frozen process stays frozen (default 2,6)")
    soak.add_argument("--seed", type=int, default=0, help="of the faults and the episodes")
    soak.add_argument("--uavs", type=int, default=3, help="UAVs (one agent process each)")
    soak.add_argument("--rate", type=float, default=10.0, help="steps per second")
    soak.add_argument("--map", choices=("online", "perfect", "outdated"), default="online",
                      help="the agents' SINR map (as jamnav up)")
    soak.add_argument("--run-dir", default=None, metavar="DIR",
                      help="a new directory: logs, report.json, ledger.json (default "
                           "runs/chaos-<time>)")
    soak.set_defaults(handler=guarded(cmd_chaos))


def add_up_command(commands) -> None:
    up = commands.add_parser("up", help="run the system: router, world, cloud, one agent per UAV")
    add_bus_arguments(up)
    add_scenario(up)
    _add_flight_arguments(up)
    _add_jammer_arguments(up)
    _add_cloud_and_output_arguments(up)
    _add_system_arguments(up)
    up.set_defaults(handler=guarded(cmd_up))


def _add_flight_arguments(up: argparse.ArgumentParser) -> None:
    """The fleet, how long the run lasts, its clock and the map the agents fly on."""
    up.add_argument("--uavs", type=int, default=None,
                    help="UAVs, one agent process each (default: the scenario's)")
    length = up.add_mutually_exclusive_group()
    length.add_argument("--episodes", type=int, default=None, help="stop after K episodes")
    length.add_argument("--duration", type=float, default=None, metavar="SEC",
                        help="stop after SEC seconds of flight (default: run until Ctrl-C)")
    clock = up.add_mutually_exclusive_group()
    clock.add_argument("--lockstep", action="store_true",
                       help="each step waits for every agent (default; deterministic)")
    clock.add_argument("--realtime", action="store_true", help="steps at a fixed rate")
    up.add_argument("--rate", type=float, default=None,
                    help=f"--realtime: steps per second (default {DEFAULT_RATE:g})")
    up.add_argument("--deadline", type=float, default=2.0,
                    help="lockstep: seconds a step waits for the actions")
    up.add_argument("--map", choices=("online", "perfect", "outdated"), default="online",
                    help="the agents' SINR map: learned online, true, or without the jammer")


def _add_jammer_arguments(up: argparse.ArgumentParser) -> None:
    """The jammer at the start and how it moves during the run."""
    jam = up.add_mutually_exclusive_group()
    jam.add_argument("--jammer", metavar="X,Y,P[,H]",
                     help="initial jammer (default: the scenario's)")
    jam.add_argument("--no-jammer", action="store_true", help="start without a jammer")
    up.add_argument("--swap-jammer-at", type=float, default=None, metavar="SEC",
                    help="move the jammer over the control topic SEC seconds into the flight")
    up.add_argument("--swap-to", default=None, metavar="X,Y,P|off",
                    help=f"where --swap-jammer-at moves it (default {DEFAULT_SWAP_TO})")
    up.add_argument("--swap-every", type=int, default=None, metavar="K",
                    help="move the jammer to a fresh random setting every K episodes, the "
                         "ones jamnav eval --swap-every K flies")


def _add_cloud_and_output_arguments(up: argparse.ArgumentParser) -> None:
    """The cloud's latency and networks, the episodes' seed, and where the run's files go."""
    up.add_argument("--cloud-latency", type=float, default=None, metavar="S",
                    help="lockstep, online map: flight seconds from a step's uploads to the "
                         "maps they trigger in service (default: the scenario's "
                         "online_map.cloud_latency_s; --realtime runs on the wall clock)")
    up.add_argument("--seed", type=int, default=0, help="of the episodes (default 0)")
    up.add_argument("--model", default=None, metavar="NAME|PATH",
                    help=f"the {VALUE_NET_HELP} the cloud serves")
    up.add_argument("--sinr-map", default=None, metavar="PATH",
                    help="the survey's no-jammer SINR map the online map starts from "
                         "(default: the shipped one of the scenario's radio world)")
    up.add_argument("--run-dir", default=None, metavar="DIR",
                    help="logs, report, figures, SINR maps (default runs/up-<time>)")
    up.add_argument("--report", default=None, metavar="FILE",
                    help="report JSON (default DIR/report.json)")
    up.add_argument("--retrain-samples", type=int, default=None, metavar="N",
                    help="post-change measurements the cloud retrains on (default: mapper's)")
    up.add_argument("--no-figures", action="store_true", help="skip the trajectory figures")


def _add_system_arguments(up: argparse.ArgumentParser) -> None:
    """Security, the routers, the recording and the console."""
    up.add_argument("--secure", action="store_true",
                    help="logins and access rules enforced by the router; fresh credentials "
                         "in DIR/credentials.json unless --credentials names a file")
    up.add_argument("--routers", type=int, choices=(1, 2), default=1,
                    help="2: the world and the cloud on one router, the agents on another, "
                         "the routers linked over TLS with certificates both ways (mTLS; "
                         "fresh ones in DIR/tls)")
    up.add_argument("--agent-endpoint", default=None, metavar="ENDPOINT",
                    help="--routers 2: the agents' router (default: --endpoint's port + 1)")
    up.add_argument("--link-endpoint", default=None, metavar="ENDPOINT",
                    help="--routers 2: where the first router awaits the second, tls/HOST:PORT "
                         "(default: --endpoint's port + 2)")
    up.add_argument("--record", default=None, metavar="FILE.mcap",
                    help="record every message of the run to an MCAP file (`jamnav replay`, "
                         "Foxglove)")
    web = up.add_mutually_exclusive_group()
    web.add_argument("--web", default=None, metavar="HOST:PORT",
                     help="where the console serves its page (default 127.0.0.1:8470, or a "
                          "free port if another system holds it)")
    web.add_argument("--no-web", action="store_true", help="no console")
