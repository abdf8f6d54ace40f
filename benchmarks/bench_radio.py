"""The radio model's throughput (SINR, level and serving GBS per point, float64, one core),
under its compiled core and under its numpy reference (``JAMNAV_PLANNER=reference``) in the
same run: a million points of icc2021, a batch the size of training's, and the points a world
process reads in one step, its UAVs' reports (the step's end the last of each): 4 UAVs on
icc2021 (44 points, 12 GBSs) and 50 on the city (550 points, 192 GBSs)."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure, best_rate, planner_chosen
from shared.radio import RadioModel
from shared.scenario import load_scenario

# (scenario, points, what they are); the first keeps the figure's older name and its target.
CASES = (("icc2021", 1_000_000, None),
         ("icc2021", 4 * 11, "a step of 4 UAVs' reports"),
         ("city", 50 * 11, "a step of 50 UAVs' reports on the city"))
TARGET_POINTS_PER_S = 2_000_000


def run() -> list[Figure]:
    figures = []
    for name, count, what in CASES:
        scenario = load_scenario(name)
        area = scenario.area
        points = np.random.default_rng(0).uniform([area.x_min, area.y_min],
                                                  [area.x_max, area.y_max], size=(count, 2))
        rates = {}
        for planner in ("compiled", "reference"):
            with planner_chosen(planner):
                radio = RadioModel(scenario)

            def evaluate(radio: RadioModel = radio, points: np.ndarray = points) -> int:
                radio.evaluate(points, radio.default_jammers)
                return len(points)

            rates[planner] = best_rate(evaluate, repeats=3, min_seconds=1.0)
        if what is None:
            figures += [Figure("radio model, points/s (jammer on, float64)", rates["compiled"],
                               "points/s", TARGET_POINTS_PER_S),
                        Figure("radio model, points/s, the numpy reference", rates["reference"],
                               "points/s")]
            what = "a million points"
        else:
            figures += [Figure(f"radio model, {what}, {planner}: us", 1e6 * count / rate, "us")
                        for planner, rate in rates.items()]
        figures.append(Figure(f"radio model, {what}: compiled / reference",
                              rates["compiled"] / rates["reference"], "x"))
    return figures
