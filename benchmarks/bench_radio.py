"""Radio model throughput: SINR + level + serving GBS per point, float64, one core."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure, best_rate
from shared.radio import RadioModel
from shared.scenario import load_scenario


def run() -> list[Figure]:
    scenario = load_scenario()
    radio = RadioModel(scenario)
    points = np.random.default_rng(0).uniform(-50, 50, size=(1_000_000, 2))
    jammers = radio.default_jammers

    def evaluate() -> int:
        radio.evaluate(points, jammers)
        return points.shape[0]

    rate = best_rate(evaluate, repeats=3, min_seconds=1.0)
    return [Figure("radio model, points/s (jammer on, float64)", rate, "points/s", 2_000_000)]
