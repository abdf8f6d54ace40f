"""The episodes value-network training flies (the episode loop of Algorithm 1), as seen
from the learner: the training jammer of each period, the state each UAV acted from and the
reward it received, handed over mission by mission, and each episode's statistics."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cloud_service.rollout import EpisodeHooks, RasterMaps
from planning.features import MethodOptions, joint_state_size, observation_state
from shared.outcomes import Outcome
from shared.scenario import Jammer, JammerPath, Scenario
from world_sim.core import StepResult, VectorWorld, episode_seed, fleet_observation

TRAINING_JAMMER_STREAM = 7  # separates the jammer schedule's random stream from missions'


def training_jammers(scenario: Scenario, seed: int, period: int) -> tuple[Jammer, ...]:
    """The jammers of training period ``period`` (``scenario.training``): none, or 1 to
    ``jammer_count_max`` at random places and powers, a share of them driving. A scenario
    with one still jammer at most draws as the shipped networks' training did."""
    rng = np.random.default_rng([seed, TRAINING_JAMMER_STREAM, period])
    spec, area = scenario.training, scenario.area
    if rng.random() < spec.jammer_absent_probability:
        return ()

    def anywhere() -> tuple[float, float]:
        return float(rng.uniform(area.x_min, area.x_max)), float(rng.uniform(area.y_min,
                                                                             area.y_max))

    def drawn() -> tuple[float, float, float]:
        return *anywhere(), float(rng.uniform(*spec.jammer_power_range_w))

    places = [drawn()]
    if spec.jammer_count_max > 1:
        places += [drawn() for _ in range(int(rng.integers(1, spec.jammer_count_max + 1)) - 1)]
    jammers = []
    for x, y, power_w in places:
        path = None
        if spec.moving_jammer_share > 0 and rng.random() < spec.moving_jammer_share:
            path = JammerPath(waypoints=[anywhere()], loop=True,
                              speed_mps=float(rng.uniform(*spec.moving_jammer_speed_range_mps)))
        jammers.append(Jammer(x=x, y=y, power_w=power_w, height_m=scenario.jammer.height_m,
                              efficiency_db=scenario.jammer.efficiency_db, path=path))
    return tuple(jammers)


def training_maps(scenario: Scenario) -> RasterMaps:
    """The true map of each environment's training jammers, a moving one shown where it was
    at the last multiple of ``training.moving_map_every_s`` into the episode."""
    every_s, step_s = scenario.training.moving_map_every_s, scenario.timing.step_s
    return RasterMaps(scenario, moving_every_steps=max(1, round(every_s / step_s)))


class TrajectoryRecorder:
    """Per-UAV states and rewards of the running episodes, flushed when a mission ends."""

    def __init__(self, envs: int, uavs: int, horizon: int, state_size: int):
        self.states = np.zeros((envs, uavs, horizon + 1, state_size), dtype=np.float32)
        self.rewards = np.zeros((envs, uavs, horizon), dtype=np.float32)
        self.length = np.zeros((envs, uavs), dtype=np.int64)

    def record(self, rows_state: np.ndarray, rows: np.ndarray, reward: np.ndarray) -> None:
        """Store the state each active UAV acted from, and the reward it then received."""
        uavs = self.length.shape[1]
        env, uav = rows // uavs, rows % uavs
        t = self.length[env, uav]
        self.states[env, uav, t] = rows_state
        self.rewards[env, uav, t] = reward[env, uav]
        self.length[env, uav] = t + 1

    def take(self, env: int, uav: int) -> tuple[np.ndarray, np.ndarray]:
        length = self.length[env, uav]
        self.length[env, uav] = 0
        return self.states[env, uav, :length], self.rewards[env, uav, :length]


@dataclass
class EpisodeStats:
    episode: int
    outcomes: np.ndarray  # (J,)
    mean_return: float
    straight_bound: float


def straight_line_bound(scenario: Scenario, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Reward of flying straight at full speed, ignoring R_s and R_c (the paper's bound)."""
    reach = scenario.uav.max_speed_mps * scenario.timing.step_s
    distance = np.linalg.norm(goal - start, axis=-1) - scenario.uav.arrival_tolerance_m
    steps = np.maximum(1, np.ceil(distance / reach))
    return scenario.rewards.arrival + scenario.rewards.step * steps


class TrainingFlight(EpisodeHooks):
    """Training's side of a flight: the training jammer schedule, the state each UAV acted
    from and the reward it received (with the disconnection penalty), and each episode's
    statistics."""

    def __init__(
        self,
        world: VectorWorld,
        maps: RasterMaps,
        options: MethodOptions,
        seed: int,
        on_missions: Callable[[list[tuple[np.ndarray, np.ndarray]]], None],
        on_episode: Callable[[EpisodeStats], None],
    ):
        self.world, self.maps, self.options, self.seed = world, maps, options, seed
        self.on_missions, self.on_episode = on_missions, on_episode
        size = joint_state_size(world.scenario, options)
        self.recorder = TrajectoryRecorder(world.num_envs, world.num_uavs, world.step_limit, size)
        self.returns = np.zeros((world.num_envs, world.num_uavs))
        self.decisions = 0
        self.next_episode = 0  # the first episode not yet started
        # From before_step to after_step: the rows of the UAVs about to act, and their states.
        self.rows = np.zeros(0, dtype=np.int64)
        self.states = np.zeros((0, size), dtype=np.float32)

    def start(self, env: int, episode: int) -> None:
        scenario = self.world.scenario
        period = episode // scenario.training.jammer_change_every_episodes
        self.next_episode = episode + 1
        self.world.set_jammers([env], training_jammers(scenario, self.seed, period))
        self.world.reset([env], [episode_seed(self.seed, episode)])
        self.returns[env] = 0.0

    def before_step(self, running: np.ndarray) -> None:
        world, options = self.world, self.options
        self.rows = np.flatnonzero((world.active & running[:, None]).ravel())
        self.states = observation_state(
            fleet_observation(world).select(self.rows), world.scenario, options,
            self.maps(world, self.rows) if options.route_distance else None)

    def after_step(self, result: StepResult, slot_episode: np.ndarray,
                   running: np.ndarray) -> None:
        self.decisions += self.rows.size
        lost = result.finished & (self.world.status == Outcome.DISCONNECTION)
        reward = result.reward + self.options.disconnection_reward * lost
        self.recorder.record(self.states, self.rows, reward)
        self.returns += reward
        self.on_missions([self.recorder.take(e, u)
                          for e, u in zip(*np.nonzero(result.finished), strict=True)])

    def end(self, env: int, episode: int) -> None:
        world = self.world
        bound = straight_line_bound(world.scenario, world.start[env], world.destination[env])
        self.on_episode(EpisodeStats(int(episode), world.status[env].copy(),
                                     float(self.returns[env].mean()), float(bound.mean())))
