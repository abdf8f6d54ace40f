"""The cloud's replay memory: how fast it stores uploads. One CPU thread.

(How fast the online map adapts to a jammer change is ``bench_adaptation``.)
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import Figure, best_rate
from cloud_service.simulated_measurements import simulated_measurements
from cloud_service.sinr_memory import SinrMemory
from shared.measurements import MeasurementSpec
from shared.scenario import Scenario, load_scenario


def run() -> list[Figure]:
    return _append_rates(load_scenario())


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
