"""How well the default planner flies: the shipped best network on the online map (the
transient after the jammer appears counted), against the same network on the perfect map.
Table I's four settings and three settings no parameter was tuned on, 3 seeds x 400 episodes
of 4 UAVs each; then 8 and 16 UAVs on Table I's settings. The runs are independent, so they
fly in parallel processes (outcomes, not speed, are measured here)."""

from __future__ import annotations

import multiprocessing
import os
import sys

import numpy as np

from benchmarks.common import Figure
from shared.paper import TABLE_I_JAMMERS, JammerSetting

UNTUNED = (JammerSetting(10.0, 25.0, 0.75), JammerSetting(-20.0, -25.0, 1.0),
           JammerSetting(35.0, 35.0, 0.4))
SEEDS = (0, 1, 2)
EPISODES = 400
CROWDS = ((8, 200), (16, 100))  # UAVs per episode, episodes per Table I setting (seed 0)
RATES = ("success_rate", "disconnection_rate", "collision_rate")


def fly(job: tuple[str, JammerSetting, int, int, int]) -> tuple[tuple, dict[str, float]]:
    from cloud_service.evaluation import evaluate
    from shared.scenario import load_scenario

    method, setting, seed, uavs, episodes = job
    report = evaluate(load_scenario(), method, episodes, seed, setting, uavs=uavs)
    return job, {key: report[key] for key in RATES}


def run() -> list[Figure]:
    jobs = [(method, setting, seed, 4, EPISODES) for setting in (*TABLE_I_JAMMERS, *UNTUNED)
            for seed in SEEDS for method in ("proposed", "perfect")]
    jobs += [("proposed", setting, 0, uavs, episodes) for uavs, episodes in CROWDS
             for setting in TABLE_I_JAMMERS]
    results = {}
    with multiprocessing.get_context("spawn").Pool(os.cpu_count() or 1) as pool:
        for job, rates in pool.imap_unordered(fly, jobs):
            results[job] = rates
            method, setting, seed, uavs, _ = job
            print(f"  {len(results)}/{len(jobs)}: {method} {setting.label} seed {seed}, "
                  f"{uavs} UAVs: success {rates['success_rate']:.1%}", file=sys.stderr,
                  flush=True)

    def mean(method: str, setting: JammerSetting, key: str, uavs: int = 4) -> float:
        return 100 * float(np.mean([rates[key] for (m, s, _, u, _), rates in results.items()
                                    if m == method and s == setting and u == uavs]))

    figures = []
    for setting in (*TABLE_I_JAMMERS, *UNTUNED):
        label = f"{setting.label}{'' if setting in TABLE_I_JAMMERS else ' (untuned)'}"
        success = mean("proposed", setting, "success_rate")
        figures += [
            Figure(f"proposed {label}: success", success, "%", 97),
            Figure(f"proposed {label}: disconnection", mean("proposed", setting,
                   "disconnection_rate"), "%", 1.5, lower_is_better=True),
            Figure(f"proposed {label}: collision", mean("proposed", setting, "collision_rate"),
                   "%", 0.2, lower_is_better=True),
            Figure(f"proposed {label}: points under the perfect map",
                   mean("perfect", setting, "success_rate") - success, "points", 1,
                   lower_is_better=True),
        ]
    for uavs, _ in CROWDS:
        figures.append(Figure(f"proposed, {uavs} UAVs, Table I settings: success", float(
            np.mean([mean("proposed", s, "success_rate", uavs) for s in TABLE_I_JAMMERS])),
            "%", 95))
    return figures
