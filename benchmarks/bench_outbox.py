"""The agents' outbox: what appending a measurement costs the flight loop, in memory and
durable (a file per UAV, as ``jamnav up`` gives its agents), and the agents' decision time in
``jamnav up`` runs with either."""

from __future__ import annotations

import io
import logging
import socket
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import Figure, best_rate
from jamnav.supervisor import Supervisor, UpConfig
from shared.measurements import FEATURES_DTYPE, scenario_features
from shared.scenario import load_scenario
from uav_agent.uploads import DEFAULT_BATCH, DEFAULT_CAPACITY, Outbox, open_outbox

ROUNDS = 2  # runs of each outbox, alternated; each figure keeps its better run
EPISODES = 30
APPEND_TARGET_US = 10  # a step's 10 reports then cost a tenth of the 1 ms decision target


def _append_rate(outbox: Outbox, step: list[tuple]) -> float:
    """Measurements per second through ``outbox``: a step's reports at a time, as the flight
    loop adds them, and a receipt for everything after every 64 steps, as the sender's."""
    def work() -> int:
        for _ in range(64):
            outbox.add(step, DEFAULT_BATCH)
        outbox.acknowledge(outbox.ledger.taken - 1)
        outbox.tidy()
        return 64 * len(step)

    return best_rate(work)


def _up(run_dir: Path, durable: bool) -> dict:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{probe.getsockname()[1]}"
    config = UpConfig(endpoint=endpoint, run_dir=run_dir, uavs=4, episodes=EPISODES,
                      map="perfect", figures=False, durable_outboxes=durable)
    return Supervisor(config, load_scenario(), stream=io.StringIO()).run()


def run() -> list[Figure]:
    scenario = load_scenario()
    positions = np.random.default_rng(0).uniform(-40, 40, (scenario.uav.measurements_per_step, 2))
    features = scenario_features(scenario, positions).astype(FEATURES_DTYPE, copy=False)
    step = [(f"3-0123abcd-{1_000_000 + i}", "uav-3", 120, 1.8e9, row.tobytes(), 1)
            for i, row in enumerate(features)]
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, directory in (("memory", None), ("durable", Path(tmp))):
            outbox = open_outbox(DEFAULT_CAPACITY, directory, 3, logging.getLogger("bench"))
            figures.append(Figure(f"outbox append per measurement, {label}",
                                  1e6 / _append_rate(outbox, step), "us", APPEND_TARGET_US,
                                  True))
            outbox.close()
        reports: dict[str, list[dict]] = {"memory": [], "durable": []}
        for attempt in range(ROUNDS):
            for label, runs in reports.items():
                runs.append(_up(Path(tmp) / f"{label}{attempt}", label == "durable"))
    for label, runs in reports.items():
        wall, cpu = (min(_worst_agent(report, key) for report in runs)
                     for key in ("decision_p99_us", "decision_cpu_p99_us"))
        figures += [
            Figure(f"agent decision p99, 4 agents, {label} outbox (wall, worst agent)",
                   wall, "us", 1000, True),
            Figure(f"agent decision p99, 4 agents, {label} outbox (CPU, worst agent)",
                   cpu, "us", 1000, True),
            Figure(f"lockstep steps/s, 4 agent processes, {label} outbox",
                   max(report["steps_per_second"] for report in runs), "steps/s", 200)]
    return figures


def _worst_agent(report: dict, key: str) -> float:
    return max(agent[key] for agent in report["agents"].values())
