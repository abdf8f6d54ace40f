"""Lookahead decisions/s: full evaluation of every permissible action for 256 UAVs at once
(64 environments x 4 UAVs), true map with a jammer, value network on one CPU thread; for the
paper's method (one step), and for the shipped extended network (route distances, safe cells,
and the scenario's deeper search for UAVs whose one-step choice is a trap)."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure, best_rate
from cloud_service.evaluation import load_policy
from cloud_service.rollout import LookaheadController, perfect_maps
from cloud_service.torch_networks import TorchValueNetwork
from shared.features import joint_state_size
from shared.policy import LookaheadPolicy
from shared.scenario import load_scenario
from shared.shipped import EXTENDED_VALUE_NET
from world_sim.core import VectorWorld, episode_seed


def run() -> list[Figure]:
    scenario = load_scenario()
    world = VectorWorld(scenario, 64, 4)
    world.reset(np.arange(64), [episode_seed(0, k) for k in range(64)])
    policies = {
        "paper's method": LookaheadPolicy(
            scenario, TorchValueNetwork(joint_state_size(scenario), 2.0).inference()),
        "extended": load_policy(scenario, EXTENDED_VALUE_NET),
    }
    figures = []
    for name, policy in policies.items():
        controller = LookaheadController(policy, perfect_maps(scenario))

        def decide(controller: LookaheadController = controller) -> int:
            controller.act(world)
            return int(world.active.sum())

        rate = best_rate(decide, repeats=3, min_seconds=1.0)
        figures.append(Figure(f"lookahead decisions/s, {name} (256 UAVs x all actions, "
                              "batched)", rate, "decisions/s", 20_000))
    return figures
