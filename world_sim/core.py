"""The vectorized world: E independent environments x J UAVs stepped together with numpy.

It owns the truth (positions, the jammers, the SINR each UAV measures) and knows no policy: it
takes commanded speeds and headings, enforces the kinematic limits, and books per-UAV outcomes
that are exclusive and final. Training, evaluation and the world process all run this engine.
A UAV whose mission has ended leaves the airspace (landed or lost): it no longer moves, is no
longer measured, and cannot be collided with.
"""

from __future__ import annotations

import functools
import math
from collections import defaultdict
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from shared.jammer_motion import position_at, transmits_at
from shared.kinematics import ActionSet, closest_approach, velocity_of
from shared.neighbours import nearby_others
from shared.observation import Observation, decision_reach
from shared.outcomes import Outcome, arrivals, disconnections
from shared.radio import JammerParams, RadioModel, RadioReading
from shared.rewards import RewardModel
from shared.scenario import MAX_JAMMERS, Jammer, Scenario

_CANDIDATES_PER_DRAW = 64
_RECEIVER_NOISE = 1  # second word of an episode's receiver-noise seed: a stream of its own
_MAX_DRAWS = 500
# From this many UAVs on, a k-d tree finds the pairs that may touch within a step; below it,
# checking every pair is cheaper than building the trees.
_TREE_FROM_UAVS = 32
_PAIR_SLACK_M = 1.0  # added to the pair search's reach against rounding at its edge


def episode_seed(master_seed: int, episode: int) -> int:
    """The seed of episode ``episode`` of a run: independent of how episodes are batched."""
    return int(np.random.SeedSequence([int(master_seed), int(episode)]).generate_state(1)[0])


class StepResult(NamedTuple):
    """What a world step did: each UAV's reward, whose missions ended, and which
    environments have finished."""

    reward: np.ndarray  # (E, J); 0 for UAVs that were already finished
    finished: np.ndarray  # (E, J) bool: the mission ended in this step
    env_done: np.ndarray  # (E,) bool: every UAV of the environment has finished


class _Spread:
    """Points kept at least ``separation`` apart, hashed on a grid of cells twice that wide:
    a new point is checked against the points of its own and the 8 adjacent cells only (any
    other is farther than a cell), so placing J points costs O(J), not O(J^2)."""

    def __init__(self, separation: float):
        self.separation = separation
        self.cell = 2 * separation
        self.cells: dict[tuple[int, int], list[tuple[float, float]]] = defaultdict(list)

    def _key(self, x: float, y: float) -> tuple[int, int]:
        return math.floor(x / self.cell), math.floor(y / self.cell)

    def clear_of(self, x: float, y: float) -> bool:
        cx, cy = self._key(x, y)
        return not any(math.hypot(x - px, y - py) < self.separation
                       for dx in (-1, 0, 1) for dy in (-1, 0, 1)
                       for px, py in self.cells.get((cx + dx, cy + dy), ()))

    def add(self, x: float, y: float) -> None:
        self.cells[self._key(x, y)].append((x, y))


class MissionSampler:
    """Starts and destinations of one episode, drawn from the episode's own seed."""

    def __init__(self, scenario: Scenario):
        area, missions = scenario.area, scenario.missions
        self.low = np.array([area.x_min + missions.margin_m, area.y_min + missions.margin_m])
        self.high = np.array([area.x_max - missions.margin_m, area.y_max - missions.margin_m])
        self.min_trip = missions.min_trip_m
        self.max_trip = math.inf if missions.max_trip_m is None else missions.max_trip_m
        self.min_separation = max(missions.min_separation_m, 2 * scenario.uav.radius_m + 1e-6)

    def sample(self, seed: int, num_uavs: int) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng(seed)
        starts: list[tuple[float, float]] = []
        goals: list[tuple[float, float]] = []
        start_spread, goal_spread = _Spread(self.min_separation), _Spread(self.min_separation)
        for _ in range(_MAX_DRAWS):
            draw = rng.uniform(self.low, self.high, size=(2, _CANDIDATES_PER_DRAW, 2))
            trip = np.hypot(*(draw[1] - draw[0]).T)
            drawn = (trip >= self.min_trip) & (trip <= self.max_trip)
            for (sx, sy), (gx, gy) in zip(
                draw[0][drawn].tolist(), draw[1][drawn].tolist(), strict=True
            ):
                if not (start_spread.clear_of(sx, sy) and goal_spread.clear_of(gx, gy)):
                    continue
                start_spread.add(sx, sy)
                goal_spread.add(gx, gy)
                starts.append((sx, sy))
                goals.append((gx, gy))
                if len(starts) == num_uavs:
                    return np.asarray(starts), np.asarray(goals)
        raise ValueError(
            f"could not place {num_uavs} missions in the area: lower missions.min_trip_m or "
            "missions.min_separation_m, or raise missions.max_trip_m"
        )


