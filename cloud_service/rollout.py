"""In-process rollouts: the vectorized world flown by a controller.

A controller turns the world's state into commanded speeds and headings for every UAV. The
lookahead controller sees only what each UAV observes (``Observation``) and a radio map; the
baselines (ORCA, straight flight) need no map. Training, validation and ``jamnav eval`` all
fly episodes through ``fly_episodes`` (``run_episodes`` for evaluation) with these
controllers.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np

from planning.maps import MAP_SPACING_M, LevelRaster, RadioMap, RasterMap
from planning.orca import orca_velocities, preferred_velocity_toward
from planning.reference import LookaheadPolicy
from shared.outcomes import Outcome
from shared.paper import JammerSetting
from shared.radio import JammerParams, Jammers, RadioModel, as_jammers
from shared.scenario import Scenario
from world_sim.core import StepResult, VectorWorld, episode_seed, fleet_observation
from world_sim.jammers import JammerSchedule, JammerSet, jammer_set

MapFor = Callable[[VectorWorld, np.ndarray], RadioMap]


class RasterMaps:
    """Radio maps of the world's environments as rasters, the ``kept`` most recently used
    jammer settings cached. A training run meets hundreds of settings, and each raster grows
    its own route fields (megabytes with the extended method): keeping them all grew a
    20,000-episode run's memory by gigabytes. No more than one setting per environment is in
    flight at once, so keeping twice the environments flown never samples a raster twice."""

    def __init__(self, scenario: Scenario, jam: bool = True, kept: int = 128,
                 moving_every_steps: int = 1, late_steps: int = 0):
        """``moving_every_steps``: a moving jammer is shown where it was at the last multiple
        of this many steps into the episode (1: where it is); ``late_steps``: where it was
        this many steps ago, at the episode's start at the earliest (0: where it is; negative:
        where it will be)."""
        self.scenario = scenario
        self.radio = RadioModel(scenario)
        self.jam = jam
        self.kept = kept
        self.moving_every_steps = moving_every_steps
        self.late_steps = late_steps
        self.cache: OrderedDict[tuple[float, ...], LevelRaster] = OrderedDict()

    def raster(self, jammers: Jammers) -> LevelRaster:
        key = tuple(tuple(map(float, jammer)) for jammer in as_jammers(jammers)
                    if jammer.power_w > 0)
        if key in self.cache:
            self.cache.move_to_end(key)
        else:
            params = [JammerParams(*jammer) for jammer in key]
            self.cache[key] = LevelRaster.sample(
                self.scenario, lambda xy: self.radio.evaluate(xy, params).level, MAP_SPACING_M
            )
            if len(self.cache) > self.kept:
                self.cache.popitem(last=False)
        return self.cache[key]

    def __call__(self, world: VectorWorld, rows: np.ndarray) -> RadioMap:
        if not self.jam:
            return RasterMap(self.scenario, [self.raster(None)], np.zeros(rows.size, np.int64))
        self.kept = max(self.kept, 2 * world.num_envs)  # never evict a setting in flight
        env = rows // world.num_uavs
        jammers = {e: world.jammers_as_of(e, self.moving_every_steps, self.late_steps)
                   for e in np.unique(env).tolist()}
        keys = sorted(set(jammers.values()))
        position = {key: index for index, key in enumerate(keys)}
        rasters = [self.raster([JammerParams(*jammer) for jammer in key]) for key in keys]
        which = np.array([position[jammers[e]] for e in env.tolist()], dtype=np.int64)
        return RasterMap(self.scenario, rasters, which)


def perfect_maps(scenario: Scenario) -> RasterMaps:
    """The true current map of each UAV's environment ("perfectly updated map")."""
    return RasterMaps(scenario, jam=True)


def outdated_maps(scenario: Scenario) -> RasterMaps:
    """The map of the world without any jammer ("outdated map")."""
    return RasterMaps(scenario, jam=False)


class Controller(Protocol):
    def act(self, world: VectorWorld) -> tuple[np.ndarray, np.ndarray]:
        """Commanded speed and heading (E, J) for the world's current state."""


class LookaheadController:
    def __init__(
        self,
        policy: LookaheadPolicy,
        map_for: MapFor,
        epsilon: float = 0.0,
        rng: np.random.Generator | None = None,
    ):
        self.policy = policy
        self.map_for = map_for
        self.epsilon = epsilon
        self.rng = rng

    def act(self, world: VectorWorld) -> tuple[np.ndarray, np.ndarray]:
        rows = np.flatnonzero(world.active.ravel())
        observation = fleet_observation(world).select(rows)
        decision = self.policy.decide(
            observation, self.map_for(world, rows), self.epsilon, self.rng
        )
        speed = np.zeros(world.num_envs * world.num_uavs)
        heading = world.heading.ravel().copy()
        speed[rows] = decision.speed
        heading[rows] = decision.heading
        shape = world.active.shape
        return speed.reshape(shape), heading.reshape(shape)


