"""The compiled planner (planning.lookahead) against its reference (planning.reference) on
the same rows: how far their scores may differ, derived from float32 arithmetic, and how many
rows break the agreement rule. ``tests/test_compiled_planner.py`` asserts it on a few thousand
rows; ``benchmarks/bench_planner_agreement.py`` counts it over 100,000 and more."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields

import numpy as np

from cloud_service.rollout import LookaheadController, MapFor
from planning.features import ABSENT_DISTANCE, OTHER_FEATURES, OWN_FEATURES, MethodOptions
from planning.lookahead import CompiledLookahead
from planning.maps import RasterMap
from planning.networks import ValueNetwork
from planning.reference import LookaheadPolicy
from shared.observation import Observation
from shared.paper import TABLE_I_JAMMERS, jammer_params
from tests import float32_bounds as bounds
from world_sim.core import VectorWorld, episode_seed, fleet_observation

# Either planner's value of a state against exact arithmetic on the reference's float32 state
# (tests/float32_bounds.py: the standardization, the dense layers in any order of summation,
# tanh and the scale), with the planners' own features off by one float32 rounding (u |x|,
# u = 2^-24) of float64 values computed in up to 16 operations on quantities below 2^11 m,
# each off by half an ulp of 2^11 at most (FEATURE_SLACK); the features both copy (a UAV's
# radius, top speed, level, steps below T_s, the constant zeros, an absent other's block) are
# the same exactly. A score R + gamma V differs by gamma (or, searched deeper, gamma^2 <=
# gamma) times the two planners' value errors, plus the float64 rounding of the rewards:
# REWARD_SLACK.
FEATURE_SLACK = 16 * 2.0**-42
REWARD_SLACK = 1e-12


def value_error_bound(network: ValueNetwork, states: np.ndarray) -> np.ndarray:
    """The most either planner's value of each of ``states`` (K, F) can differ from exact
    (K,), the reference's float32 states standing in for the exact features."""
    rounded = np.where(computed_features(network, states),
                       bounds.UNIT_ROUNDOFF * np.abs(states.astype(np.float64))
                       + FEATURE_SLACK, 0.0)
    return bounds.values(network, states, rounded).bound


def computed_features(network: ValueNetwork, states: np.ndarray) -> np.ndarray:
    """Which features (K, F) the planners compute, rather than copy (see above)."""
    own, width = len(OWN_FEATURES), len(OTHER_FEATURES)
    others = (states.shape[1] - own - 1 - sum(
        MethodOptions.from_dict(network.method)[:2])) // width
    computed = np.ones(states.shape, dtype=bool)
    computed[:, [OWN_FEATURES.index(name) for name in
                 ("dest_y", "dest_azimuth", "radius", "max_speed")]] = False
    computed[:, own + width * others:] = False  # level, steps below, and the route distance:
    computed[:, -1] |= MethodOptions.from_dict(network.method).route_distance  # computed
    for k in range(others):
        block = states[:, own + k * width : own + (k + 1) * width]
        absent = (block[:, 0] == -ABSENT_DISTANCE) & (block[:, 1:4] == 0).all(axis=1)
        computed[absent, own + k * width : own + (k + 1) * width] = False
    return computed


def score_bound(scenario, network: ValueNetwork, asked: list[np.ndarray],
                searched: np.ndarray) -> np.ndarray:
    """How far the two planners' scores of each row may differ (N,): the reference asks for
    the one-step states of every row first (N x actions), then for the leaves of the deeper
    search, whose bound the rows ``searched`` deeper (N,) share."""
    one_step = value_error_bound(network, asked[0]).reshape(len(searched), -1).max(axis=1)
    deeper = max((value_error_bound(network, leaves).max() for leaves in asked[1:]),
                 default=0.0)
    values = np.where(searched, np.maximum(one_step, deeper), one_step)
    return scenario.policy.gamma * 2 * values + REWARD_SLACK


class Recording(ValueNetwork):
    """A network's own values, keeping every state the planner asks about."""

    def __init__(self, network: ValueNetwork):
        super().__init__(network.architecture(), network.tensors)
        self.network = network
        self.states: list[np.ndarray] = []

    def __call__(self, states):
        self.states.append(states.reshape(-1, states.shape[-1]))
        return self.network(states)


