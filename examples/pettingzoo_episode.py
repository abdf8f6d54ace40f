"""Fly one PettingZoo episode with a shipped value network and the lookahead planner.

    python examples/pettingzoo_episode.py --uavs 4 --seed 0
"""

import argparse

import numpy as np

from cloud_service.rollout import perfect_maps
from planning.chosen import lookahead_policy
from planning.networks import load_network
from shared.shipped import VALUE_NETS
from world_sim import parallel_env
from world_sim.core import fleet_observation

parser = argparse.ArgumentParser(prog="pettingzoo_episode", description=__doc__.splitlines()[0])
parser.add_argument("--uavs", type=int, default=4, help="UAVs, one PettingZoo agent each")
parser.add_argument("--seed", type=int, default=0, help="of the episode")
parser.add_argument("--model", choices=sorted(VALUE_NETS), default="extended")
args = parser.parse_args()

env = parallel_env(num_uavs=args.uavs)
network, _ = load_network(VALUE_NETS[args.model], {"kind": "value"})  # models/*.safetensors
policy = lookahead_policy(env.scenario, network)
maps = perfect_maps(env.scenario)  # the planner reads the true SINR map of the jammer in force
env.reset(seed=args.seed)
while env.agents:
    # The flying UAVs' observations, one row each; the planner picks an action of the set.
    rows = np.flatnonzero(env.world.active[0])
    decision = policy.decide(fleet_observation(env.world).select(rows), maps(env.world, rows))
    actions = {env.possible_agents[j]: int(a) for j, a in zip(rows, decision.action, strict=True)}
    _, _, terminated, truncated, infos = env.step(actions)
    for agent in actions:  # a UAV's mission ends once: it leaves env.agents
        if terminated[agent] or truncated[agent]:
            print(f"{agent}: {infos[agent]['outcome']} at step {env.world.steps[0]}")
