"""A reactive jammer, on only while a UAV in flight is within its reach, against a still
jammer of the same power and place that is always on: success on the perfect and the outdated
maps, and how long the jammer jammed, in UAV-seconds: each step it transmitted in, the
seconds of each UAV still in flight after it. icc2021, the jammer at Table I's (0, 0), 1 W;
reach 20 m; 400 episodes of 4 UAVs."""

from __future__ import annotations

from benchmarks.common import Figure
from cloud_service.evaluation import load_policy
from cloud_service.rollout import LookaheadController, outdated_maps, perfect_maps, run_episodes
from shared.outcomes import Outcome
from shared.scenario import Scenario, load_scenario
from shared.shipped import value_net_for
from world_sim.core import VectorWorld

EPISODES = 400
SEED = 0
REACH_M = 20.0


def run() -> list[Figure]:
    still = load_scenario()
    reactive = Scenario.model_validate({**still.model_dump(), "jammers": [
        {**still.jammer.model_dump(), "schedule": {"kind": "reactive", "radius_m": REACH_M}}]})
    figures = []
    for label, scenario in (("still", still), (f"reactive within {REACH_M:g} m", reactive)):
        for maps_name, maps in (("perfect", perfect_maps), ("outdated", outdated_maps)):
            success, jammed = _fly(scenario, maps(scenario))
            name = f"icc2021, jammer (0,0) 1 W {label}, {maps_name} map"
            figures += [Figure(f"{name}: success", 100.0 * success, "%"),
                        Figure(f"{name}: UAV-seconds jammed per episode", jammed, "UAV-s")]
    return figures


def _fly(scenario: Scenario, maps) -> tuple[float, float]:
    """Success, and the UAV-seconds per episode the jammer transmitted with UAVs in flight."""
    policy = load_policy(scenario, value_net_for(None, scenario, scenario.missions.uav_count))
    jammed = [0.0]

    def count(world: VectorWorld) -> None:  # after each step: the jammer on in it, who flies on
        on = world.jammer_power.sum(axis=1) > 0
        jammed[0] += float((world.active.sum(axis=1) * on).sum()) * world.dt

    results = run_episodes(scenario, LookaheadController(policy, maps), EPISODES, SEED,
                           scenario.flown_jammers, on_step=count)
    return float((results.outcomes == Outcome.SUCCESS).mean()), jammed[0] / EPISODES