@dataclass
class Agreement:
    """Counts over rows decided by both planners. The rule: every score within the bound
    (and the same moves ruled out), so the same action wherever the reference's two best
    scores are further apart than twice the bound (the tie margin), and the chosen values
    within the bound. ``broken`` counts each way a row can break it."""

    rows: int = 0
    tied: int = 0  # the reference's two best scores within the tie margin
    different: int = 0  # another action, ties included
    searched_deeper: int = 0
    scores_beyond_bound: int = 0
    moves_ruled_out_apart: int = 0
    different_beyond_ties: int = 0
    values_beyond_bound: int = 0
    bound: float = 0.0  # the largest score bound met

    def __iadd__(self, other: Agreement) -> Agreement:
        for part in fields(self):
            mine, theirs = getattr(self, part.name), getattr(other, part.name)
            setattr(self, part.name, max(mine, theirs) if part.name == "bound"
                    else mine + theirs)
        return self

    def broken(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in (
            "scores_beyond_bound", "moves_ruled_out_apart", "different_beyond_ties",
            "values_beyond_bound")}


def agreement(scenario, network: ValueNetwork, observation: Observation, radio_map: RasterMap,
              **options) -> Agreement:
    """Both planners, ``options`` as ``LookaheadPolicy`` takes them, on the same rows."""
    recording = Recording(network)
    _, want, _ = LookaheadPolicy(scenario, recording, **options).scored(observation, radio_map)
    got = CompiledLookahead(scenario, network, **options).decide_scored(observation, radio_map)
    searched = (~np.isfinite(want) & got.allowed).any(axis=1)
    bound = score_bound(scenario, network, recording.states, searched)
    finite = np.isfinite(want)
    apart = (np.isfinite(got.score) != finite).any(axis=1)
    both = finite & np.isfinite(got.score)
    excess = np.zeros(want.shape)
    excess[both] = np.abs(got.score[both] - want[both])
    top_two = -np.sort(-want, axis=1)[:, :2]
    tied = top_two[:, 0] - top_two[:, 1] <= 2 * bound
    chosen = want.argmax(axis=1)
    different = got.decision.action != chosen
    rows = np.arange(len(observation))
    value_error = np.abs(got.decision.value - want[rows, got.decision.action])
    return Agreement(
        rows=len(observation), tied=int(tied.sum()), different=int(different.sum()),
        searched_deeper=int(searched.sum()),
        scores_beyond_bound=int((excess > bound[:, None]).any(axis=1).sum()),
        moves_ruled_out_apart=int(apart.sum()),
        different_beyond_ties=int((different & ~tied).sum()),
        values_beyond_bound=int((~(value_error <= bound)).sum()),
        bound=float(bound.max(initial=0.0)))


def flown_states(scenario, network: ValueNetwork, map_for: MapFor, envs: int, steps: int,
                 seed: int, jam: Callable[[VectorWorld, int], None], epsilon: float = 0.0,
                 **options) -> Iterator[tuple[Observation, RasterMap]]:
    """Every step's observations of ``envs`` fleets of the scenario's UAVs flown by the
    compiled planner (``options``, exploring with ``epsilon``) on the maps of ``map_for``,
    ``jam(world, env)`` setting each environment's jammers, and the maps they were decided
    on: at most ``steps`` steps, or until every mission has ended."""
    policy = CompiledLookahead(scenario, network, **options)
    controller = LookaheadController(policy, map_for, epsilon, np.random.default_rng(seed))
    world = VectorWorld(scenario, envs, scenario.missions.uav_count)
    world.reset(np.arange(envs), [episode_seed(seed, k) for k in range(envs)])
    for env in range(envs):
        jam(world, env)
    for _ in range(steps):
        rows = np.flatnonzero(world.active.ravel())
        if rows.size == 0:
            return
        yield fleet_observation(world).select(rows), controller.map_for(world, rows)
        world.step(*controller.act(world))


def table_one_jammers(world: VectorWorld, env: int) -> None:
    """Each environment on one of Table I's jammers."""
    world.set_jammer([env], jammer_params(world.scenario, TABLE_I_JAMMERS[env % 4]))
