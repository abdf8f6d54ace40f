"""World core throughput: E=256 environments x J=4 UAVs flying toward their destinations; and a
world process's step (one environment, reports recorded) under the compiled radio and its numpy
reference, 4 UAVs on icc2021 and 50 on the city."""

from __future__ import annotations

import numpy as np

from benchmarks.common import Figure, best_rate, planner_chosen
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
    figures = [Figure("world core, UAV-steps/s (E=256, J=4, resets included)", rate, "steps/s",
                      200_000)]
    for name, uavs in (("icc2021", 4), ("city", 50)):
        seconds = {}
        for planner in ("compiled", "reference"):
            with planner_chosen(planner):
                seconds[planner] = one_environment_step(name, uavs)
            figures.append(Figure(f"world process's step, {uavs} UAVs on {name}, {planner} radio",
                                  seconds[planner] * 1e6, "us"))
        figures.append(Figure(f"world process's step, {uavs} UAVs on {name}: reference / "
                              "compiled", seconds["reference"] / seconds["compiled"], "x"))
    return figures


def one_environment_step(name: str, uavs: int) -> float:
    """Seconds a step of a world process's one environment takes, its reports recorded,
    every UAV flying straight to its destination (best of repeats over whole episodes)."""
    scenario = load_scenario(name)
    world = VectorWorld(scenario, 1, uavs, record_measurements=True)
    episode = 0
    world.reset([0], [episode_seed(0, episode)])

    def step() -> int:
        nonlocal episode
        to_goal = world.destination - world.position
        result = world.step(np.full((1, uavs), scenario.uav.max_speed_mps),
                            np.arctan2(to_goal[..., 1], to_goal[..., 0]))
        if result.env_done[0]:
            episode += 1
            world.reset([0], [episode_seed(0, episode)])
        return 1

    return 1.0 / best_rate(step, repeats=3, min_seconds=1.0)
