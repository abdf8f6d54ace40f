"""World core throughput: E=256 environments x J=4 UAVs flying toward their destinations."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure, best_rate
from shared.scenario import load_scenario
from world_sim.core import VectorWorld, episode_seed


def run() -> list[Figure]:
    scenario = load_scenario()
    envs, uavs = 256, 4
    world = VectorWorld(scenario, envs, uavs)
    world.reset(np.arange(envs), [episode_seed(0, k) for k in range(envs)])
    speed = np.full((envs, uavs), scenario.uav.max_speed_mps)
    next_episode = envs

    def step() -> int:
        nonlocal next_episode
        to_goal = world.destination - world.position
        result = world.step(speed, np.arctan2(to_goal[..., 1], to_goal[..., 0]))
        done = np.flatnonzero(result.env_done)
        if done.size:
            seeds = [episode_seed(0, next_episode + i) for i in range(done.size)]
            world.reset(done, seeds)
            next_episode += done.size
        return envs * uavs

    rate = best_rate(step, repeats=3, min_seconds=1.0)
    return [Figure("world core, UAV-steps/s (E=256, J=4, resets included)", rate, "steps/s",
                   200_000)]
