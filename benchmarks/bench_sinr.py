"""The cloud's replay memory: how fast it stores uploads, and how long a restarted cloud
takes to rebuild its no-jammer reference from it. One CPU thread.

(How fast the online map adapts to a jammer change is ``bench_adaptation``.)
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import Figure, best_rate
from cloud_service.simulated_measurements import simulated_measurements
from cloud_service.sinr_mapping import OnlineSinrMapper
from cloud_service.sinr_memory import SinrMemory
from cloud_service.upload_positions import positions_from_features
from planning.networks import load_network
from shared.measurements import MeasurementSpec
from shared.scenario import Scenario, load_scenario
from shared.survey_maps import sinr_map_for

REBUILT_REPORTS = 200_000  # twice the paper's replay capacity


def run() -> list[Figure]:
    return _append_rates(load_scenario()) + _restart_times(load_scenario())


def _append_rates(scenario: Scenario) -> list[Figure]:
    """Batches of 100 into a file-backed memory (WAL): as records off the wire (dicts, checked
    by the pydantic model) and as arrays (the simulation's path)."""
    spec = MeasurementSpec.of(scenario)
    rng = np.random.default_rng(0)
    batch = simulated_measurements(scenario, None, 100, rng)
    records = [record.model_dump() for record in batch.records()]
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        memory = SinrMemory(Path(tmp) / "records.sqlite", spec)
        counter = [0]

        def append_records() -> int:
            counter[0] += 1
            for i, record in enumerate(records):
                record["id"] = f"r{counter[0]}-{i}"
            return memory.append(records)[0]

        figures.append(Figure("replay memory append, records in batches of 100",
                              best_rate(append_records, repeats=3, min_seconds=1.0),
                              "meas/s", 20_000))
        memory.close()
        memory = SinrMemory(Path(tmp) / "arrays.sqlite", spec)

        def append_arrays() -> int:
            counter[0] += 1
            ids = [f"a{counter[0]}-{i}" for i in range(len(batch))]
            return memory.append(dataclasses.replace(batch, ids=ids))[0]

        figures.append(Figure("replay memory append, arrays in batches of 100",
                              best_rate(append_arrays, repeats=3, min_seconds=1.0), "meas/s",
                              20_000))
        memory.close()
    return figures


def _restart_times(scenario: Scenario) -> list[Figure]:
    """Seconds a mapper takes to start over a memory of ``REBUILT_REPORTS`` dB reports, its
    no-jammer reference rebuilt from them, beside its start over an empty memory: the
    difference is the rebuild (best of three). And the part of it that finds where each
    report was taken (``positions_from_features``), once: a chunk of the memory's reads at a
    time, as the rebuild does, and all in one call."""
    reporting = scenario.changed({"uav.report": "db"})
    spec = MeasurementSpec.of(reporting)
    network, card = load_network(sinr_map_for(scenario))
    batch = REBUILT_REPORTS // 20
    with tempfile.TemporaryDirectory() as tmp:
        full = SinrMemory(Path(tmp) / "full.sqlite", spec, capacity=REBUILT_REPORTS)
        for k in range(20):
            full.append(simulated_measurements(reporting, None, batch, np.random.default_rng(k),
                                               time=float(k * batch)))
        empty = SinrMemory(Path(tmp) / "empty.sqlite", spec)

        def start(memory: SinrMemory) -> float:
            begun = time.perf_counter()
            OnlineSinrMapper(reporting, memory, network, card["accuracy"], background=False)
            return time.perf_counter() - begun

        figures = [Figure(f"mapper start, {name}", min(start(memory) for _ in range(3)), "s",
                          lower_is_better=True)
                   for name, memory in ((f"reference rebuilt from {REBUILT_REPORTS:,} dB reports",
                                         full), ("empty memory", empty))]
        chunks = [reports.features for reports in full.db_reports()]
        for name, parts in (("a chunk at a time", chunks),
                            ("in one call", [np.concatenate(chunks)])):
            begun = time.perf_counter()
            for features in parts:
                positions_from_features(reporting, features)
            figures.append(Figure(f"places of {REBUILT_REPORTS:,} reports, {name}",
                                  time.perf_counter() - begun, "s", lower_is_better=True))
        full.close()
        empty.close()
    return figures
