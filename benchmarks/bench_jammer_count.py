"""How many jammers the cloud counts, and where it places each, from the uploads of four UAVs
flying for 20 s after the jammers appeared: 40 seeded settings, ten each of 0, 1, 2 and 3
jammers, each anywhere in the area at a power of the scenario's training range. The estimate
reads the shipped survey map, as the cloud does (``estimate_jammers``); uploads come from
``online_map_sim.Fleet``. In the idealized world with level reports, and in the shadowed world
with dB reports; then the idealized world again after 120 s, to show what longer flights
bring."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure
from cloud_service.jammer_estimation import estimate_jammers
from cloud_service.online_map_sim import Fleet
from cloud_service.upload_positions import positions_from_features
from planning.networks import load_network, predict_probabilities
from shared.measurements import MeasurementBatch
from shared.paper import jammer_params
from shared.scenario import Scenario, load_scenario
from shared.survey_maps import sinr_map_for
from world_sim.jammers import random_jammer

SETTINGS = 40
MOST_JAMMERS = 3  # settings cycle through 0..MOST_JAMMERS jammers
FLIGHT_S = 20.0  # the target's
LONGER_FLIGHT_S = 120.0
UAVS = 4


def run() -> list[Figure]:
    shadowed = load_scenario("icc2021-shadowed")
    reporting = shadowed.changed({"uav.report": "db"}, name="icc2021-shadowed, dB reports")
    idealized = load_scenario("icc2021")
    return (count_figures(idealized, FLIGHT_S) + count_figures(reporting, FLIGHT_S)
            + count_figures(idealized, LONGER_FLIGHT_S))


def count_figures(scenario: Scenario, flight_s: float) -> list[Figure]:
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    right, undecided, errors = 0, 0, []
    by_count = np.zeros((MOST_JAMMERS + 1, 3), dtype=int)  # truth x (right, wrong, undecided)
    for k in range(SETTINGS):
        count = k % (MOST_JAMMERS + 1)
        jammers, found = _trial(scenario, survey, k, count, flight_s)
        if found is None:
            undecided += 1
            by_count[count, 2] += 1
            continue
        hit = len(found) == count
        right += hit
        by_count[count, 0 if hit else 1] += 1
        errors += [min(np.hypot(e.x - j.x, e.y - j.y) for e in found) for j in jammers] if hit \
            else []
    name = f"{scenario.name}, jammers counted from {flight_s:.0f} s of {UAVS} UAVs"
    figures = [Figure(f"{name}: count right, of {SETTINGS} settings of 0-{MOST_JAMMERS}",
                      100.0 * right / SETTINGS, "%", 95.0 if flight_s == FLIGHT_S else None),
               Figure(f"{name}: undecided (no count yet)", 100.0 * undecided / SETTINGS, "%")]
    for count, (hit, wrong, open_) in enumerate(by_count.tolist()):
        figures += [Figure(f"{name}: {count} jammer(s), counted right", hit, "settings"),
                    Figure(f"{name}: {count} jammer(s), counted wrong", wrong, "settings"),
                    Figure(f"{name}: {count} jammer(s), undecided", open_, "settings")]
    if errors:
        figures.append(Figure(f"{name}: position error of each jammer when counted right, "
                              "median", float(np.median(errors)), "m"))
    return figures


def _trial(scenario: Scenario, survey, seed: int, count: int, flight_s: float):
    rng = np.random.default_rng([seed, 0x40])
    jammers = [jammer_params(scenario, random_jammer(scenario, rng)) for _ in range(count)]
    fleet = Fleet(scenario, UAVS, rng)
    dt = scenario.timing.step_s
    batches = []
    for step in range(int(flight_s / dt)):
        fleet.fly()
        batches.append(fleet.uploads(jammers, step * dt, step))
    data = MeasurementBatch.concatenate(batches)
    found = estimate_jammers(scenario, positions_from_features(scenario, data.features),
                             data.levels, reported_db=data.sinr_db,
                             no_jammer_levels=predict_probabilities(survey, data.features))
    return jammers, found
