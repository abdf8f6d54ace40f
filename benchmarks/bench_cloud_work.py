"""The cloud's two costly pieces of work on a change, compiled against their references in one
run: a jammer estimate from 4,000 uploads (the uploads' report tables and the search's sums;
numpy's gathers are the reference) and a refit of the SINR map on them and the prior, the
scenario's 1,000 steps (torch's step is the reference), with the refit map's held-out accuracy
either way. Each is the best of 3, on icc2021 with a 1 W jammer."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from benchmarks.common import Figure, planner_chosen
from cloud_service.change_handling import RetrainConfig
from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.simulated_measurements import measurements_at, uniform_positions
from cloud_service.sinr_training import train_sinr_map
from planning.compiled import chosen_planner
from planning.measuring import scenario_features
from planning.networks import load_network
from shared.radio import JammerParams, RadioModel
from shared.scenario import load_scenario
from shared.survey_maps import sinr_map_for

UPLOADS = 4000  # the post-change uploads at which the cloud settles a change (RetrainConfig)


def run() -> list[Figure]:
    scenario = load_scenario()
    radio = RadioModel(scenario)
    rng = np.random.default_rng(0)
    xy = uniform_positions(scenario, UPLOADS, rng)
    jammer = JammerParams(10.0, -20.0, 1.0, scenario.jammer.height_m)
    uploads = measurements_at(scenario, radio, jammer, xy, rng)
    survey, _ = load_network(sinr_map_for(scenario))
    prior_xy = uniform_positions(scenario, scenario.online_map.prior_points, rng)
    features = np.concatenate([uploads.features, scenario_features(scenario, prior_xy)])
    levels = np.concatenate([uploads.levels, radio.evaluate(prior_xy, jammer).level])
    no_jammer = radio.evaluate(xy).level

    def estimate() -> None:
        estimate_jammer(scenario, xy, uploads.levels, no_jammer_levels=no_jammer)

    accuracy = {}

    def refit() -> None:
        accuracy[chosen_planner()] = train_sinr_map(
            features, levels, survey.levels, network=survey, steps=RetrainConfig().steps).accuracy

    figures = []
    for label, work in (("jammer estimate, 4,000 uploads", estimate),
                        ("SINR map refit, 1,000 steps", refit)):
        seconds = {planner: best_seconds(work, planner) for planner in ("reference", "compiled")}
        figures += [
            Figure(f"{label}: reference, ms", 1e3 * seconds["reference"], "ms",
                   lower_is_better=True),
            Figure(f"{label}: compiled, ms", 1e3 * seconds["compiled"], "ms",
                   lower_is_better=True),
            Figure(f"{label}: compiled's speed-up, x",
                   seconds["reference"] / seconds["compiled"], "x"),
        ]
    # Not the same map bit for bit (a fit carries each step's rounding on), but as right.
    figures += [Figure(f"SINR map refit: held-out accuracy, {planner}, %",
                       100 * accuracy[planner], "%") for planner in ("reference", "compiled")]
    return figures


def best_seconds(work: Callable[[], None], planner: str, repeats: int = 3) -> float:
    """The fastest of ``repeats`` runs of ``work`` with ``planner`` chosen (after one run
    that pays any first call's set-up)."""
    with planner_chosen(planner):
        work()
        times = []
        for _ in range(repeats):
            begun = time.perf_counter()
            work()
            times.append(time.perf_counter() - begun)
    return min(times)
