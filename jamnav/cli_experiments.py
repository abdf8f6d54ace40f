"""The paper's experiments flown in-process: ``jamnav eval`` (seeded episodes of one method),
``table`` (Table I), ``figures`` (Fig. 2a, 2b and 3), ``online-map`` (the online map's accuracy
across jammer changes, Fig. 2b) and ``cloud-latency`` (success against the cloud's latency)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jamnav.arguments import (
    UsageError,
    add_jammer,
    add_scenario,
    check_fleet,
    check_range,
    comma_numbers,
    output_path,
    scenario_argument,
    scenario_with_jammer,
    sinr_map_argument,
    survey_map_argument,
)
from jamnav.cli_training import one_torch_thread
from shared.radio import RadioModel
from shared.scenario import MAX_UAVS, SEED_MAX, Scenario
from shared.shipped import (
    SINR_MAP_NO_JAMMER,
    VALUE_NET,
    VALUE_NET_HELP,
    value_net_for,
    value_net_path,
)
from shared.topics import ArgumentParser

EVAL_METHODS = ("proposed", "perfect", "outdated", "orca", "straight")
MAX_ONLINE_PERIOD_S = 3600.0


def _value_net(name_or_path: str | None, scenario: Scenario, uavs: int | None = None) -> Path:
    return value_net_for(name_or_path, scenario, uavs or scenario.missions.uav_count)


def _add_online_map_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cloud-latency", type=float, default=None, metavar="S",
                        help="flight seconds from an upload to the online map it triggers in "
                             "service, 0 to 3600 (default: the scenario's "
                             "online_map.cloud_latency_s)")
    parser.add_argument("--reports", choices=("level", "db"), default=None,
                        help="what the UAVs' receivers report: the SINR's level (the paper's) "
                             "or the SINR itself in dB (default: the scenario's uav.report)")


def with_online_map_options(args: argparse.Namespace, scenario: Scenario) -> Scenario:
    """``scenario`` with --cloud-latency and --reports applied, where given."""
    changes = {}
    if args.cloud_latency is not None:
        check_range("--cloud-latency", args.cloud_latency, 0, 3600)
        changes["online_map.cloud_latency_s"] = args.cloud_latency
    if args.reports is not None:
        changes["uav.report"] = args.reports
    return scenario.changed(changes) if changes else scenario


def cmd_eval(args: argparse.Namespace) -> int:
    import torch

    from cloud_service.evaluation import LOOKAHEAD_METHODS, EvaluationError, evaluate
    from jamnav.progress import ProgressBar

    check_range("--episodes", args.episodes, 1)
    check_range("--uavs", args.uavs, 1, MAX_UAVS)
    check_range("--seed", args.seed, 0, SEED_MAX)
    if args.swap_every is not None:
        check_range("--swap-every", args.swap_every, 1)
    scenario = with_online_map_options(args, scenario_with_jammer(args))
    check_fleet("--uavs", args.uavs or scenario.missions.uav_count, scenario, args.seed)
    setting = scenario.flown_jammers
    # Options a method would not read are refused, not ignored: the user meant something.
    if args.sinr_map is not None:
        if args.method != "proposed":
            raise UsageError(f"--sinr-map is the proposed method's initial map; --method "
                             f"{args.method} does not read one")
        survey_map_argument("--sinr-map", args.sinr_map, scenario)
    for option, value in (("--cloud-latency", args.cloud_latency), ("--reports", args.reports)):
        if value is not None and args.method != "proposed":
            raise UsageError(f"{option} is the online map's; --method {args.method} flies "
                             "without one")
    if args.model is not None and args.method not in LOOKAHEAD_METHODS:
        raise UsageError(f"--model: --method {args.method} flies without a value network")
    torch.set_num_threads(1)
    bar = ProgressBar(f"eval {args.method}", args.episodes)
    finished = 0

    def on_episode(_episode: int) -> None:
        nonlocal finished
        finished += 1
        bar.update(finished)

    try:
        report = evaluate(scenario, args.method, args.episodes, args.seed, setting, args.uavs,
                          _value_net(args.model, scenario, args.uavs),
                          args.sinr_map and Path(args.sinr_map),
                          on_episode,
                          args.swap_every)
    except EvaluationError as exc:
        raise UsageError(f"eval: {exc}") from None
    if not args.per_episode:
        del report["outcomes"], report["ended_at_step"]
    if args.json:
        print(json.dumps(report))
    else:
        print(f"{args.method}, every episode: {rates_text(report)}")
        for part in ("transient", "steady"):
            if part in report and report[part]["episodes"]:
                print(f"  {part} ({report[part]['episodes']} episodes): "
                      f"{rates_text(report[part])}")
    return 0


def rates_text(rates: dict) -> str:
    return ", ".join(f"{key[:-5]} {rates[key]:.1%}" for key in rates if key.endswith("_rate"))


def cmd_table(args: argparse.Namespace) -> int:
    import torch

    from cloud_service.evaluation import EvaluationError, load_policy, table_one, write_table

    check_range("--episodes", args.episodes, 1)
    check_range("--seed", args.seed, 0, SEED_MAX)
    out = output_path("--out", args.out, directory=True)
    torch.set_num_threads(1)
    scenario = with_online_map_options(args, scenario_argument(args))
    check_fleet("the scenario's missions.uav_count", scenario.missions.uav_count, scenario,
                args.seed)
    nets = {"paper": value_net_path(args.model),
            "extended": _value_net(args.extended_model, scenario)}
    for option, path in zip(("--model", "--extended-model"), nets.values(), strict=True):
        try:  # each network first flies after hours of the others' runs
            load_policy(scenario, path)
        except EvaluationError as exc:
            raise UsageError(f"{option}: {exc}") from None
    runs = 4 * 3 * len(nets)
    done = 0

    def on_run(label: str) -> None:
        nonlocal done
        done += 1
        print(f"table: run {done}/{runs}: {label}", file=sys.stderr, flush=True)

    try:
        rows = table_one(scenario, args.episodes, args.seed, nets, on_run)
    except EvaluationError as exc:
        raise UsageError(f"table: {exc}") from None
    command = "jamnav " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["table"] else "jamnav table"
    md_path, csv_path = write_table(rows, out, command)
    print(md_path.read_text(encoding="utf-8"))
    print(f"wrote {md_path} and {csv_path}", file=sys.stderr)
    return 0


def _check_train_log(log: Path) -> None:
    """The columns Fig. 2a plots, read as plot_reward_curve reads them."""
    if log.is_dir():
        raise UsageError(f"--train-log {log}: a directory, not a training log")
    if not log.is_file():
        raise UsageError(f"--train-log {log}: no such file (run jamnav train first)")
    try:
        with log.open(encoding="utf-8") as handle:
            columns = handle.readline().strip().split(",")
        missing = [name for name in ("episode", "mean_return", "straight_bound")
                   if name not in columns]
        rows = 0 if missing else np.atleast_1d(  # and rows cut short by a crash are refused
            np.genfromtxt(log, delimiter=",", names=True)).size
    except OSError as exc:
        raise UsageError(f"--train-log {log}: {exc.strerror}") from None
    except ValueError:  # UnicodeDecodeError is one too
        raise UsageError(f"--train-log {log}: not readable as a CSV training log") from None
    if missing:
        raise UsageError(f"--train-log {log}: not a training log (no column "
                         f"{', '.join(missing)})")
    if rows == 0:
        raise UsageError(f"--train-log {log}: no episodes logged yet")


def cmd_figures(args: argparse.Namespace) -> int:
    from cloud_service.evaluation import EvaluationError, load_policy, trajectories
    from shared.paper import TABLE_I_JAMMERS
    from shared.plots import plot_reward_curve, save_trajectory_figure

    one_torch_thread()
    check_range("--seed", args.seed, 0, SEED_MAX)
    out = output_path("--out", args.out, directory=True)
    scenario = scenario_argument(args)
    log = Path(args.train_log)
    _check_train_log(log)
    try:  # Fig. 3 flies it last, after the online-map simulation of Fig. 2b
        load_policy(scenario, _value_net(args.model, scenario))
    except EvaluationError as exc:
        raise UsageError(f"--model: {exc}") from None
    plot_reward_curve(log, out / "fig2a_reward_curve.png")
    print(f"wrote {out / 'fig2a_reward_curve.png'}", file=sys.stderr)
    _online_map_figure(args, out / "fig2b_online_map_accuracy.png")
    panels = []
    for setting in (None, *TABLE_I_JAMMERS[:3]):
        jammer = None if setting is None else scenario.with_jammer(*setting)
        params = None if jammer is None else RadioModel.jammer_of(jammer)
        try:
            positions, destinations, outcomes = trajectories(
                scenario, setting, args.seed, _value_net(args.model, scenario))
        except EvaluationError as exc:
            raise UsageError(f"figures: {exc}") from None
        panels.append(("", params, positions, destinations, outcomes))
    save_trajectory_figure(scenario, panels, out / "fig3_trajectories.png")
    print(f"wrote {out / 'fig3_trajectories.png'}", file=sys.stderr)
    return 0


def _online_map_figure(args: argparse.Namespace, out: Path) -> None:
    """Fig. 2b for ``jamnav figures``: ``jamnav online-map`` with its defaults, on the
    scenario and seed of ``args``."""
    online = ArgumentParser(prog="jamnav online-map")
    _add_online_map_command_arguments(online)
    argv = ["--out", str(out), "--seed", str(args.seed)]
    if args.scenario:
        argv += ["--scenario", args.scenario]
    cmd_online_map(online.parse_args(argv))


def cmd_online_map(args: argparse.Namespace) -> int:
    from cloud_service.online_map_sim import (
        DEFAULT_UAVS,
        Schedule,
        save_online_map_figure,
        simulate_online_map,
    )
    from jamnav.progress import ProgressBar

    one_torch_thread()
    scenario = scenario_argument(args)
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise UsageError(f"--out {args.out}: the figure is written as PNG; name it *.png")
    output_path("--out", args.out, beside=(".json",))  # the timeline goes beside the figure
    uavs = DEFAULT_UAVS if args.uavs is None else args.uavs
    check_range("--uavs", uavs, 1, MAX_UAVS)
    # A setting must last steps enough to be seen at all; a day of flight is a figure no
    # one waits for.
    check_range("--period", args.period, 2 * scenario.timing.step_s, MAX_ONLINE_PERIOD_S)
    check_range("--seed", args.seed, 0, SEED_MAX)
    network, card = sinr_map_argument("--model", args.model, scenario)
    if not isinstance(card.get("accuracy"), int | float):
        raise UsageError(f"--model {args.model}: its card states no accuracy")
    schedule = Schedule.table_i(first_change=args.period / 2, period=args.period)
    bar: ProgressBar | None = None

    def on_step(done: int, steps: int) -> None:
        nonlocal bar
        bar = bar or ProgressBar("online-map", steps)
        bar.update(done)

    timeline = simulate_online_map(scenario, network, float(card["accuracy"]), schedule,
                                   schedule.starts[-1] + args.period, uavs=uavs,
                                   seed=args.seed, on_step=on_step)
    save_online_map_figure(timeline, out)
    published = [e for e in timeline["events"] if e["type"] == "sinr_weights_published"]
    print(f"wrote {out} and {out.with_suffix('.json')} "
          f"({len(published)} maps published)", file=sys.stderr)
    return 0


def cmd_cloud_latency(args: argparse.Namespace) -> int:
    from cloud_service.evaluation import EvaluationError
    from cloud_service.latency_sweep import save_runs, sweep, write_outputs

    check_range("--episodes", args.episodes, 1)
    check_range("--seeds", args.seeds, 1, 100)
    check_range("--swap-every", args.swap_every, 1)
    latencies = comma_numbers(args.latencies, len(args.latencies.split(",")), "--latencies")
    for latency in latencies:
        check_range("--latencies", latency, 0, 3600)
    out = output_path("--out", args.out, directory=True)
    scenario = scenario_with_jammer(args)
    check_fleet("--uavs", args.uavs or scenario.missions.uav_count, scenario, 0)
    one_torch_thread()
    runs, command = args.seeds * (len(latencies) + 1), "jamnav " + " ".join(sys.argv[1:])

    def on_run(so_far: dict, label: str) -> None:
        save_runs(so_far, out, command)
        print(f"cloud-latency: run {len(so_far['runs'])}/{runs}: {label}", file=sys.stderr,
              flush=True)

    try:
        result = sweep(scenario, latencies, args.seeds, args.episodes, args.swap_every,
                       args.uavs, on_run)
    except EvaluationError as exc:
        raise UsageError(f"cloud-latency: {exc}") from None
    paths = write_outputs(result, out, command)
    print(paths[1].read_text(encoding="utf-8"))
    print("wrote " + ", ".join(map(str, paths)), file=sys.stderr)
    return 0


def cmd_jammers_table(args: argparse.Namespace) -> int:
    import os

    from cloud_service.evaluation import EvaluationError
    from cloud_service.scenario_tables import METHODS, jammer_table_runs, write_jammer_table
    from shared.survey_maps import NoSurveyMapError, sinr_map_for

    check_range("--episodes", args.episodes, 1)
    check_range("--seeds", args.seeds, 1, 100)
    check_range("--jobs", args.jobs, 1, 64)
    out = output_path("--out", args.out, directory=True)
    for name in args.scenarios:  # every one readable and flyable before hours of runs
        scenario = scenario_argument(argparse.Namespace(scenario=name))
        check_fleet(f"scenario {name}", scenario.missions.uav_count, scenario, 0)
        try:  # the online map starts from the survey map of the scenario's radio world
            sinr_map_for(scenario)
        except NoSurveyMapError as exc:
            raise UsageError(f"scenario {name}: {exc}") from None
    runs = len(args.scenarios) * len(METHODS) * args.seeds
    command = (f"jamnav jammers-table {' '.join(args.scenarios)} --seeds {args.seeds} "
               f"--episodes {args.episodes}")  # what the table holds, wherever it was run
    done = 0

    def on_run(run: dict) -> None:
        nonlocal done
        done += 1
        print(f"jammers-table: run {done}/{runs}: {run['scenario']} {run['method']} seed "
              f"{run['seed']}: success {run['success_rate']:.1%}", file=sys.stderr, flush=True)

    try:
        result = jammer_table_runs(args.scenarios, args.seeds, args.episodes,
                                   args.jobs or os.cpu_count() or 1, on_run)
    except EvaluationError as exc:
        raise UsageError(f"jammers-table: {exc}") from None
    md_path, json_path = write_jammer_table(result, out, command)
    print(md_path.read_text(encoding="utf-8"))
    print(f"wrote {md_path} and {json_path}", file=sys.stderr)
    return 0


# -- parsers ------------------------------------------------------------------------------------
def add_eval_command(commands) -> None:
    evaluation = commands.add_parser("eval", help="fly seeded episodes in-process and score them")
    add_scenario(evaluation)
    add_jammer(evaluation)
    evaluation.add_argument("--method", choices=EVAL_METHODS, default="proposed",
                            help="maps the UAVs fly on: proposed (the online map), perfect "
                                 "(the true one), outdated (the no-jammer one); or orca or "
                                 "straight, which fly without one (default: proposed)")
    evaluation.add_argument("--episodes", type=int, default=200, help="default 200")
    evaluation.add_argument("--uavs", type=int, default=None,
                            help="UAVs per episode (default: the scenario's; at most as many "
                                 "as its area holds missions for)")
    evaluation.add_argument("--seed", type=int, default=0, help="default 0")
    evaluation.add_argument("--model", default=None, help=VALUE_NET_HELP)
    evaluation.add_argument("--sinr-map", default=None,
                            help="initial SINR map of the proposed method (default: the "
                                 "shipped no-jammer map of the scenario)")
    evaluation.add_argument("--swap-every", type=int, default=None, metavar="K",
                            help="resilience evaluation: move the jammer to a fresh random "
                                 "setting every K episodes")
    _add_online_map_options(evaluation)
    evaluation.add_argument("--json", action="store_true", help="print JSON")
    evaluation.add_argument("--per-episode", action="store_true",
                            help="include each episode's per-UAV outcomes and the step "
                                 "at which each mission ended")
    evaluation.set_defaults(handler=cmd_eval)


def add_table_command(commands) -> None:
    table = commands.add_parser("table", help="Table I: 4 jammer settings x 3 methods")
    add_scenario(table)
    table.add_argument("--episodes", type=int, default=200,
                       help="episodes per cell (default 200)")
    table.add_argument("--seed", type=int, default=0, help="default 0")
    table.add_argument("--out", default="results", metavar="DIR",
                       help="where table1.md and table1.csv go (default: results, the shipped "
                            "ones)")
    table.add_argument("--model", default="paper",
                       help="the paper-method column's value network (a name or a path)")
    table.add_argument("--extended-model", default=None,
                       help="the extended column's value network (a name or a path; default: "
                            "the best shipped one for the scenario's fleet)")
    _add_online_map_options(table)
    table.set_defaults(handler=cmd_table)


def add_figures_command(commands) -> None:
    figures = commands.add_parser("figures", help="the paper's Fig. 2a, 2b and 3 from real runs")
    add_scenario(figures)
    figures.add_argument("--out", default="results", metavar="DIR",
                         help="where the PNGs go (default: results, the shipped ones)")
    figures.add_argument("--seed", type=int, default=0, help="default 0")
    figures.add_argument("--train-log", default=str(VALUE_NET.with_name("train_log.csv")),
                         help="training log for Fig. 2a (default: the shipped model's)")
    figures.add_argument("--model", default=None,
                         help=f"{VALUE_NET_HELP}, flown in Fig. 3")
    figures.set_defaults(handler=cmd_figures)


def _add_online_map_command_arguments(parser: argparse.ArgumentParser) -> None:
    add_scenario(parser)
    parser.add_argument("--model", default=str(SINR_MAP_NO_JAMMER), metavar="PATH",
                        help="the initial map (default: models/sinr_map_no_jammer.safetensors)")
    parser.add_argument("--uavs", type=int, default=None,
                        help="UAVs reporting along their paths (default 20)")
    parser.add_argument("--period", type=float, default=120.0,
                        help="simulated seconds per jammer setting (default 120; from two "
                             f"steps to {MAX_ONLINE_PERIOD_S:g})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, metavar="FILE.png")


def add_online_map_command(commands) -> None:
    online = commands.add_parser(
        "online-map", help="accuracy of the online SINR map across jammer changes (Fig. 2b)"
    )
    _add_online_map_command_arguments(online)
    online.set_defaults(handler=cmd_online_map)


def _add_seeds_and_episodes(parser: argparse.ArgumentParser, episodes: int, per: str) -> None:
    """The runs of a sweep over seeds 0..N-1, of ``episodes`` episodes each by default."""
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    parser.add_argument("--episodes", type=int, default=episodes,
                        help=f"episodes per {per} (default {episodes})")


def add_cloud_latency_command(commands) -> None:
    latency = commands.add_parser(
        "cloud-latency", help="success on the online map against the cloud's latency, the "
                              "jammer moving (figure, table)")
    add_scenario(latency)
    add_jammer(latency)
    latency.add_argument("--latencies", default="0,1,2,5,10,30,60", metavar="S,S,...",
                         help="cloud latencies to fly, seconds of flight (default "
                              "0,1,2,5,10,30,60)")
    _add_seeds_and_episodes(latency, 200, "seed and latency")
    latency.add_argument("--swap-every", type=int, default=10, metavar="K",
                         help="move the jammer to a fresh random setting every K episodes "
                              "(default 10)")
    latency.add_argument("--uavs", type=int, default=None, help="UAVs per episode")
    latency.add_argument("--out", default="results", metavar="DIR",
                         help="where cloud_latency_<scenario>.{json,md,png} go (default: "
                              "results)")
    latency.set_defaults(handler=cmd_cloud_latency)


def add_jammers_table_command(commands) -> None:
    table = commands.add_parser(
        "jammers-table", help="scenarios' own jammers: the online, perfect and outdated maps "
                              "over seeds (table)")
    table.add_argument("scenarios", nargs="+", metavar="SCENARIO",
                       help="scenario names or TOML files, each flown with the jammers it lists "
                            "(e.g. two-jammers convoy)")
    _add_seeds_and_episodes(table, 400, "scenario, map and seed")
    table.add_argument("--jobs", type=int, default=None,
                       help="runs flown at once, each in its own process (default: the CPUs)")
    table.add_argument("--out", default="results/jammers", metavar="DIR",
                       help="where jammers_table.{md,json} go (default: results/jammers)")
    table.set_defaults(handler=cmd_jammers_table)