def _speed_heading(world: VectorWorld, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    speed = np.hypot(velocity[..., 0], velocity[..., 1])
    heading = np.where(speed > 1e-9, np.arctan2(velocity[..., 1], velocity[..., 0]), world.heading)
    return speed, heading


class OrcaController:
    """ORCA toward the destination: avoids other UAVs, blind to connectivity."""

    def __init__(self, scenario: Scenario):
        self.horizon = scenario.policy.orca_time_horizon_s

    def act(self, world: VectorWorld) -> tuple[np.ndarray, np.ndarray]:
        preferred = preferred_velocity_toward(
            world.position, world.destination, world.max_speed, world.dt
        )
        velocity = orca_velocities(
            world.position, world.velocity, world.radius, preferred, world.max_speed,
            world.active, self.horizon, world.dt,
        )
        return _speed_heading(world, velocity)


class StraightController:
    """Straight to the destination at full speed: the paper's upper-bound reference."""

    def act(self, world: VectorWorld) -> tuple[np.ndarray, np.ndarray]:
        preferred = preferred_velocity_toward(
            world.position, world.destination, world.max_speed, world.dt
        )
        return _speed_heading(world, preferred)


class EpisodeHooks:
    """What a flight of episodes (``fly_episodes``) does besides flying; nothing by default."""

    def start(self, env: int, episode: int) -> None:
        """Set up slot ``env`` for ``episode`` (its jammer, its missions)."""

    def before_step(self, running: np.ndarray) -> None:
        """Called before every step; ``running``: (E,) the slots flying an episode."""

    def after_step(self, result: StepResult, slot_episode: np.ndarray,
                   running: np.ndarray) -> None:
        """Called after every step; ``slot_episode``: (E,) the episode each slot flew."""

    def end(self, env: int, episode: int) -> None:
        """Book the ended ``episode`` of slot ``env``, before the slot takes the next one."""


def fly_episodes(world: VectorWorld, controller: Controller, episodes: range,
                 hooks: EpisodeHooks) -> None:
    """Fly ``episodes`` in the world's environment slots, all slots stepping together; a slot
    takes the next episode as soon as its current one ends, and idles (no active UAV) when
    none is left."""
    slot_episode = np.full(world.num_envs, -1)
    upcoming = iter(episodes)

    def refill(env: int) -> None:
        episode = next(upcoming, -1)
        slot_episode[env] = episode
        if episode >= 0:
            hooks.start(env, episode)

    for env in range(world.num_envs):
        refill(env)
    while (running := slot_episode >= 0).any():
        hooks.before_step(running)
        result = world.step(*controller.act(world))
        hooks.after_step(result, slot_episode, running)
        for env in np.flatnonzero(result.env_done & running):
            hooks.end(env, slot_episode[env])
            refill(env)


class EpisodeResults(NamedTuple):
    outcomes: np.ndarray  # (episodes, J) Outcome codes
    returns: np.ndarray  # (episodes, J) accumulated reward per UAV
    steps: np.ndarray  # (episodes,) steps until every UAV finished
    ended_at: np.ndarray  # (episodes, J) the step at whose end each UAV's mission ended


class EvaluationBook(EpisodeHooks):
    """Evaluation's side of a flight: each episode's jammer, then its outcomes, returns,
    steps and the step each UAV's mission ended."""

    def __init__(
        self,
        world: VectorWorld,
        episodes: int,
        seed: int,
        jammer_at: JammerSchedule,
        on_step: Callable[[VectorWorld], None] | None,
        on_episode: Callable[[int], None] | None,
    ):
        self.world, self.seed, self.jammer_at = world, seed, jammer_at
        self.on_step, self.on_episode = on_step, on_episode
        self.results = EpisodeResults(np.zeros((episodes, world.num_uavs), dtype=np.int8),
                                      np.zeros((episodes, world.num_uavs)),
                                      np.zeros(episodes, dtype=np.int64),
                                      np.zeros((episodes, world.num_uavs), dtype=np.int64))

    def start(self, env: int, episode: int) -> None:
        self.world.set_jammers([env], self.jammer_at(episode))
        self.world.reset([env], [episode_seed(self.seed, episode)])

    def after_step(self, result: StepResult, slot_episode: np.ndarray,
                   running: np.ndarray) -> None:
        if self.on_step is not None:
            self.on_step(self.world)
        self.results.returns[slot_episode[running]] += result.reward[running]
        env, uav = np.nonzero(result.finished & running[:, None])
        self.results.ended_at[slot_episode[env], uav] = self.world.steps[env]

    def end(self, env: int, episode: int) -> None:
        self.results.outcomes[episode] = self.world.status[env]
        self.results.steps[episode] = self.world.steps[env]
        if self.on_episode is not None:
            self.on_episode(episode)


def run_episodes(
    scenario: Scenario,
    controller: Controller,
    episodes: int,
    seed: int,
    jammer: JammerSetting | JammerSet | None | JammerSchedule,
    num_uavs: int | None = None,
    num_envs: int = 64,
    on_step: Callable[[VectorWorld], None] | None = None,
    on_episode: Callable[[int], None] | None = None,
    record_measurements: bool = False,
) -> EpisodeResults:
    """Fly ``episodes`` episodes (episode k seeded by ``episode_seed(seed, k)``) under one
    jammer setting or a scenario's list of jammers, or under ``jammer(k)`` for episode k,
    ``num_envs`` at a time. Results are independent of ``num_envs``."""
    jammers = None if callable(jammer) else jammer_set(scenario, jammer)
    jammer_at = jammer if callable(jammer) else (lambda _episode: jammers)
    world = VectorWorld(scenario, min(num_envs, episodes), num_uavs, record_measurements)
    book = EvaluationBook(world, episodes, seed, jammer_at, on_step, on_episode)
    fly_episodes(world, controller, range(episodes), book)
    return book.results


def outcome_rates(outcomes: np.ndarray) -> dict[str, float]:
    """Share of UAV-episodes ending in each outcome."""
    total = outcomes.size
    return {
        f"{outcome.label}_rate": float(np.count_nonzero(outcomes == outcome) / total)
        for outcome in (Outcome.SUCCESS, Outcome.DISCONNECTION, Outcome.COLLISION,
                        Outcome.TIMEOUT)
    }
