"""The ``jamnav`` command line: the parser of every sub-command and ``main``, which runs the one
asked for. Each sub-command parses, calls core code, and prints; the commands live by group in
``cli_radio`` (the radio world), ``cli_experiments`` (the paper's experiments in-process),
``cli_training`` (training the networks), ``cli_up`` (the whole system) and ``cli_runtime``
(a running system).

Errors a user can cause (bad arguments, bad files) end with one line on stderr and exit code 2,
never a traceback.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Sequence

from jamnav import cli_experiments, cli_radio, cli_runtime, cli_training, cli_up
from jamnav.arguments import UsageError
from planning import PlannerError
from shared.scenario import ScenarioError
from shared.topics import ArgumentParser

# Each adds one sub-command, in the order `jamnav --help` lists them.
COMMANDS = (
    cli_radio.add_scenario_command,
    cli_radio.add_sinr_command,
    cli_radio.add_map_command,
    cli_experiments.add_eval_command,
    cli_experiments.add_table_command,
    cli_experiments.add_figures_command,
    cli_training.add_train_command,
    cli_training.add_fit_sinr_command,
    cli_experiments.add_online_map_command,
    cli_experiments.add_cloud_latency_command,
    cli_experiments.add_jammers_table_command,
    cli_up.add_chaos_command,
    cli_up.add_up_command,
    cli_runtime.add_console_command,
    cli_runtime.add_record_command,
    cli_runtime.add_replay_command,
    cli_runtime.add_jammer_command,
    cli_runtime.add_status_command,
    cli_runtime.add_router_command,
)


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="jamnav", description="Jamming-resilient path planning for many UAVs."
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add_command in COMMANDS:
        add_command(commands)
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
