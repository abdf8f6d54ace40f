"""What correcting the survey map with a jammer estimate is worth, the estimate taken as the
true jammer: the shipped planner flies icc2021-shadowed's survey map uncorrected, corrected by
the map's levels alone, corrected by what its probabilities read near a level's edge (the
cloud's way), the same with denser surveys learned without a model (bench_map_ceiling's
local shares of 10 and 100 reports per square metre, against the survey map's 3), with a
perfectly learned survey (the world's own shares of reports at each level), and the true
map. The gap between the last two is what no estimate can close (the jammer link's own
shadowing); between the cloud's way and the perfect survey, what the survey map's errors
cost. And how far the idealized world's survey map says the world departs from the ideal
model where UAVs report, which is why the reading changes nothing there. One CPU thread;
outcomes, not speed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from benchmarks.bench_adaptation import TruthGrid
from benchmarks.bench_map_ceiling import LocalReportMap
from benchmarks.common import Figure
from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.evaluation import load_policy
from cloud_service.map_correction import corrected_levels
from cloud_service.no_jammer_belief import fit_shadowing_sigma
from cloud_service.online_map_sim import Fleet
from cloud_service.report_likelihood import report_shares
from cloud_service.rollout import (
    LookaheadController,
    outcome_rates,
    perfect_maps,
    run_episodes,
)
from cloud_service.upload_positions import positions_from_features
from planning.maps import MAP_SPACING_M, LevelRaster, RasterMap
from planning.measuring import scenario_features
from planning.networks import load_network, predict_levels, predict_probabilities
from shared.measurements import MeasurementBatch
from shared.paper import JammerSetting, jammer_params
from shared.radio import RadioModel
from shared.scenario import Scenario, load_scenario
from shared.shipped import value_net_for
from shared.survey_maps import sinr_map_for
from world_sim.jammers import random_jammer

# The last is the still jammer of the dB reports' target (BENCHMARKS.md, "A jammer the
# reference took in"): the ceiling of any correction at its own setting.
SETTINGS = (JammerSetting(0.0, 0.0, 1.0), JammerSetting(-30.0, 10.0, 1.0),
            JammerSetting(-25.0, 15.0, 1.0))
EPISODES = 200
SEED = 0
DENSE_SURVEYS = (10, 100)  # reports per square metre
DENSE_SURVEY_SQUARE_M = 1.0  # the most accurate of bench_map_ceiling's squares at both


def run() -> list[Figure]:
    scenario = load_scenario("icc2021-shadowed")
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    truth = RadioModel(scenario)
    grid = TruthGrid(scenario)

    def survey_probabilities(xy: np.ndarray) -> np.ndarray:
        return predict_probabilities(survey, scenario_features(scenario, xy))

    def world_shares(xy: np.ndarray) -> np.ndarray:
        return report_shares(truth, truth.evaluate(xy).sinr_db)

    dense_surveys = {density: LocalReportMap(scenario, truth, density, DENSE_SURVEY_SQUARE_M)
                     for density in DENSE_SURVEYS}
    figures = []
    for setting in SETTINGS:
        estimate = JammerEstimate(True, setting.x, setting.y, setting.power_w, None,
                                  0.0, 0.0, 0.0, 0, 0.0)
        maps: dict[str, Callable[[np.ndarray], np.ndarray]] = {
            "survey map, uncorrected": lambda xy: survey_probabilities(xy).argmax(-1),
            "corrected by the survey map's levels": lambda xy, e=estimate: corrected_levels(
                scenario, lambda p: survey_probabilities(p).argmax(-1), e, xy),
            "corrected by the survey map's probabilities (shipped)":
                lambda xy, e=estimate: corrected_levels(scenario, survey_probabilities, e, xy),
            **{f"corrected from a survey of {density} reports per m2 without a model":
               lambda xy, e=estimate, survey=dense: corrected_levels(scenario, survey.shares, e, xy)
               for density, dense in dense_surveys.items()},
            "corrected by a perfect survey's report shares":
                lambda xy, e=estimate: corrected_levels(scenario, world_shares, e, xy),
        }
        name = f"icc2021-shadowed, {setting.x:g},{setting.y:g} {setting.power_w:g} W, true jammer"
        figures.append(Figure(f"{name}: levels the jammer moves, of the area",
                              100.0 * grid.moved(setting), "%"))
        uncorrected = maps["survey map, uncorrected"](grid.xy)
        for label in ("corrected by the survey map's levels",
                      "corrected by the survey map's probabilities (shipped)"):
            correction = label.removeprefix("corrected ")
            figures.append(Figure(f"{name}: levels the correction {correction} moves",
                                  100.0 * np.mean(maps[label](grid.xy) != uncorrected), "%"))
        for label, levels_at in maps.items():
            figures.append(Figure(f"{name}: {label}, success",
                                  _success(scenario, setting, levels_at), "%"))
        figures.append(Figure(f"{name}: the true map, success",
                              _success(scenario, setting, None), "%"))
    spreads = _idealized_spreads(load_scenario("icc2021"))
    figures.append(Figure(f"icc2021: the world's fitted spread about the ideal model where "
                          f"{SPREAD_UAVS} UAVs reported for {SPREAD_FLIGHT_S:.0f} s, most of "
                          f"{len(spreads)} settings", 100.0 * max(spreads), "0.01 dB"))
    return figures


SPREAD_SETTINGS = 6
SPREAD_UAVS = 4
SPREAD_FLIGHT_S = 30.0


def _idealized_spreads(scenario: Scenario) -> list[float]:
    """``fit_shadowing_sigma`` of the survey map's levels at the reports of four UAVs after a
    random jammer appeared, as the estimator fits it (dB), per setting."""
    survey, _ = load_network(sinr_map_for(scenario), {"kind": "sinr_map"})
    radio = RadioModel(scenario, shadowed=False)
    spreads = []
    for k in range(SPREAD_SETTINGS):
        rng = np.random.default_rng(1000 + k)
        jammer = jammer_params(scenario, random_jammer(scenario, rng))
        fleet = Fleet(scenario, SPREAD_UAVS, rng)
        batches = []
        for step in range(int(SPREAD_FLIGHT_S / scenario.timing.step_s)):
            fleet.fly()
            batches.append(fleet.uploads(jammer, float(step), step))
        data = MeasurementBatch.concatenate(batches)
        spreads.append(fit_shadowing_sigma(radio, positions_from_features(scenario, data.features),
                                           predict_levels(survey, data.features)))
    return spreads


def _success(scenario: Scenario, setting: JammerSetting,
             levels_at: Callable[[np.ndarray], np.ndarray] | None) -> float:
    """Success (%) of the shipped planner flying the map ``levels_at`` (None: the true map)."""
    policy = load_policy(scenario, value_net_for(None, scenario, scenario.missions.uav_count))
    if levels_at is None:
        maps = perfect_maps(scenario)
    else:
        raster = LevelRaster.sample(scenario, levels_at, MAP_SPACING_M)

        def maps(world, rows):
            return RasterMap(scenario, [raster], np.zeros(rows.size, np.int64))

    results = run_episodes(scenario, LookaheadController(policy, maps), EPISODES, SEED, setting)
    return 100.0 * outcome_rates(results.outcomes)["success_rate"]
