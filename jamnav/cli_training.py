"""``jamnav train`` and ``jamnav fit-sinr``: the commands that train the networks, the value
network of Algorithm 1 and a SINR map from simulated measurements."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from jamnav.arguments import (
    UsageError,
    add_jammer,
    add_scenario,
    check_range,
    output_path,
    scenario_argument,
    scenario_with_jammer,
)
from shared.radio import RadioModel
from shared.scenario import SEED_MAX, Scenario

if TYPE_CHECKING:  # the training module imports torch: only where a command trains
    from cloud_service.training_config import TrainConfig


def one_torch_thread() -> None:
    """The SINR network is tiny (batches of 200 through 32 units): a second thread only adds
    hand-offs, and on a 2-core machine makes training several times slower."""
    import torch

    torch.set_num_threads(1)


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


def _final_rate(text: str | None, method: str) -> float | None:
    """--final-lr as TrainConfig takes it: a rate, None for the constant rate, or the
    method's default when not given."""
    from cloud_service.training_config import DEFAULT_FINAL_LEARNING_RATE, TrainConfig

    if text is None:
        return DEFAULT_FINAL_LEARNING_RATE[method]
    if text == "constant":
        return None
    try:
        rate = float(text)
    except ValueError:
        rate = math.nan
    if not 0 < rate <= TrainConfig.learning_rate:
        raise UsageError(f"--final-lr {text}: expected 'constant' or a rate above 0 and at "
                         f"most the starting rate, {TrainConfig.learning_rate:g}")
    return rate


def cmd_train(args: argparse.Namespace) -> int:
    from cloud_service.training_config import MAX_ENVS, TrainConfig
    from cloud_service.value_training import train
    from jamnav.progress import ProgressBar

    scenario = scenario_argument(args)
    check_range("--episodes", args.episodes, 1)
    check_range("--envs", args.envs, 1, MAX_ENVS)
    check_range("--uavs", args.uavs, 1, 64)
    check_range("--seed", args.seed, 0, SEED_MAX)
    _check_device(args.device)
    out = output_path("--out", args.out, directory=True)
    config = TrainConfig(episodes=args.episodes, envs=args.envs, uavs=args.uavs,
                         seed=args.seed, device=args.device, method=args.method,
                         final_learning_rate=_final_rate(args.final_lr, args.method))
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


def cmd_fit_sinr(args: argparse.Namespace) -> int:
    from cloud_service.sinr_training import fit_sinr_map
    from cloud_service.value_training import git_commit
    from jamnav.progress import ProgressBar
    from planning.networks import save_network

    one_torch_thread()
    scenario = scenario_with_jammer(args)
    flown = scenario.flown_jammers
    if len(flown) > 1 or any(not jammer.still for jammer in flown):
        flies = "several jammers" if len(flown) > 1 else "a jammer that moves or switches"
        raise UsageError(f"fit-sinr learns the map of one still jammer, and scenario "
                         f"{scenario.name} flies {flies}: name one with --jammer X,Y,P (or "
                         "--no-jammer)")
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


# -- parsers ------------------------------------------------------------------------------------
def add_train_command(commands) -> None:
    training = commands.add_parser("train", help="train the value network (Algorithm 1)")
    add_scenario(training)
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
    training.add_argument("--final-lr", default=None, metavar="RATE",
                          help="let the learning rate fall along half a cosine to RATE by the "
                               "run's end, or keep it at the paper's 0.001 ('constant'); "
                               "default: 1e-5 for the extended method, constant for the "
                               "paper's")
    training.add_argument(
        "--method", choices=("paper", "extended"), default="paper",
        help="paper: the paper's joint state; extended: adds disconnection memory and the "
             "route distance over the map, and penalizes a lost mission",
    )
    training.set_defaults(handler=cmd_train)


def add_fit_sinr_command(commands) -> None:
    fit = commands.add_parser("fit-sinr", help="train a SINR map from simulated measurements")
    add_scenario(fit)
    add_jammer(fit)
    fit.add_argument("--samples", type=int, default=30000,
                     help="simulated measurements, uniform over the area")
    fit.add_argument("--steps", type=int, default=10000, help="mini-batches of 200")
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("--out", required=True, metavar="FILE.safetensors")
    fit.set_defaults(handler=cmd_fit_sinr)