def near_pairs(position: np.ndarray, active: np.ndarray,
               reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(env, i, k), i < k: the pairs of active UAVs of E fleets of J (position (E, J, 2),
    active (E, J)) that are within ``reach`` of each other, or every pair of active UAVs
    when J is small. O(J log J) per fleet with the tree, where all pairs are O(J^2)."""
    e, j = active.shape
    if j < _TREE_FROM_UAVS:
        env, first, second = _every_pair(e, j)
        both = active[env, first] & active[env, second]
        return env[both], first[both], second[both]
    found = [np.empty((0, 3), dtype=np.int64)]
    for env in range(e):
        members = np.flatnonzero(active[env])
        pairs = cKDTree(position[env, members]).query_pairs(reach, output_type="ndarray")
        found.append(np.column_stack([np.full(len(pairs), env), members[pairs]]))
    env, first, second = np.concatenate(found).T
    return env, first, second


@functools.lru_cache(maxsize=16)
def _every_pair(envs: int, uavs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(env, i, k), i < k, of every pair of E fleets of J: the same every step, so built once
    (read-only)."""
    first, second = np.triu_indices(uavs, 1)
    pairs = (np.repeat(np.arange(envs), first.size), np.tile(first, envs), np.tile(second, envs))
    for index in pairs:
        index.flags.writeable = False
    return pairs


class VectorWorld:
    """E environments x J UAVs. All state is public numpy arrays, indexed [env, uav]."""

    def __init__(
        self,
        scenario: Scenario,
        num_envs: int,
        num_uavs: int | None = None,
        record_measurements: bool = False,
    ):
        if num_envs < 1:
            raise ValueError("num_envs must be at least 1")
        self.scenario = scenario
        self.num_envs = num_envs
        self.num_uavs = scenario.missions.uav_count if num_uavs is None else num_uavs
        if self.num_uavs < 1:
            raise ValueError("num_uavs must be at least 1")
        self.radio = RadioModel(scenario)
        self.actions = ActionSet(scenario)
        self.rewards = RewardModel(scenario)
        self.sampler = MissionSampler(scenario)
        self.dt = scenario.timing.step_s
        self.disconnection_limit = scenario.timing.disconnection_limit_steps
        self.step_limit = scenario.timing.episode_limit_steps
        self.radius = np.full((num_envs, self.num_uavs), scenario.uav.radius_m)
        self.max_speed = np.full((num_envs, self.num_uavs), scenario.uav.max_speed_mps)
        e, j = num_envs, self.num_uavs
        self.position = np.zeros((e, j, 2))
        self.velocity = np.zeros((e, j, 2))
        self.heading = np.zeros((e, j))
        self.start = np.zeros((e, j, 2))
        self.destination = np.zeros((e, j, 2))
        self.status = np.full((e, j), int(Outcome.ACTIVE), dtype=np.int8)
        self.below_steps = np.zeros((e, j), dtype=np.int64)
        self.sinr_db = np.zeros((e, j))
        self.level = np.zeros((e, j), dtype=np.int8)
        self.serving_gbs = np.zeros((e, j), dtype=np.int64)
        self.steps = np.zeros(e, dtype=np.int64)
        # What each UAV's receiver reported along its last step (uav.measurements_per_step
        # points, the step's end last, each with the receiver's measurement noise), for the
        # online SINR map; off unless asked for, as it costs radio evaluations that training
        # does not need. The noise of episode k is drawn from k's seed alone, so a batch and a
        # single environment (or the world process) report the same measurements.
        self.record_measurements = record_measurements
        samples = scenario.uav.measurements_per_step
        self.measured_xy = np.zeros((e, j, samples, 2))
        self.measured_level = np.zeros((e, j, samples), dtype=np.int8)
        self.measured_sinr_db = np.full((e, j, samples), np.nan)  # NaN: levels only
        self.measured = np.zeros((e, j), dtype=bool)
        self._receiver_noise = [np.random.default_rng(0) for _ in range(e)]
        # The jammers where they are now, one column per slot (a slot off: power 0); the
        # environments whose jammers move or keep a schedule are placed again every step.
        slots = len(scenario.jammers)
        self.jammer_x = np.zeros((e, slots))
        self.jammer_y = np.zeros((e, slots))
        self.jammer_power = np.zeros((e, slots))
        self.jammer_height = np.full((e, slots), scenario.jammer.height_m)
        self._driven: dict[int, tuple[Jammer, ...]] = {}
        self.set_jammers(slice(None), scenario.jammers)

    # -- control ---------------------------------------------------------------------------
    def set_jammer(self, env_ids, jammer: JammerParams | None) -> None:
        """One still jammer in the given environments, in place of any they had (None: no
        jammer); its fields may be arrays, one value per environment."""
        env_ids = self._env_list(env_ids)
        self._clear_jammers(env_ids)
        if jammer is None:
            return
        _check_jammer(jammer)
        self.jammer_x[env_ids, 0] = jammer.x
        self.jammer_y[env_ids, 0] = jammer.y
        self.jammer_power[env_ids, 0] = jammer.power_w
        self.jammer_height[env_ids, 0] = jammer.height_m

    def set_jammers(self, env_ids, jammers: tuple[Jammer, ...]) -> None:
        """The jammers of the given environments, moving or scheduled as configured, in place
        of any they had; placed where they are at each environment's time into its episode."""
        if len(jammers) > MAX_JAMMERS:
            raise ValueError(f"{len(jammers)} jammers: at most {MAX_JAMMERS}")
        for jammer in jammers:
            _check_jammer(JammerParams(jammer.x, jammer.y, jammer.power_w, jammer.height_m))
        if len(jammers) > self.jammer_x.shape[1]:
            self._widen_jammer_slots(len(jammers))
        env_ids = self._env_list(env_ids)
        self._clear_jammers(env_ids)
        for slot, jammer in enumerate(jammers):
            self.jammer_height[env_ids, slot] = jammer.height_m
            if jammer.still and jammer.enabled:
                self.jammer_x[env_ids, slot] = jammer.x
                self.jammer_y[env_ids, slot] = jammer.y
                self.jammer_power[env_ids, slot] = jammer.power_w
        if not all(jammer.still for jammer in jammers):
            self._driven.update({env: tuple(jammers) for env in env_ids})
            self._place_driven_jammers(env_ids, self.steps, self.position, self.active)

    def _env_list(self, env_ids) -> list[int]:
        return np.arange(self.num_envs)[env_ids].reshape(-1).tolist()

    def _clear_jammers(self, env_ids: list[int]) -> None:
        for env in env_ids:
            self._driven.pop(env, None)
        self.jammer_x[env_ids] = self.jammer_y[env_ids] = self.jammer_power[env_ids] = 0.0
        self.jammer_height[env_ids] = self.scenario.jammer.height_m

    def _widen_jammer_slots(self, slots: int) -> None:
        extra = slots - self.jammer_x.shape[1]
        for name in ("jammer_x", "jammer_y", "jammer_power", "jammer_height"):
            value = getattr(self, name)
            setattr(self, name, np.pad(value, ((0, 0), (0, extra)), constant_values=(
                self.scenario.jammer.height_m if name == "jammer_height" else 0.0)))

    def _place_driven_jammers(self, env_ids, steps: np.ndarray, position: np.ndarray,
                              flying: np.ndarray) -> None:
        """Each moving or scheduled jammer of ``env_ids`` where it is, and on or off, after
        ``steps`` (E,) steps of its episode; a reactive one hears the UAVs ``flying`` (E, J) at
        ``position`` (E, J, 2)."""
        for env in env_ids:
            jammers = self._driven.get(env)
            if jammers is None:
                continue
            t = float(steps[env]) * self.dt
            flying_xy = position[env][flying[env]]
            for slot, jammer in enumerate(jammers):
                x, y = position_at(jammer, t)
                self.jammer_x[env, slot], self.jammer_y[env, slot] = x, y
                self.jammer_power[env, slot] = (
                    jammer.power_w if transmits_at(jammer, t, flying_xy) else 0.0)

    def jammer(self, env_ids=slice(None)) -> tuple[JammerParams, ...]:
        """The jammers of the given environments, one per slot, as arrays shaped (n, 1) for
        (n, J) points."""
        return tuple(JammerParams(self.jammer_x[env_ids, slot, None],
                                  self.jammer_y[env_ids, slot, None],
                                  self.jammer_power[env_ids, slot, None],
                                  self.jammer_height[env_ids, slot, None])
                     for slot in range(self.jammer_x.shape[1]))

    def jammers_as_of(self, env: int, every_steps: int = 1,
                      late_steps: int = 0) -> tuple[tuple[float, ...], ...]:
        """As ``jammers_now``, each moving jammer where it was ``late_steps`` steps ago (at
        the episode's start at the earliest; negative: where it will be), held at the last
        multiple of ``every_steps`` steps into the episode (whether it transmits: as now)."""
        jammers = self._driven.get(env)
        if jammers is None or (every_steps == 1 and late_steps == 0):
            return self.jammers_now(env)
        steps = max(0, int(self.steps[env]) - late_steps)
        t = float(steps - steps % every_steps) * self.dt
        return tuple((*position_at(jammer, t), float(power), float(height))
                     for jammer, power, height in zip(jammers, self.jammer_power[env],
                                                      self.jammer_height[env], strict=False)
                     if power > 0)

    def jammers_now(self, env: int) -> tuple[tuple[float, float, float, float], ...]:
        """(x, y, power, height) of each jammer transmitting in environment ``env`` now."""
        return tuple((float(x), float(y), float(power), float(height)) for x, y, power, height
                     in zip(self.jammer_x[env], self.jammer_y[env], self.jammer_power[env],
                            self.jammer_height[env], strict=True) if power > 0)

    def reset(self, env_ids, seeds) -> None:
        """Start new episodes in ``env_ids``; episode ``k`` uses ``seeds[k]`` alone."""
        env_ids = np.atleast_1d(np.asarray(env_ids, dtype=np.int64))
        seeds = np.atleast_1d(np.asarray(seeds))
        for env, seed in zip(env_ids, seeds, strict=True):
            starts, goals = self.sampler.sample(int(seed), self.num_uavs)
            self.start[env] = starts
            self.position[env] = starts
            self.destination[env] = goals
            to_goal = goals - starts
            self.heading[env] = np.arctan2(to_goal[:, 1], to_goal[:, 0])
            self._receiver_noise[env] = np.random.default_rng([int(seed), _RECEIVER_NOISE])
        self.velocity[env_ids] = 0.0
        self.measured[env_ids] = False
        self.status[env_ids] = int(Outcome.ACTIVE)
        self.steps[env_ids] = 0
        self._place_driven_jammers(env_ids.tolist(), self.steps, self.position, self.active)
        reading = self.radio.evaluate(self.position[env_ids], self.jammer(env_ids))
        self.sinr_db[env_ids] = reading.sinr_db
        self.level[env_ids] = reading.level
        self.serving_gbs[env_ids] = reading.serving_gbs
        self.below_steps[env_ids] = (reading.level == 0).astype(np.int64)

    def _record_measurements(self, new_position: np.ndarray, active: np.ndarray
                             ) -> RadioReading:
        """Book what each receiver reported along the step to ``new_position``, and return the
        radio at the step's end: its last report point, so one evaluation serves both."""
        samples = self.measured_xy.shape[2]
        share = (np.arange(1, samples) / samples)[None, None, :, None]
        along = self.position[:, :, None] + share * (new_position - self.position)[:, :, None]
        self.measured_xy = np.concatenate([along, new_position[:, :, None]], axis=2)
        truth = self._radio_of_active(self.measured_xy, active)
        # Every UAV's receiver noise is drawn, so that each episode's stream of draws does not
        # depend on when its other UAVs ended their missions.
        reports = [self.radio.measured_reports(truth.sinr_db[env], self._receiver_noise[env])
                   for env in range(self.num_envs)]
        self.measured_level = np.stack([report.level for report in reports])
        self.measured_sinr_db = np.stack([report.sinr_db for report in reports])
        self.measured = active.copy()
        return RadioReading(*(field[:, :, -1] for field in truth))

    def _radio_of_active(self, xy: np.ndarray, active: np.ndarray) -> RadioReading:
        """The radio at points ``xy`` (E, J, ..., 2) of the active UAVs (``active`` (E, J)),
        each under its environment's jammer; zero for the others, whose missions ended and
        whose readings are never read again. Evaluating them anyway cost the city's 256-UAV
        episode about a fifth of its time, while its last few UAVs flew on alone."""
        env, uav = np.nonzero(active)
        points = xy[env, uav]
        some = self.radio.evaluate(points, self._jammers_of_points(env, points.ndim))
        every = RadioReading(*(np.zeros(xy.shape[:-1], dtype=field.dtype) for field in some))
        for whole, part in zip(every, some, strict=True):
            whole[env, uav] = part
        return every

    def _jammers_of_points(self, env: np.ndarray, ndim: int) -> list[JammerParams]:
        """Each jammer slot for points (n, ..., 2) of environments ``env`` (n,): its fields
        one value per point, or plain numbers when the world has one environment (the world
        process's), which spares a step the per-point copies."""
        if self.num_envs == 1:
            return [JammerParams(*map(float, slot)) for slot in zip(
                self.jammer_x[0], self.jammer_y[0], self.jammer_power[0], self.jammer_height[0],
                strict=True)]
        per_point = (-1,) + (1,) * (ndim - 2)
        return [JammerParams(*(np.asarray(field)[env].reshape(per_point) for field in slot))
                for slot in self.jammer()]

    # -- dynamics --------------------------------------------------------------------------
    @property
    def active(self) -> np.ndarray:
        return self.status == int(Outcome.ACTIVE)

    def step(self, speed: np.ndarray, heading: np.ndarray) -> StepResult:
        """Apply commanded speeds and headings (E, J); clipped to the kinematic limits."""
        active = self.active
        speed, heading = self.actions.clip(speed, heading, self.heading)
        speed = np.where(active, speed, 0.0)
        heading = np.where(active, heading, self.heading)
        velocity = velocity_of(speed, heading)
        dt = self.dt

        # Two UAVs farther apart than both steps and the discomfort band can neither touch nor
        # cost each other a reward: their gap counts as infinite.
        reach = (2 * (self.max_speed.max() * dt + self.radius.max())
                 + self.scenario.rewards.discomfort_distance_m + _PAIR_SLACK_M)
        env, first, second = near_pairs(self.position, active, reach)
        pair_gap = closest_approach(
            self.position[env, second] - self.position[env, first],
            velocity[env, second] - velocity[env, first],
            dt,
        ) - self.radius[env, first] - self.radius[env, second]
        gap = np.full(active.shape, np.inf)
        np.minimum.at(gap, (env, first), pair_gap)
        np.minimum.at(gap, (env, second), pair_gap)
        collided = active & (gap <= 0)
        arrived, new_position = arrivals(self.position, velocity, self.destination, dt,
                                         self.scenario.uav.arrival_tolerance_m,
                                         may_arrive=active & ~collided)
        self._place_driven_jammers(self._driven, self.steps + 1, new_position, active)
        reading = (self._record_measurements(new_position, active) if self.record_measurements
                   else self._radio_of_active(new_position, active))
        below, disconnected = disconnections(reading.level, self.below_steps,
                                             self.disconnection_limit,
                                             still_flying=active & ~collided & ~arrived)

        check_now = self.rewards.is_check_step(self.steps)[:, None]
        self.steps += 1
        reward = np.where(active, self.rewards.total(reading.level, check_now, gap, arrived), 0.0)
        timed_out = (
            active & ~collided & ~arrived & ~disconnected & (self.steps >= self.step_limit)[:, None]
        )
        status = self.status.copy()
        status[collided] = Outcome.COLLISION
        status[arrived] = Outcome.SUCCESS
        status[disconnected] = Outcome.DISCONNECTION
        status[timed_out] = Outcome.TIMEOUT

        self.position = np.where(active[..., None], new_position, self.position)
        self.velocity = np.where((status == Outcome.ACTIVE)[..., None], velocity, 0.0)
        self.heading = heading
        self.sinr_db = np.where(active, reading.sinr_db, self.sinr_db)
        self.level = np.where(active, reading.level, self.level).astype(np.int8)
        self.serving_gbs = np.where(active, reading.serving_gbs, self.serving_gbs)
        self.below_steps = np.where(active, below, self.below_steps)
        finished = active & (status != Outcome.ACTIVE)
        self.status = status
        # A UAV whose mission ended in this step uploads nothing more: over the bus its agent
        # hears nothing more from the world.
        self.measured &= ~finished
        return StepResult(reward, finished, ~self.active.any(axis=1))


def _check_jammer(jammer: JammerParams) -> None:
    """A NaN SINR would read as the best level (levels are found by sorting): refused here,
    where every caller's jammer enters the world."""
    if not all(np.isfinite(value).all() for value in jammer) or (
            np.min(jammer.power_w) < 0 or np.min(jammer.height_m) < 0):
        raise ValueError(f"jammer {tuple(jammer)}: position, power and height must be "
                         "finite, power and height >= 0")


def fleet_observation(world: VectorWorld) -> Observation:
    """What every UAV of the world observes, one row per UAV (env-major): of the others, only
    those that can change its decision (``nearby_others``), so that a step costs O(J log J)."""
    reach = float(decision_reach(world.scenario, world.radius.max()))
    others = nearby_others(world.position, world.active,
                           world.scenario.policy.observed_uavs, reach)
    return Observation.of_fleet(
        world.position, world.velocity, world.heading, world.destination, world.radius,
        world.max_speed, world.level, world.below_steps, world.active, world.steps, others,
    )
