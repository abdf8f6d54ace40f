"""What a step's reports cost an agent on board (the spot filter and the features, compiled
beside their numpy reference), and the agents' outbox: what appending a measurement costs the
flight loop, in memory and
durable (a file per UAV, as ``jamnav up`` gives its agents), and the agents' decision time in
``jamnav up`` runs with either. And what an upload costs per measurement: the agent's encoding,
the cloud's decoding, and its storing, one upload or four to a transaction."""

from __future__ import annotations

import io
import logging
import socket
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import Figure, best_rate, planner_chosen
from cloud_service.sinr_memory import SinrMemory
from jamnav.supervisor import Supervisor, UpConfig
from planning.measuring import SpotFilter, scenario_features
from shared.cloud_messages import MeasurementUpload, encode_upload
from shared.measurements import FEATURES_DTYPE, MeasurementSpec
from shared.scenario import Scenario, load_scenario
from shared.wire import decode
from uav_agent.uploads import DEFAULT_BATCH, DEFAULT_CAPACITY, Outbox, open_outbox

ROUNDS = 2  # runs of each outbox (and of the upload figures), alternated; each figure keeps
# its better run
EPISODES = 30
UPLOADS = 200  # uploads timed per figure: 12,800 measurements
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


def upload_figures(scenario: Scenario, directory: Path) -> list[Figure]:
    """Per measurement, over UPLOADS uploads of DEFAULT_BATCH new measurements: the agent's
    encoding, the cloud's decoding, and its storing, one upload or four to a transaction
    (best of ROUNDS, on fresh memories)."""
    rng = np.random.default_rng(1)
    features = scenario_features(scenario, rng.uniform(-40, 40, (DEFAULT_BATCH, 2))).astype(
        FEATURES_DTYPE, copy=False)
    uploads = [[(f"3-0123abcd-{n * DEFAULT_BATCH + i}", "uav-3", 120, 1.8e9, row.tobytes(), 1,
                 None) for i, row in enumerate(features)] for n in range(UPLOADS)]
    spec = MeasurementSpec.of(scenario)
    best: dict[str, float] = {}
    for attempt in range(ROUNDS):
        started = time.perf_counter()
        payloads = [encode_upload(3, "uav-3", records) for records in uploads]
        encoded = time.perf_counter()
        batches = [decode(MeasurementUpload, payload).batch() for payload in payloads]
        decoded = time.perf_counter()
        seconds = {"the agent encodes": encoded - started, "the cloud decodes": decoded - encoded}
        for together in (1, 4):
            with SinrMemory(directory / f"memory-{attempt}-{together}.sqlite", spec) as memory:
                started = time.perf_counter()
                for first in range(0, UPLOADS, together):
                    memory.store_each(batches[first:first + together])
                seconds[f"the cloud stores, {together} upload{'s' * (together > 1)} a "
                        "transaction"] = time.perf_counter() - started
        for what, elapsed in seconds.items():
            best[what] = min(best.get(what, np.inf), elapsed / (UPLOADS * DEFAULT_BATCH))
    return [Figure(f"upload of {DEFAULT_BATCH}: {what}, per measurement", value * 1e6, "us")
            for what, value in best.items()]


def on_board_figures(scenario: Scenario) -> list[Figure]:
    """A step's reports as an agent takes them: the spot filter's choice and the features of
    those kept, for one UAV flying a straight line (every report kept), under each planner,
    and the reference's time over the compiled core's, measured in turn."""
    reports = scenario.uav.measurements_per_step
    rng = np.random.default_rng(2)
    start = rng.uniform(-40, 40, 2)
    along = start + np.linspace(0.0, 3.0, reports)[:, None] * np.array([0.6, 0.8])
    levels = np.full((1, reports), 2, dtype=np.int64)
    uav = np.zeros(1, dtype=np.int64)
    spots = SpotFilter(scenario, 1)

    def step() -> int:
        spots.last_xy[:] = np.inf  # as far from the last kept report as can be
        kept = spots.keep(uav, along[None], levels)[0]
        scenario_features(scenario, along[kept])
        return 1

    per_step = {}
    for planner in ("reference", "compiled"):
        with planner_chosen(planner):
            per_step[planner] = 1e6 / best_rate(step)
    return [Figure(f"a step's {reports} reports on board ({scenario.name}): spot filter and "
                   f"features, {planner}", seconds, "us") for planner, seconds in per_step.items()
            ] + [Figure(f"a step's reports on board ({scenario.name}): reference / compiled",
                        per_step["reference"] / per_step["compiled"], "x")]


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
    figures = on_board_figures(scenario) + on_board_figures(load_scenario("city"))
    with tempfile.TemporaryDirectory() as tmp:
        figures += upload_figures(scenario, Path(tmp))
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
