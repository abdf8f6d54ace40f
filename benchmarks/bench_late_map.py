"""How late may the map of a driving jammer be? The convoy (a 1 W jammer crossing the area at
3 m/s) flown on the true map shown as the world was 0 to 4 s before, 3 seeds x 400 episodes
of 4 UAVs each: what any cloud that places the jammer where its uploads saw it, with no
foresight of its drive, could fly at best with that delay. The late map shows the jammer at
its drive's start for an episode's first seconds, where a cloud would still show the last
episode's end: a generous bound. And the true map 1 and 2 s ahead, the jammer where it will
be when the UAVs reach the places the lookahead weighs: what moving a tracked jammer's hole
forward could bring."""

from __future__ import annotations

from benchmarks.common import Figure
from cloud_service.evaluation import load_policy
from cloud_service.rollout import LookaheadController, RasterMaps, outcome_rates, run_episodes
from shared.scenario import load_scenario
from shared.shipped import value_net_for

SCENARIO = "convoy"
EPISODES = 400
SEEDS = (0, 1, 2)
LATE_S = (-2, -1, 0, 1, 2, 3, 4)  # negative: ahead
TARGET_POINTS = 3.0  # the convoy's target: the online map within 3 points of the perfect map


def run() -> list[Figure]:
    scenario = load_scenario(SCENARIO)
    policy = load_policy(scenario, value_net_for(None, scenario, scenario.missions.uav_count,
                                                 scenario.flown_jammers))
    success = {}
    for late_s in LATE_S:
        late_steps = round(late_s / scenario.timing.step_s)
        rates = [outcome_rates(run_episodes(
            scenario, LookaheadController(policy, RasterMaps(scenario, late_steps=late_steps)),
            EPISODES, seed, scenario.flown_jammers).outcomes)["success_rate"] for seed in SEEDS]
        success[late_s] = 100.0 * sum(rates) / len(rates)
    figures = [Figure(f"{SCENARIO}, the true map {_when(late_s)}: success", rate, "%")
               for late_s, rate in success.items()]
    allowed = max(late_s for late_s, rate in success.items()
                  if rate >= success[0] - TARGET_POINTS)
    return figures + [Figure(f"{SCENARIO}: lateness within {TARGET_POINTS:g} points of the "
                             "true map", allowed, "s")]


def _when(late_s: int) -> str:
    return "on time" if late_s == 0 else f"{abs(late_s)} s {'late' if late_s > 0 else 'ahead'}"
