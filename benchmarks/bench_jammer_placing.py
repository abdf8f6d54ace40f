"""Where the cloud places two still jammers while the UAVs fly their missions: the online map
(``jamnav eval --method proposed``) in two-jammers (idealized, level reports) and in
two-jammers-shadowed (dB reports), 100 episodes of 4 UAVs, seed 0. Each published estimate's
jammers, each against the nearest true one; and the share of estimates that count both."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure
from cloud_service.evaluation import evaluate
from shared.scenario import load_scenario

EPISODES, SEED = 100, 0
TARGETS_M = {"two-jammers": 5.0, "two-jammers-shadowed": 10.0}  # median, the issue's


def run() -> list[Figure]:
    figures = []
    for name, target in TARGETS_M.items():
        scenario = load_scenario(name)
        report = evaluate(scenario, "proposed", EPISODES, SEED, scenario.flown_jammers)
        truth = np.array([(jammer.x, jammer.y) for jammer in scenario.flown_jammers])
        estimates = [event for event in report["events"] if event["type"] == "jammer_estimated"]
        errors = [float(np.hypot(*(truth - (member["x"], member["y"])).T).min())
                  for event in estimates for member in [event, *event["others"]]]
        both = sum(len(event["others"]) == len(truth) - 1 for event in estimates)
        label = f"{name}, {EPISODES} episodes of 4 UAVs"
        figures += [
            Figure(f"{label}: each estimated jammer from the nearest true one, median",
                   float(np.median(errors)) if errors else float("nan"), "m", target,
                   lower_is_better=True),
            Figure(f"{label}: estimates published that count both, of {len(estimates)}",
                   100.0 * both / max(len(estimates), 1), "%"),
            Figure(f"{label}: online map's success", 100.0 * report["success_rate"], "%")]
    return figures
