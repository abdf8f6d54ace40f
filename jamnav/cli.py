"""The ``jamnav`` command line. Each sub-command parses, calls core code, and prints.

Errors a user can cause (bad arguments, bad files) end with one line on stderr and exit code 2,
never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from jamnav.arguments import (
    UsageError,
    check_fleet,
    check_range,
    output_path,
    sinr_map_argument,
    survey_map_argument,
)
from jamnav.cli_runtime import _guarded
from jamnav.cli_runtime import register as register_runtime
from planning import PlannerError
from shared.radio import RadioModel
from shared.scenario import (
    MAX_UAVS,
    SEED_MAX,
    Scenario,
    ScenarioError,
    load_scenario,
    resolve_scenario_path,
)
from shared.shipped import (
    SINR_MAP_NO_JAMMER,
    VALUE_NET,
    VALUE_NET_HELP,
    value_net_for,
    value_net_path,
)
from shared.topics import DEFAULT_ENDPOINT, DEFAULT_PREFIX, ENDPOINT_ENV, ArgumentParser

if TYPE_CHECKING:  # training's modules load only where a command trains
    from cloud_service.training_config import TrainConfig


# -- argument helpers -------------------------------------------------------------------------
def _check_device(text: str) -> None:
    """Only cpu and cuda[:N] are supported: torch.device also accepts names such as mps or
    meta, which then fail as tracebacks deep inside training."""
    import torch

    try:
        device = torch.device(text)
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise UsageError(f"--device {text}: expected cpu, cuda or cuda:N")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UsageError(f"--device {text}: CUDA is not available on this machine")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise UsageError(f"--device {text}: this machine has {torch.cuda.device_count()} "
                         "CUDA device(s)")


def _load_scenario(args: argparse.Namespace) -> Scenario:
    """load_scenario, with a file that exists but cannot be read as one line too."""
    try:
        return load_scenario(args.scenario)
    except OSError as exc:
        raise UsageError(f"{resolve_scenario_path(args.scenario)}: {exc.strerror}") from None


def _value_net(name_or_path: str | None, scenario: Scenario, uavs: int | None = None) -> Path:
    return value_net_for(name_or_path, scenario.area.square_metres,
                         uavs or scenario.missions.uav_count)


def _numbers(text: str, count: int, what: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(part) for part in parts]
    except ValueError:
        raise UsageError(f"{what} {text!r}: expected {count} comma-separated numbers") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise UsageError(f"{what} {text!r}: expected {count} finite comma-separated numbers")
    return values


def _add_scenario(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", default=None, metavar="NAME|PATH",
        help="scenario name under scenarios/ or a TOML file (default: icc2021)",
    )


def _add_jammer(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--jammer", metavar="X,Y,P[,H]",
        help="jammer position (m), nominal power (W) and height (m, default: the scenario's)",
    )
    group.add_argument("--no-jammer", action="store_true", help="no jammer at all")


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


def scenario_with_jammer(args: argparse.Namespace) -> Scenario:
    """The scenario named by --scenario with --jammer/--no-jammer applied and validated."""
    from shared.messages import JammerInfo

    scenario = _load_scenario(args)
    if getattr(args, "no_jammer", False):
        return scenario.without_jammer()
    if getattr(args, "jammer", None) is not None:
        try:
            jammer = JammerInfo.parse(args.jammer, scenario.jammer.height_m)
        except ValueError as exc:
            raise UsageError(f"--{exc}") from None
        if not scenario.area.contains(jammer.x, jammer.y):
            area = scenario.area
            raise UsageError(
                f"--jammer {args.jammer!r}: position outside the area "
                f"[{area.x_min:g}, {area.x_max:g}] x [{area.y_min:g}, {area.y_max:g}]"
            )
        return scenario.with_jammer(jammer.x, jammer.y, jammer.power_w, jammer.height_m)
    return scenario


def _read_points(args: argparse.Namespace) -> np.ndarray:
    if args.at:
        return np.array([_numbers(text, 2, "--at") for text in args.at])
    source = args.points_json
    try:
        text = sys.stdin.read() if source == "-" else Path(source).read_text(encoding="utf-8")
        data = json.loads(text)
    except OSError as exc:
        raise UsageError(f"--points-json {source}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise UsageError(f"--points-json {source}: not valid JSON ({exc.msg})") from None
    except UnicodeDecodeError:
        raise UsageError(f"--points-json {source}: not UTF-8 text") from None
    points = []
    for item in data if isinstance(data, list) else [None]:
        if isinstance(item, dict) and {"x", "y"} <= item.keys():
            item = [item["x"], item["y"]]
        if (
            not isinstance(item, list | tuple)
            or len(item) != 2
            # JSON true and false arrive as bool, a subclass of int
            or not all(isinstance(v, int | float) and not isinstance(v, bool)
                       and math.isfinite(v) for v in item)
        ):
            raise UsageError(
                f"--points-json {source}: expected a list of [x, y] or {{\"x\", \"y\"}} "
                "with finite numbers"
            )
        points.append([float(item[0]), float(item[1])])
    return np.array(points, dtype=np.float64).reshape(-1, 2)


# -- commands -----------------------------------------------------------------------------------
def cmd_scenario_show(args: argparse.Namespace) -> int:
    scenario = _load_scenario(args)
    data = scenario.model_dump(mode="json")
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    for section, values in data.items():
        if not isinstance(values, dict):
            print(f"{section} = {values}")
            continue
        print(f"[{section}]")
        for key, value in values.items():
            print(f"  {key} = {value}")
    return 0


def cmd_sinr(args: argparse.Namespace) -> int:
    if args.model:
        return _sinr_from_model(args)
    scenario = scenario_with_jammer(args)
    points = _read_points(args)
    radio = RadioModel(scenario)
    reading = radio.evaluate(points, radio.default_jammer)
    rows = [
        {
            "x": float(x),
            "y": float(y),
            "sinr_db": round(float(db), 6),
            "level": int(level),
            "serving_gbs": int(serving),
        }
        for (x, y), db, level, serving in zip(
            points, reading.sinr_db, reading.level, reading.serving_gbs, strict=True
        )
    ]
    print(json.dumps(rows))
    return 0


def _sinr_from_model(args: argparse.Namespace) -> int:
    """Levels predicted by a SINR-map network, in the shape of the true-map query; the
    network predicts levels only, so sinr_db and serving_gbs are null."""
    from planning.networks import predict_levels
    from shared.measurements import scenario_features

    if args.jammer or args.no_jammer:
        raise UsageError("--model: the network is the map of the jammer it was trained for; "
                         "--jammer/--no-jammer do not apply")
    scenario = _load_scenario(args)
    network, _ = sinr_map_argument("--model", args.model, scenario)
    points = _read_points(args)
    levels = predict_levels(network, scenario_features(scenario, points))
    rows = [
        {"x": float(x), "y": float(y), "sinr_db": None, "level": int(level), "serving_gbs": None}
        for (x, y), level in zip(points, levels, strict=True)
    ]
    print(json.dumps(rows))
    return 0


def cmd_map(args: argparse.Namespace) -> int:
    from shared.plots import save_coverage_map

    scenario = scenario_with_jammer(args)
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise UsageError(f"--out {args.out}: the map is written as PNG; name it *.png")
    output_path("--out", args.out)
    check_range("--resolution", args.resolution, 20, 2000)
    share = save_coverage_map(scenario, RadioModel.jammer_of(scenario), out, args.resolution)
    print(f"wrote {out} (covered {share:.1%} of the area)", file=sys.stderr)
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    import torch

    from cloud_service.evaluation import LOOKAHEAD_METHODS, EvaluationError, evaluate
    from jamnav.progress import ProgressBar
    from shared.paper import JammerSetting

    check_range("--episodes", args.episodes, 1)
    check_range("--uavs", args.uavs, 1, MAX_UAVS)
    check_range("--seed", args.seed, 0, SEED_MAX)
    if args.swap_every is not None:
        check_range("--swap-every", args.swap_every, 1)
    scenario = with_online_map_options(args, scenario_with_jammer(args))
    check_fleet("--uavs", args.uavs or scenario.missions.uav_count, scenario, args.seed)
    jammer = RadioModel.jammer_of(scenario)
    setting = None if jammer is None else JammerSetting(jammer.x, jammer.y, jammer.power_w)
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
        del report["outcomes"]
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
    scenario = with_online_map_options(args, _load_scenario(args))
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

    _one_torch_thread()
    check_range("--seed", args.seed, 0, SEED_MAX)
    out = output_path("--out", args.out, directory=True)
    scenario = _load_scenario(args)
    log = Path(args.train_log)
    _check_train_log(log)
    try:  # Fig. 3 flies it last, after the online-map simulation of Fig. 2b
        load_policy(scenario, _value_net(args.model, scenario))
    except EvaluationError as exc:
        raise UsageError(f"--model: {exc}") from None
    plot_reward_curve(log, out / "fig2a_reward_curve.png")
    print(f"wrote {out / 'fig2a_reward_curve.png'}", file=sys.stderr)
    online_argv = ["online-map", "--out", str(out / "fig2b_online_map_accuracy.png"),
                   "--seed", str(args.seed)]
    if args.scenario:
        online_argv += ["--scenario", args.scenario]
    cmd_online_map(build_parser().parse_args(online_argv))
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


def _check_checkpoint(out: Path, scenario: Scenario, config: TrainConfig, resume: bool) -> None:
    """A checkpoint in ``out`` must fit the command: --resume continues it, so every file it
    would load must be whole and its run made with the same settings (train() would fail
    late, as a traceback, or continue another run under this one's card); a fresh start would
    throw it away."""
    from cloud_service.training_checkpoint import Checkpoint, CheckpointError
    from cloud_service.value_learner import Learner

    checkpoint = Checkpoint(out)
    if resume:
        try:
            checkpoint.load(Learner.fresh(scenario, config), scenario, config)
        except CheckpointError as exc:
            raise UsageError(f"--resume: {exc}") from None
    elif checkpoint.exists():
        try:
            held = f"a checkpoint of {checkpoint.progress()['episodes_done']} episodes"
        except (CheckpointError, KeyError):  # damaged, but still a run not to throw away
            held = "a checkpoint"
        raise UsageError(f"--out {out} holds {held}: --resume continues it; to start afresh, "
                         f"remove {checkpoint.root} or choose another --out")


def cmd_train(args: argparse.Namespace) -> int:
    from cloud_service.training_config import MAX_ENVS, TrainConfig
    from cloud_service.value_training import train
    from jamnav.progress import ProgressBar

    scenario = _load_scenario(args)
    check_range("--episodes", args.episodes, 1)
    check_range("--envs", args.envs, 1, MAX_ENVS)
    check_range("--uavs", args.uavs, 1, 64)
    check_range("--seed", args.seed, 0, SEED_MAX)
    _check_device(args.device)
    out = output_path("--out", args.out, directory=True)
    config = TrainConfig(episodes=args.episodes, envs=args.envs, uavs=args.uavs,
                         seed=args.seed, device=args.device, method=args.method)
    _check_checkpoint(out, scenario, config, args.resume)
    bar = ProgressBar("train", args.episodes)
    validated = ""

    def progress(info: dict) -> None:
        nonlocal validated
        phase = info["phase"]
        if phase == "td":
            bar.update(info["episodes_done"], f"eps {info['epsilon']:.2f} "
                       f"success(last 200) {info['recent_success']:.0%}{validated}")
        elif phase == "validation":
            validated = (f" validation {info['success_rate']:.1%} (best "
                         f"{info['best_success_rate']:.1%} at {info['best_episode']})")
        elif phase == "interrupted":
            if bar.interactive:  # its line is not ended yet
                print(file=sys.stderr)
            print(f"train: stopped after {info['episodes_done']} episodes, all of them in the "
                  f"checkpoint in {info['checkpoint']}: --resume continues it", file=sys.stderr)
        else:
            print(f"train: {phase} {info.get('episodes', '')}".rstrip(), file=sys.stderr)

    command = "jamnav " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["train"] else "jamnav train"
    card = train(scenario, config, out, resume=args.resume, progress=progress, command=command)
    validation = card["validation"]
    print(json.dumps({
        "out": str(out),
        "episodes": card["episodes"],
        "wall_seconds": card["wall_seconds"],
        "decisions_per_second": card["decisions_per_second"],
        "selected_episode": card["selection"]["selected_episode"],
        "validation": {k: validation[k] for k in ("success_rate", "disconnection_rate",
                                                   "collision_rate", "timeout_rate")},
    }, indent=2))
    return 0


def _one_torch_thread() -> None:
    """The SINR network is tiny (batches of 200 through 32 units): a second thread only adds
    hand-offs, and on a 2-core machine makes training several times slower."""
    import torch

    torch.set_num_threads(1)


def cmd_fit_sinr(args: argparse.Namespace) -> int:
    from cloud_service.sinr_training import fit_sinr_map
    from cloud_service.value_training import git_commit
    from jamnav.progress import ProgressBar
    from planning.networks import save_network

    _one_torch_thread()
    scenario = scenario_with_jammer(args)
    # Simulating takes about 1.4 kB per sample: a million is 1.4 GB, far past the default.
    check_range("--samples", args.samples, 100, 1_000_000)
    check_range("--steps", args.steps, 1)
    check_range("--seed", args.seed, 0, SEED_MAX)
    out = Path(args.out)
    if out.suffix != ".safetensors":
        raise UsageError(f"--out {args.out}: name the weights file *.safetensors")
    output_path("--out", args.out, beside=(".json",))  # the card goes beside the weights
    bar = ProgressBar("fit-sinr", args.steps)

    def progress(step: int, accuracy: float) -> None:
        bar.update(step, f"held-out accuracy {accuracy:.1%}", force=step == args.steps)

    network, figures = fit_sinr_map(scenario, RadioModel.jammer_of(scenario), args.samples,
                                    args.steps, args.seed, progress)
    command = "jamnav " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["fit-sinr"] else (
        "jamnav fit-sinr")
    card = {"command": command, **figures, "git_commit": git_commit()}
    card["sha256"] = save_network(network, out, card)
    print(json.dumps({"out": str(out), **card}, indent=2))
    return 0


MAX_ONLINE_PERIOD_S = 3600.0


def cmd_cloud_latency(args: argparse.Namespace) -> int:
    from cloud_service.evaluation import EvaluationError
    from cloud_service.latency_sweep import save_runs, sweep, write_outputs

    check_range("--episodes", args.episodes, 1)
    check_range("--seeds", args.seeds, 1, 100)
    check_range("--swap-every", args.swap_every, 1)
    latencies = _numbers(args.latencies, len(args.latencies.split(",")), "--latencies")
    for latency in latencies:
        check_range("--latencies", latency, 0, 3600)
    out = output_path("--out", args.out, directory=True)
    scenario = scenario_with_jammer(args)
    check_fleet("--uavs", args.uavs or scenario.missions.uav_count, scenario, 0)
    _one_torch_thread()
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


def cmd_online_map(args: argparse.Namespace) -> int:
    from cloud_service.online_map_sim import (
        DEFAULT_UAVS,
        Schedule,
        save_online_map_figure,
        simulate_online_map,
    )
    from jamnav.progress import ProgressBar

    _one_torch_thread()
    scenario = _load_scenario(args)
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


def cmd_chaos(args: argparse.Namespace) -> int:
    from jamnav.chaos import QUIET_S, chaos, fault_schedule
    from jamnav.supervisor import UpConfig
    from shared.topics import Topics, endpoint_from

    scenario = _load_scenario(args)
    check_range("--uavs", args.uavs, 1, 64)
    check_range("--rate", args.rate, 0, above=True)
    check_range("--seed", args.seed, 0, SEED_MAX)
    interval = _numbers(args.interval, 2, "--interval")
    freeze = _numbers(args.freeze, 2, "--freeze")
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


EVAL_METHODS = ("proposed", "perfect", "outdated", "orca", "straight")


# -- parser -----------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="jamnav", description="Jamming-resilient path planning for many UAVs."
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    scenario = commands.add_parser("scenario", help="inspect scenario files")
    scenario_commands = scenario.add_subparsers(dest="scenario_command", required=True)
    show = scenario_commands.add_parser("show", help="print the effective scenario")
    _add_scenario(show)
    show.add_argument("--json", action="store_true", help="print JSON")
    show.set_defaults(handler=cmd_scenario_show)

    sinr = commands.add_parser("sinr", help="SINR, level and serving GBS at points")
    _add_scenario(sinr)
    _add_jammer(sinr)
    where = sinr.add_mutually_exclusive_group(required=True)
    where.add_argument("--at", nargs="+", metavar="X,Y", help="points as X,Y")
    where.add_argument(
        "--points-json", metavar="FILE|-", help='JSON list of [x, y] or {"x", "y"}; - = stdin'
    )
    sinr.add_argument(
        "--model", metavar="PATH",
        help="predict levels with a SINR-map network (safetensors + JSON card) instead",
    )
    sinr.set_defaults(handler=cmd_sinr)

    coverage = commands.add_parser("map", help="coverage map as in the paper's Fig. 3")
    _add_scenario(coverage)
    _add_jammer(coverage)
    coverage.add_argument("--out", required=True, metavar="FILE.png", help="the figure (PNG)")
    coverage.add_argument("--resolution", type=int, default=301,
                          help="grid points per side, 20 to 2000 (default 301)")
    coverage.set_defaults(handler=cmd_map)

    evaluation = commands.add_parser("eval", help="fly seeded episodes in-process and score them")
    _add_scenario(evaluation)
    _add_jammer(evaluation)
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
                            help="include each episode's per-UAV outcomes")
    evaluation.set_defaults(handler=cmd_eval)

    table = commands.add_parser("table", help="Table I: 4 jammer settings x 3 methods")
    _add_scenario(table)
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

    figures = commands.add_parser("figures", help="the paper's Fig. 2a, 2b and 3 from real runs")
    _add_scenario(figures)
    figures.add_argument("--out", default="results", metavar="DIR",
                         help="where the PNGs go (default: results, the shipped ones)")
    figures.add_argument("--seed", type=int, default=0, help="default 0")
    figures.add_argument("--train-log", default=str(VALUE_NET.with_name("train_log.csv")),
                         help="training log for Fig. 2a (default: the shipped model's)")
    figures.add_argument("--model", default=None,
                         help=f"{VALUE_NET_HELP}, flown in Fig. 3")
    figures.set_defaults(handler=cmd_figures)

    training = commands.add_parser("train", help="train the value network (Algorithm 1)")
    _add_scenario(training)
    training.add_argument("--episodes", type=int, default=20000,
                          help="TD-learning episodes in all, resumed ones included "
                               "(default 20000)")
    training.add_argument("--envs", type=int, default=64,
                          help="environments flown at once (default 64, at most 4096; more "
                               "than --episodes adds nothing)")
    training.add_argument("--uavs", type=int, default=None, help="UAVs per episode")
    training.add_argument("--seed", type=int, default=0)
    training.add_argument("--out", default="runs/train", metavar="DIR",
                          help="where the network, its card, the log and the checkpoint go "
                               "(default runs/train)")
    training.add_argument("--resume", action="store_true",
                          help="continue the run in DIR/checkpoint, with the settings it was "
                               "made with and more --episodes")
    training.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    training.add_argument(
        "--method", choices=("paper", "extended"), default="paper",
        help="paper: the paper's joint state; extended: adds disconnection memory and the "
             "route distance over the map, and penalizes a lost mission",
    )
    training.set_defaults(handler=cmd_train)

    fit = commands.add_parser("fit-sinr", help="train a SINR map from simulated measurements")
    _add_scenario(fit)
    _add_jammer(fit)
    fit.add_argument("--samples", type=int, default=30000,
                     help="simulated measurements, uniform over the area")
    fit.add_argument("--steps", type=int, default=10000, help="mini-batches of 200")
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("--out", required=True, metavar="FILE.safetensors")
    fit.set_defaults(handler=cmd_fit_sinr)

    online = commands.add_parser(
        "online-map", help="accuracy of the online SINR map across jammer changes (Fig. 2b)"
    )
    _add_scenario(online)
    online.add_argument("--model", default=str(SINR_MAP_NO_JAMMER), metavar="PATH",
                        help="the initial map (default: models/sinr_map_no_jammer.safetensors)")
    online.add_argument("--uavs", type=int, default=None,
                        help="UAVs reporting along their paths (default 20)")
    online.add_argument("--period", type=float, default=120.0,
                        help="simulated seconds per jammer setting (default 120; from two "
                             f"steps to {MAX_ONLINE_PERIOD_S:g})")
    online.add_argument("--seed", type=int, default=0)
    online.add_argument("--out", required=True, metavar="FILE.png")
    online.set_defaults(handler=cmd_online_map)

    latency = commands.add_parser(
        "cloud-latency", help="success on the online map against the cloud's latency, the "
                              "jammer moving (figure, table)")
    _add_scenario(latency)
    _add_jammer(latency)
    latency.add_argument("--latencies", default="0,1,2,5,10,30,60", metavar="S,S,...",
                         help="cloud latencies to fly, seconds of flight (default "
                              "0,1,2,5,10,30,60)")
    latency.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    latency.add_argument("--episodes", type=int, default=200,
                         help="episodes per seed and latency (default 200)")
    latency.add_argument("--swap-every", type=int, default=10, metavar="K",
                         help="move the jammer to a fresh random setting every K episodes "
                              "(default 10)")
    latency.add_argument("--uavs", type=int, default=None, help="UAVs per episode")
    latency.add_argument("--out", default="results", metavar="DIR",
                         help="where cloud_latency_<scenario>.{json,md,png} go (default: "
                              "results)")
    latency.set_defaults(handler=cmd_cloud_latency)

    soak = commands.add_parser(
        "chaos", help="run the system while killing and freezing its processes, then check "
                      "that nothing was lost")
    _add_scenario(soak)
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
    soak.set_defaults(handler=_guarded(cmd_chaos))
    register_runtime(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except (UsageError, ScenarioError, PlannerError) as exc:
        print(f"jamnav: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jamnav: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader went away (`jamnav sinr ... | head -1`): nothing is wrong. stdout now
        # goes nowhere, so that the interpreter's last flush does not fail again; the exit
        # status is a shell's for a writer a closed pipe stopped.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE


if __name__ == "__main__":
    sys.exit(main())
