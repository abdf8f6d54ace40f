"""How well the cloud can follow the convoy's jammer (3 m/s across the area) from windows of
uploads, as the online mapper does (``jammer_tracking.WindowedTracker``): UAVs on random legs
(``online_map_sim.Fleet``) for the 33 s of the crossing, each window of
``online_map.tracking_window_s`` estimated alone with the shipped survey map, the estimates
that place the jammer joined by the constant-velocity filter. Four UAVs (the scenario's) and
sixteen; the share of windows that place the jammer, and the track's error against where
the jammer is at the end of each of those windows."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure
from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.jammer_tracking import WindowedTracker
from cloud_service.online_map_sim import Fleet
from cloud_service.upload_positions import positions_from_features
from planning.networks import load_network, predict_probabilities
from shared.jammer_motion import position_at
from shared.measurements import MeasurementBatch
from shared.radio import JammerParams
from shared.scenario import Scenario, load_scenario
from shared.survey_maps import sinr_map_for

CROSSING_S = 33  # the convoy's 100 m at 3 m/s
SEEDS = 6
FLEETS = (4, 16)
TRACK_TARGET_M = 5.0  # the issue's: tracked within 5 m median while the UAVs cross its zone


def run() -> list[Figure]:
    scenario = load_scenario("convoy")
    return [figure for uavs in FLEETS for figure in fleet_figures(scenario, uavs)]


def fleet_figures(scenario: Scenario, uavs: int) -> list[Figure]:
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    jammer = scenario.flown_jammers[0]
    window_s = scenario.online_map.tracking_window_s
    windows, placed, track_errors = 0, 0, []
    for seed in range(SEEDS):
        fleet, batches = Fleet(scenario, uavs, np.random.default_rng([seed, 7])), []
        tracker = WindowedTracker(0.0, window_s)
        for step in range(CROSSING_S):
            fleet.fly()
            x, y = position_at(jammer, float(step))
            batches.append(fleet.uploads(JammerParams(x, y, jammer.power_w, jammer.height_m),
                                         float(step), step))
            if not tracker.due(step + 1.0):
                continue
            data = MeasurementBatch.concatenate(batches)
            windows += 1

            def estimate_window(start: float, end: float, data=data):
                rows = np.flatnonzero((data.times >= start) & (data.times < end))
                window = data.take(rows)
                return estimate_jammer(
                    scenario, positions_from_features(scenario, window.features), window.levels,
                    reported_db=window.sinr_db,
                    no_jammer_levels=predict_probabilities(survey, window.features))

            if tracker.follow(step + 1.0, estimate_window):
                placed += 1
                track_errors.append(np.hypot(*(np.array(tracker.track.at(step + 1.0))
                                               - position_at(jammer, step + 1.0))))
    name = f"convoy, {uavs} UAVs, {window_s:g} s windows over the 3 m/s crossing"
    return [Figure(f"{name}: windows that place the jammer, of {windows}",
                   100.0 * placed / max(windows, 1), "%"),
            Figure(f"{name}: track's position error at each window's end, median",
                   float(np.median(track_errors)) if track_errors else float("nan"), "m",
                   TRACK_TARGET_M, lower_is_better=True)]
