"""Measurements as a UAV's receiver reports them (the world's truth, noise included), for the
command line, the benchmarks and the tests: the uploads the cloud's SINR map learns from."""

from __future__ import annotations

import numpy as np

from planning.measuring import scenario_features
from shared.measurements import MeasurementBatch
from shared.radio import JammerParams, RadioModel
from shared.scenario import Scenario


def simulated_measurements(
    scenario: Scenario,
    jammer: JammerParams | None,
    count: int,
    rng: np.random.Generator,
    *,
    time: float = 0.0,
    step: int = 0,
    source: str = "sim",
) -> MeasurementBatch:
    """``count`` measurements at positions uniform over the area, labelled with the level a
    UAV reports there under ``jammer``. Ids are random 64-bit numbers drawn from ``rng``:
    unique in practice, and the same for the same seed."""
    xy = uniform_positions(scenario, count, rng)
    return measurements_at(scenario, RadioModel(scenario), jammer, xy, rng, time=time,
                           step=step, source=source)


def uniform_positions(scenario: Scenario, count: int, rng: np.random.Generator) -> np.ndarray:
    area = scenario.area
    return rng.uniform((area.x_min, area.y_min), (area.x_max, area.y_max), size=(count, 2))


def measurements_at(
    scenario: Scenario,
    radio: RadioModel,
    jammer: JammerParams | None,
    xy: np.ndarray,
    rng: np.random.Generator,
    *,
    time: float | np.ndarray = 0.0,
    step: int | np.ndarray = 0,
    source: str | list[str] = "sim",
) -> MeasurementBatch:
    """Measurements at given positions ``xy`` (n, 2) under ``jammer``, labelled as a UAV's
    receiver reports them: the true SINR of ``radio`` (the world's, shadowed where the
    scenario says so) plus the receiver's measurement noise, drawn from ``rng``."""
    reports = radio.measured_reports(radio.evaluate(xy, jammer).sinr_db, rng)
    return labelled_batch(scenario, xy, reports.level, rng, time=time, step=step, source=source,
                          sinr_db=reports.sinr_db)


def labelled_batch(
    scenario: Scenario,
    xy: np.ndarray,
    levels: np.ndarray,
    rng: np.random.Generator,
    *,
    time: float | np.ndarray = 0.0,
    step: int | np.ndarray = 0,
    source: str | list[str] = "sim",
    sinr_db: np.ndarray | None = None,
) -> MeasurementBatch:
    """Uploads of ``levels`` (and the SINRs ``sinr_db``, if reported) reported at ``xy``, with
    ids drawn from ``rng`` (random 64-bit numbers: unique in practice, and the same for the
    same seed)."""
    ids = [f"{value:016x}" for value in rng.integers(0, 2**63, size=len(xy)).tolist()]
    return MeasurementBatch.of_arrays(ids, source, step, time, scenario_features(scenario, xy),
                                      levels, sinr_db)
