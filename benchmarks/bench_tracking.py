"""How well the cloud can follow the convoy's jammer (3 m/s across the area): UAVs on random
legs (``online_map_sim.Fleet``) for the 33 s of the crossing, read with the shipped survey
map in two ways.
- Windows, as the online mapper does (``jammer_tracking.track_jammer``): each window of
  ``online_map.tracking_window_s`` estimated alone, the estimates that place the jammer
  joined by the constant-velocity filter. Four UAVs (the scenario's) and sixteen; the share
  of windows that place the jammer, and the track's error against where the jammer is at the
  end of each of those windows.
- The driving fit (``driving_jammer``): every upload since the crossing began read at once,
  at the end of each window. Four UAVs; the share of those moments it places the jammer at,
  its error there, the error of the velocity it finds, and its time; and the same for the fit
  of those uploads as if the jammer stood still (``estimate_jammer``).
- The cloud's mapper (``OnlineSinrMapper``, on the simulated clock), four UAVs, the crossing
  after 10 s of quiet: how far each estimate it publishes lies from where the jammer is when
  the map corrected for it flies (the cloud's latency on), with the cloud's tries of the
  change as a driving jammer and without them (``online_map.driving_fits``, none in the
  convoy as shipped)."""

from __future__ import annotations

import math
import time

import numpy as np

from benchmarks.common import Figure
from cloud_service.change_handling import RetrainConfig
from cloud_service.driving_jammer import estimate_driving_jammer
from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.jammer_tracking import track_jammer
from cloud_service.online_map_sim import Fleet, SimulatedClock
from cloud_service.sinr_mapping import OnlineSinrMapper
from cloud_service.sinr_memory import SinrMemory
from cloud_service.upload_positions import positions_from_features
from planning.networks import load_network, predict_probabilities
from shared.jammer_motion import position_at
from shared.measurements import MeasurementBatch, MeasurementSpec
from shared.radio import JammerParams
from shared.scenario import Scenario, load_scenario
from shared.survey_maps import sinr_map_for

CROSSING_S = 33  # the convoy's 100 m at 3 m/s
SEEDS = 6
FLEETS = (4, 16)
DRIVING_FIT_UAVS = 4  # the driving fit reads every upload at each moment: 16 would take long
TRACK_TARGET_M = 5.0  # the issue's: tracked within 5 m median while the UAVs cross its zone


QUIET_S = 10  # before the crossing, for the mapper to settle on the survey map
DRIVING_TRIES = 4  # the cloud's tries of a change as a driving jammer (the convoy ships none)


def run() -> list[Figure]:
    scenario = load_scenario("convoy")
    return [*[figure for uavs in FLEETS for figure in fleet_figures(scenario, uavs)],
            *mapper_figures(scenario)]


def mapper_figures(scenario: Scenario) -> list[Figure]:
    survey, card = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    figures = []
    for driving, changed in ((f"trying a driving jammer {DRIVING_TRIES} times",
                              scenario.changed({"online_map.driving_fits": DRIVING_TRIES})),
                             ("as shipped, without", scenario)):
        seconds = [error for seed in range(SEEDS)
                   for error in errors_in_service(changed, survey, card["accuracy"], seed)]
        placed = [error for error in seconds if error is not None]
        name = (f"convoy, {DRIVING_FIT_UAVS} UAVs, the cloud's mapper {driving}: the estimate "
                f"in service each second of the crossing")
        figures += [Figure(f"{name}: seconds with one, of {len(seconds)}",
                           100.0 * len(placed) / len(seconds), "%"),
                    Figure(f"{name}: its error then, median", median(placed), "m",
                           TRACK_TARGET_M, lower_is_better=True)]
    return figures


def errors_in_service(scenario: Scenario, survey, accuracy: float,
                      seed: int) -> list[float | None]:
    """For each second of one crossing, how far the estimate behind the map in service
    (published at least the cloud's latency before) lies from the jammer; None while the map
    in service has none."""
    clock = SimulatedClock()
    memory = SinrMemory(":memory:", MeasurementSpec.of(scenario))
    mapper = OnlineSinrMapper(scenario, memory, survey, accuracy, clock=clock,
                              background=False, seed=seed,
                              retrain=RetrainConfig(max_seconds=None))
    fleet = Fleet(scenario, DRIVING_FIT_UAVS, np.random.default_rng([seed, 7]))
    jammer = scenario.flown_jammers[0]
    for step in range(QUIET_S + CROSSING_S):
        clock.now = float(step)
        fleet.fly()
        driving = []
        if step >= QUIET_S:
            x, y = position_at(jammer, float(step - QUIET_S))
            driving = [JammerParams(x, y, jammer.power_w, jammer.height_m)]
        mapper.ingest(fleet.uploads(driving, clock.now, step))
    served = [event for event in mapper.events
              if event["type"] in ("jammer_estimated", "estimate_withdrawn")]
    latency = scenario.online_map.cloud_latency_s
    errors = []
    for step in range(QUIET_S, QUIET_S + CROSSING_S):
        latest = [event for event in served if event["t"] + latency <= step]
        if not latest or latest[-1]["type"] != "jammer_estimated" or not latest[-1]["present"]:
            errors.append(None)
            continue
        truth = position_at(jammer, float(step - QUIET_S))
        errors.append(float(np.hypot(latest[-1]["x"] - truth[0], latest[-1]["y"] - truth[1])))
    return errors


