"""How many jammers the cloud counts, and where it places each, from the uploads of four UAVs
flying for 20 s after the jammers appeared: 40 seeded settings, ten each of 0, 1, 2 and 3
jammers, each anywhere in the area at a power of the scenario's training range. The estimate
reads the shipped survey map, as the cloud does (``estimate_jammers``); uploads come from
``online_map_sim.Fleet``. In the idealized world with level reports, and in the shadowed world
with dB reports; then the idealized world again after 120 s, to show what longer flights
bring.

Then what the same 20 s and 120 s of the idealized world hold for any search: in how many
settings every jammer changes the level of some report (with it and without it, the others
there), and in how many the estimator's likelihood would count right were the search
perfect: each jammer, the others given where they are, explains the uploads by more than the
rule asks (``PRESENCE_LLR`` alone, BIC's penalty beside others), and one more, all of them
given, does not; at the report spread the decision reads (1.2 dB) and at the sharpest the
estimate is refitted with (0.3 dB). Last, the rule's counts in the idealized world when it
decides at 0.3 dB."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure
from cloud_service.jammer_estimation import (
    PRESENCE_LLR,
    REPORT_SIGMA_CHOICES_DB,
    estimate_jammers,
    one_more_evidence,
)
from cloud_service.online_map_sim import Fleet
from cloud_service.report_likelihood import REPORT_SIGMA_DB
from cloud_service.upload_positions import positions_from_features
from planning.networks import load_network, predict_probabilities
from shared.measurements import MeasurementBatch
from shared.paper import jammer_params
from shared.radio import JammerParams, RadioModel
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
    sharpest_db = REPORT_SIGMA_CHOICES_DB[0]
    return (count_figures(idealized, FLIGHT_S) + count_figures(reporting, FLIGHT_S)
            + count_figures(idealized, LONGER_FLIGHT_S)
            + evidence_figures(idealized, FLIGHT_S) + evidence_figures(idealized, LONGER_FLIGHT_S)
            + count_figures(idealized, FLIGHT_S, sharpest_db)
            + count_figures(idealized, LONGER_FLIGHT_S, sharpest_db))


def count_figures(scenario: Scenario, flight_s: float,
                  report_sigma_db: float = REPORT_SIGMA_DB) -> list[Figure]:
    """The rule's counts, deciding at ``report_sigma_db``."""
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    right, undecided, errors = 0, 0, []
    by_count = np.zeros((MOST_JAMMERS + 1, 3), dtype=int)  # truth x (right, wrong, undecided)
    for k in range(SETTINGS):
        count = k % (MOST_JAMMERS + 1)
        jammers, found = _trial(scenario, survey, k, count, flight_s, report_sigma_db)
        if found is None:
            undecided += 1
            by_count[count, 2] += 1
            continue
        hit = len(found) == count
        right += hit
        by_count[count, 0 if hit else 1] += 1
        errors += [min(np.hypot(e.x - j.x, e.y - j.y) for e in found) for j in jammers] if hit \
            else []
    name = f"{scenario.name}, jammers counted from {flight_s:.0f} s of {UAVS} UAVs" + (
        "" if report_sigma_db == REPORT_SIGMA_DB else f" at {report_sigma_db:g} dB")
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


def evidence_figures(scenario: Scenario, flight_s: float) -> list[Figure]:
    """What the uploads of each setting hold, for any search and for the estimator's
    likelihood searched perfectly (the module's docstring)."""
    radio = RadioModel(scenario)
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    spreads = (REPORT_SIGMA_DB, REPORT_SIGMA_CHOICES_DB[0])
    visible, countable = 0, dict.fromkeys(spreads, 0)
    for k in range(SETTINGS):
        jammers, data = _uploads(scenario, k, k % (MOST_JAMMERS + 1), flight_s)
        xy = positions_from_features(scenario, data.features)
        levels = radio.evaluate(xy, jammers).level
        visible += all((radio.evaluate(xy, _others(jammers, i)).level != levels).any()
                       for i in range(len(jammers)))
        no_jammer_levels = predict_probabilities(survey, data.features)
        for spread in spreads:
            countable[spread] += _counted_by_perfect_search(
                scenario, xy, data.levels, no_jammer_levels, jammers, spread)
    name = f"{scenario.name}, {flight_s:.0f} s of {UAVS} UAVs"
    return [Figure(f"{name}: settings where each jammer changes a report's level", visible,
                   f"of {SETTINGS}")] + [
        Figure(f"{name}: settings a perfect search would count right at {spread:g} dB",
               count, f"of {SETTINGS}") for spread, count in countable.items()]


def _counted_by_perfect_search(scenario: Scenario, xy: np.ndarray, levels: np.ndarray,
                               no_jammer_levels: np.ndarray, jammers: list[JammerParams],
                               spread: float) -> bool:
    """Whether the estimator's likelihood at ``spread`` counts ``jammers`` right, were its
    search perfect: each one counted with the others known, and no one more."""
    def counted(known: list[JammerParams]) -> bool:
        llr, penalty = one_more_evidence(
            scenario, xy, levels, [_placed(scenario, jammer) for jammer in known],
            no_jammer_levels=no_jammer_levels, report_sigma_db=spread)
        return llr > (penalty if known else PRESENCE_LLR)

    return (all(counted(_others(jammers, index)) for index in range(len(jammers)))
            and not counted(jammers))


def _others(jammers: list[JammerParams], index: int) -> list[JammerParams]:
    return jammers[:index] + jammers[index + 1:]


def _placed(scenario: Scenario, jammer: JammerParams) -> tuple[np.ndarray, float]:
    """A jammer as the estimator takes one as known: its position and effective power (dBW)."""
    return (np.array([jammer.x, jammer.y]),
            10.0 * np.log10(jammer.power_w) + scenario.jammer.efficiency_db)


def _uploads(scenario: Scenario, seed: int, count: int, flight_s: float):
    """Setting ``seed``'s ``count`` jammers and the uploads of ``flight_s`` of the fleet."""
    rng = np.random.default_rng([seed, 0x40])
    jammers = [jammer_params(scenario, random_jammer(scenario, rng)) for _ in range(count)]
    fleet = Fleet(scenario, UAVS, rng)
    dt = scenario.timing.step_s
    batches = []
    for step in range(int(flight_s / dt)):
        fleet.fly()
        batches.append(fleet.uploads(jammers, step * dt, step))
    return jammers, MeasurementBatch.concatenate(batches)


def _trial(scenario: Scenario, survey, seed: int, count: int, flight_s: float,
           report_sigma_db: float):
    jammers, data = _uploads(scenario, seed, count, flight_s)
    found = estimate_jammers(scenario, positions_from_features(scenario, data.features),
                             data.levels, reported_db=data.sinr_db,
                             no_jammer_levels=predict_probabilities(survey, data.features),
                             report_sigma_db=report_sigma_db)
    return jammers, found
