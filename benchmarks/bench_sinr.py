"""Online SINR map: accuracy after retraining, detection latency, time to new weights, false
detections with a still jammer, replay-memory append rate. One CPU thread.

Uploads come from ``online_map_sim.Fleet``: 100 UAVs, one measurement each per 1 s step, so
the detector's window of 200 is two steps and a retraining's 4,000 measurements are 40 s of
uploads. The simulation replays those uploads as fast as the mapper takes them; wall-clock
figures are therefore compute time, and the simulated time the fleet needs to deliver the data
is reported beside them (no target).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import Figure, best_rate
from cloud_service.online_map_sim import Fleet, jammer_params
from cloud_service.sinr_mapping import (
    TARGET_ACCURACY,
    OnlineSinrMapper,
    accuracy_of,
    fit_sinr_map,
    simulated_measurements,
)
from cloud_service.sinr_memory import SinrMemory
from shared.measurements import MeasurementSpec
from shared.networks import SinrMapNetwork
from shared.paper import TABLE_I_JAMMERS, JammerSetting
from shared.scenario import Scenario, load_scenario

UAVS = 100
STILL_SECONDS = 600  # "10 minutes of simulated uploads with a still jammer"
LATENCY_SEEDS = 3


def run() -> list[Figure]:
    return measure(load_scenario())


def measure(scenario: Scenario, seed: int = 0) -> list[Figure]:
    network, card = fit_sinr_map(scenario, None, 30_000, 10_000, seed)
    baseline = card["accuracy"]
    figures = []
    latencies, to_weights, to_weights_sim, false_alarms = [], [], [], 0
    for index, setting in enumerate(TABLE_I_JAMMERS):
        result = _change_and_still(scenario, network, baseline, setting, seed + index)
        figures.append(Figure(f"SINR map accuracy after retraining, jammer {setting.label}",
                              100 * result["accuracy"], "%", 100 * TARGET_ACCURACY))
        to_weights.append(result["to_weights_wall"])
        to_weights_sim.append(result["to_weights_sim"])
        false_alarms += result["false_alarms"]
        for trial in range(LATENCY_SEEDS):
            for offset in (0, 1):  # change on a window boundary, or inside a window
                latencies.append(_detection_latency(scenario, network, baseline, setting,
                                                    1000 * seed + 10 * trial + offset, offset))
    false_alarms += _still_detections(scenario, network, baseline, None, seed)
    figures += [
        Figure(f"detection latency after first post-change window, max of {len(latencies)}",
               1000 * max(latencies), "ms", 250, lower_is_better=True),
        Figure("change -> new weights published, compute (wall), max of 4", 1000 * max(to_weights),
               "ms", 3000, lower_is_better=True),
        Figure(f"change -> new weights, simulated time ({UAVS} UAVs uploading 1/s), max of 4",
               max(to_weights_sim), "s"),
        Figure(f"false detections, still jammer, 5 maps x {STILL_SECONDS // 60} min of uploads",
               false_alarms, "count", 0, lower_is_better=True),
    ]
    figures += _append_rates(scenario)
    return figures


def _mapper(scenario: Scenario, network: SinrMapNetwork, baseline: float, now: list[float],
            published: list[float], seed: int) -> OnlineSinrMapper:
    memory = SinrMemory(":memory:", MeasurementSpec.of(scenario))
    return OnlineSinrMapper(scenario, memory, network, baseline, clock=lambda: now[0],
                            publish=lambda _: published.append(time.perf_counter()),
                            background=True, seed=seed)


def _change_and_still(scenario: Scenario, network: SinrMapNetwork, baseline: float,
                      setting: JammerSetting, seed: int) -> dict:
    """No jammer for 11 steps, then ``setting`` until new weights are out and for
    STILL_SECONDS after that."""
    now, published = [0.0], []
    mapper = _mapper(scenario, network, baseline, now, published, seed)
    fleet = Fleet(scenario, UAVS, np.random.default_rng(seed))
    dt, change_step = scenario.timing.step_s, 11
    jammer = jammer_params(scenario, setting)
    changed_at = None
    for step in range(change_step + int(STILL_SECONDS / dt)):
        now[0] = step * dt
        fleet.fly()
        if step == change_step:
            changed_at = time.perf_counter()
        mapper.ingest(fleet.uploads(jammer if step >= change_step else None, now[0], step))
        mapper.wait()
        if published:
            break
    fresh = simulated_measurements(scenario, jammer, 20_000, np.random.default_rng(seed + 99))
    accuracy = accuracy_of(mapper.current_network(), fresh.features, fresh.levels)
    if not published:  # never retrained: the figures say so instead of stopping the run
        mapper.close()
        return {"accuracy": accuracy, "to_weights_wall": float("inf"),
                "to_weights_sim": float("inf"), "false_alarms": 0}
    publication = mapper.events[-1]
    detections = len(mapper.events)
    for still_step in range(step + 1, step + 1 + int(STILL_SECONDS / dt)):
        now[0] = still_step * dt
        fleet.fly()
        mapper.ingest(fleet.uploads(jammer, now[0], still_step))
    mapper.close()
    return {
        "accuracy": accuracy,
        "to_weights_wall": published[0] - changed_at,
        "to_weights_sim": publication["t"] - change_step * dt,
        "false_alarms": sum(e["type"] == "change_detected" for e in mapper.events[detections:]),
    }


def _still_detections(scenario: Scenario, network: SinrMapNetwork, baseline: float,
                      setting: JammerSetting | None, seed: int) -> int:
    now = [0.0]
    mapper = _mapper(scenario, network, baseline, now, [], seed)
    fleet = Fleet(scenario, UAVS, np.random.default_rng(seed + 7))
    jammer = jammer_params(scenario, setting)
    for step in range(int(STILL_SECONDS / scenario.timing.step_s)):
        now[0] = step * scenario.timing.step_s
        fleet.fly()
        mapper.ingest(fleet.uploads(jammer, now[0], step))
    mapper.close()
    return sum(e["type"] == "change_detected" for e in mapper.events)


def _detection_latency(scenario: Scenario, network: SinrMapNetwork, baseline: float,
                       setting: JammerSetting, seed: int, offset: int) -> float:
    """Seconds from the moment the first complete post-change window is in to the detection:
    the wall time of the ingest call that detects, plus the simulated time of any further
    windows the detector needed (none when it fires on that window or the one before)."""
    now = [0.0]
    mapper = _mapper(scenario, network, baseline, now, [], seed)
    fleet = Fleet(scenario, UAVS, np.random.default_rng(seed))
    dt, change_step = scenario.timing.step_s, 10 + offset
    jammer = jammer_params(scenario, setting)
    first_full_end = None
    for step in range(change_step + 20):
        now[0] = step * dt
        fleet.fly()
        uploads = fleet.uploads(jammer if step >= change_step else None, now[0], step)
        started = time.perf_counter()
        report = mapper.ingest(uploads)
        spent = time.perf_counter() - started
        for check in report.windows:
            if first_full_end is None and check.start >= change_step * dt:
                first_full_end = check.end
        if report.windows and report.windows[-1].fired:
            waited = 0.0 if first_full_end is None else report.windows[-1].end - first_full_end
            mapper.close()
            return spent + waited
    mapper.close()
    return float("inf")


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
