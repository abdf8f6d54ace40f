"""The fixed validation every training checkpoint is scored on: each of Table I's jammer
settings flown greedily on the true map over the same seeded episodes, for every model. Where
the machine has a second core, a helper process flies half of the settings while the run's own
process flies the rest: the outcomes are the same wherever an episode flies."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing import get_context
from typing import Any

import numpy as np

from cloud_service.rollout import LookaheadController, outcome_rates, perfect_maps, run_episodes
from planning.chosen import lookahead_policy
from planning.compiled import planner_threads
from planning.networks import ValueNetwork, build_network
from planning.reference import PUBLISHED_LOOKAHEAD
from shared.paper import TABLE_I_JAMMERS, JammerSetting
from shared.scenario import Scenario

VALIDATION_SEED = 20210614  # fixed: every model is scored on the same episodes


def validate(scenario: Scenario, net: ValueNetwork, episodes: int, uavs: int,
             helper: Executor | None = None) -> dict[str, Any]:
    """Greedy lookahead on the true map, over the fixed validation episodes of each Table I
    jammer setting: the share of UAV-episodes ending in each outcome. ``helper`` (see
    ``validation_helper``) flies the second half of the settings meanwhile."""
    settings = list(TABLE_I_JAMMERS)
    mine = settings if helper is None else settings[: len(settings) // 2]
    theirs = [helper.submit(setting_outcomes, scenario, net.architecture(), net.tensors,
                            episodes, setting, uavs) for setting in settings[len(mine):]]
    outcomes = [setting_outcomes(scenario, net.architecture(), net.tensors, episodes, setting,
                                 uavs) for setting in mine]
    outcomes += [flown.result() for flown in theirs]
    rates = outcome_rates(np.concatenate(outcomes))
    return {**rates, "episodes_per_setting": episodes,
            "settings": [setting.label for setting in settings]}


def setting_outcomes(scenario: Scenario, architecture: dict[str, Any],
                     tensors: dict[str, np.ndarray], episodes: int, setting: JammerSetting,
                     uavs: int) -> np.ndarray:
    """The outcomes of one setting's validation episodes for the network of ``architecture``
    over ``tensors``, its subnormal weights read as zeros as training's lookahead reads them."""
    net = build_network(architecture, tensors).read_subnormals_as_zero()
    # The lookahead the network is trained with: selecting checkpoints by the deployed
    # planner would score the planner as much as the network.
    policy = lookahead_policy(scenario, net, **PUBLISHED_LOOKAHEAD)
    return run_episodes(scenario, LookaheadController(policy, perfect_maps(scenario)), episodes,
                        VALIDATION_SEED, setting, uavs).outcomes


@contextmanager
def validation_helper() -> Iterator[Executor | None]:
    """A helper process for a run's validations, or None on a machine of one core or where
    the planner keeps to one (``JAMNAV_PLANNER_THREADS=1``)."""
    if (os.cpu_count() or 1) < 2 or planner_threads() == 1:
        yield None
        return
    with ProcessPoolExecutor(1, mp_context=get_context("spawn"), initializer=_helping,
                             initargs=(os.getpid(),)) as helper:
        yield helper


def _helping(run_pid: int) -> None:
    """The helper leaves Ctrl-C to the run, which stops where its state is whole, and ends
    with the run, even one killed outright."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch_run() -> None:
        while os.getppid() == run_pid:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch_run, name="run-watch", daemon=True).start()