def fleet_figures(scenario: Scenario, uavs: int) -> list[Figure]:
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    jammer = scenario.flown_jammers[0]
    window_s = scenario.online_map.tracking_window_s
    windows = SEEDS * math.floor(CROSSING_S / window_s)
    track_errors, fit_errors, velocity_errors, still_errors = [], [], [], []
    seconds = {"driving": [], "still": []}
    for seed in range(SEEDS):
        fleet, batches = Fleet(scenario, uavs, np.random.default_rng([seed, 7])), []
        for step in range(CROSSING_S):
            fleet.fly()
            x, y = position_at(jammer, float(step))
            batches.append(fleet.uploads(JammerParams(x, y, jammer.power_w, jammer.height_m),
                                         float(step), step))
            if uavs == DRIVING_FIT_UAVS and (step + 1) % window_s == 0:
                driving, still = fit_errors_at(scenario, survey,
                                               MeasurementBatch.concatenate(batches), float(step),
                                               seconds)
                if driving is not None:
                    fit_errors.append(driving[0])
                    velocity_errors.append(driving[1])
                if still is not None:
                    still_errors.append(still)
        data = MeasurementBatch.concatenate(batches)
        for now in track_jammer(scenario, positions_from_features(scenario, data.features),
                                data.levels, data.times,
                                predict_probabilities(survey, data.features),
                                window_s=window_s, reported_db=data.sinr_db):
            end = now.t + window_s / 2.0  # each update sits at its window's middle
            ahead = np.array([now.x + now.vx * window_s / 2.0, now.y + now.vy * window_s / 2.0])
            track_errors.append(float(np.hypot(*(ahead - position_at(jammer, end)))))
    name = f"convoy, {uavs} UAVs, {window_s:g} s windows over the 3 m/s crossing"
    figures = [Figure(f"{name}: windows that place the jammer, of {windows}",
                      100.0 * len(track_errors) / windows, "%"),
               Figure(f"{name}: track's position error at each window's end, median",
                      median(track_errors), "m", TRACK_TARGET_M, lower_is_better=True)]
    if uavs == DRIVING_FIT_UAVS:
        name = (f"convoy, {uavs} UAVs, the driving fit of every upload since the crossing "
                f"began, at each {window_s:g} s window's end")
        figures += [Figure(f"{name}: moments that place the jammer, of {windows}",
                           100.0 * len(fit_errors) / windows, "%"),
                    Figure(f"{name}: position error, median", median(fit_errors), "m",
                           TRACK_TARGET_M, lower_is_better=True),
                    Figure(f"{name}: velocity error, median", median(velocity_errors), "m/s",
                           lower_is_better=True),
                    Figure(f"{name}: time a fit, mean", 1e3 * float(np.mean(seconds["driving"])),
                           "ms", lower_is_better=True),
                    Figure(f"{name}: its time over the still fit's (below)",
                           float(np.sum(seconds["driving"]) / np.sum(seconds["still"])), "x",
                           lower_is_better=True)]
        name = name.replace("the driving fit", "the still fit")
        figures += [Figure(f"{name}: moments that place the jammer, of {windows}",
                           100.0 * len(still_errors) / windows, "%"),
                    Figure(f"{name}: position error, median", median(still_errors), "m",
                           TRACK_TARGET_M, lower_is_better=True),
                    Figure(f"{name}: time a fit, mean", 1e3 * float(np.mean(seconds["still"])),
                           "ms", lower_is_better=True)]
    return figures


def fit_errors_at(scenario: Scenario, survey, data: MeasurementBatch, now: float,
                  seconds: dict[str, list[float]]
                  ) -> tuple[tuple[float, float] | None, float | None]:
    """How far from the convoy's jammer at ``now`` the driving fit of ``data`` puts it, and
    how far from its velocity; and how far the still fit puts it. None where a fit places
    nothing. Each fit's time goes to ``seconds`` under its name."""
    jammer = scenario.flown_jammers[0]
    xy = positions_from_features(scenario, data.features)
    inputs = {"reported_db": data.sinr_db,
              "no_jammer_levels": predict_probabilities(survey, data.features)}
    truth = np.array(position_at(jammer, now))

    def off(found) -> float | None:
        if found is None or not found.present:
            return None
        return float(np.hypot(found.x - truth[0], found.y - truth[1]))

    began = time.perf_counter()
    driving = estimate_driving_jammer(scenario, xy, data.times, data.levels, now, **inputs)
    seconds["driving"].append(time.perf_counter() - began)
    began = time.perf_counter()
    still = off(estimate_jammer(scenario, xy, data.levels, **inputs))
    seconds["still"].append(time.perf_counter() - began)
    if off(driving) is None:
        return None, still
    velocity = (0.0, 0.0) if driving.vx_mps is None else (driving.vx_mps, driving.vy_mps)
    true_velocity = np.subtract(position_at(jammer, now + 1.0), truth)
    return (off(driving), float(np.hypot(*(np.array(velocity) - true_velocity)))), still


def median(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")
