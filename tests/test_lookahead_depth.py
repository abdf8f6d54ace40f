from __future__ import annotations

import math

import numpy as np
import pytest

from planning.features import EXTENDED_METHOD, MethodOptions, joint_state_size
from planning.maps import MAP_SPACING_M, LevelRaster, RasterMap
from planning.networks import ValueNetwork, value_architecture
from planning.reference import LookaheadPolicy
from shared.observation import Observation
from shared.radio import JammerParams, RadioModel
from shared.scenario import ScenarioError, load_scenario
from tests.conftest import write_variant
from tests.test_policy import untrained

JAMMED_BELOW_Y = 8.0  # the crafted map: no coverage south of this line, full coverage north


class BandMap:
    """Jammed (level 0) for y < JAMMED_BELOW_Y, connected (level 2) beyond it."""

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        return np.where(xy[..., 1] < JAMMED_BELOW_Y, 0, 2)

    def for_rows(self, rows: np.ndarray) -> BandMap:
        return self


class NearGoalValue(ValueNetwork):
    """Rewards being close to the destination (feature 4 = d_d), blind to connectivity."""

    def __call__(self, states):
        return 1.0 - 0.01 * states[..., 4]


class ProjectionValue(ValueNetwork):
    """A fixed smooth function of every feature: decisions that vary from UAV to UAV."""

    def __call__(self, states):
        weights = np.random.default_rng(7).normal(0.0, 0.03, states.shape[-1])
        return np.tanh(states.astype(np.float64) @ weights)


def scripted(kind: type[ValueNetwork], size: int, method: dict) -> ValueNetwork:
    return kind(value_architecture(size, 2.0, method), untrained(size, method).tensors)


def jammed_uav(below_steps: int) -> Observation:
    """A lone UAV at the origin heading east to (40, 0), already below T_s for some steps."""
    return Observation(
        position=np.zeros((1, 2)), velocity=np.zeros((1, 2)), heading=np.zeros(1),
        destination=np.array([[40.0, 0.0]]), radius=np.ones(1), max_speed=np.full(1, 5.0),
        level=np.zeros(1, dtype=np.int64), below_steps=np.array([below_steps]),
        step=np.ones(1, dtype=np.int64), others_position=np.zeros((1, 0, 2)),
        others_velocity=np.zeros((1, 0, 2)), others_radius=np.zeros((1, 0)),
        others_present=np.zeros((1, 0), dtype=bool))


def fly(policy: LookaheadPolicy, observation: Observation, steps: int) -> list[int]:
    """Consecutive steps below T_s after each of ``steps`` decisions on the band map."""
    below = []
    for _ in range(steps):
        decision = policy.decide(observation, BandMap())
        move = decision.speed[0] * np.array([math.cos(decision.heading[0]),
                                             math.sin(decision.heading[0])])
        position = observation.position + move
        level = BandMap().level_at(position)
        below_steps = np.where(level == 0, observation.below_steps + 1, 0)
        below.append(int(below_steps[0]))
        observation = Observation(**{**vars(observation), "position": position,
                                     "heading": decision.heading, "level": level,
                                     "below_steps": below_steps, "step": observation.step + 1})
    return below


@pytest.mark.parametrize("depth", [2, 3])
def test_a_deeper_search_sees_the_trap_that_one_step_flies_into(scenario, depth):
    # Below T_s for n_t - 1 steps, at most two more before the mission is lost. North of
    # the line is 8 m away; with 5 m steps and 45 degree turns only full speed at a full left
    # turn and then another one gets there: every other first move is a trap.
    limit = scenario.timing.disconnection_limit_steps
    method = MethodOptions(disconnection_memory=True, disconnection_reward=-1.0)
    network = scripted(NearGoalValue, joint_state_size(scenario, method), method._asdict())
    start = jammed_uav(limit - 1)
    shallow = LookaheadPolicy(scenario, network, lookahead_depth=1).decide(start, BandMap())
    deep = LookaheadPolicy(scenario, network, lookahead_depth=depth).decide(start, BandMap())
    max_turn = math.radians(scenario.uav.turn_rate_deg_s) * scenario.timing.step_s
    assert abs(shallow.heading[0]) < max_turn  # toward the goal, into the trap
    assert deep.speed[0] == scenario.uav.max_speed_mps
    assert math.isclose(deep.heading[0], max_turn)
    assert max(fly(LookaheadPolicy(scenario, network, lookahead_depth=1), start, 3)) > limit
    assert fly(LookaheadPolicy(scenario, network, lookahead_depth=depth), start, 3)[-1] == 0


def jammed_raster_map(scenario, rows: int) -> RasterMap:
    radio = RadioModel(scenario)
    jammer = JammerParams(0.0, 0.0, 1.0, scenario.jammer.height_m)
    raster = LevelRaster.sample(scenario, lambda xy: radio.evaluate(xy, jammer).level,
                                MAP_SPACING_M)
    return RasterMap(scenario, [raster], np.zeros(rows, dtype=np.int64))


def random_fleet(rng: np.random.Generator, envs: int = 12, uavs: int = 4) -> Observation:
    shape = (envs, uavs)
    return Observation.of_fleet(
        rng.uniform(-45, 45, shape + (2,)), rng.uniform(-3, 3, shape + (2,)),
        rng.uniform(-3, 3, shape), rng.uniform(-45, 45, shape + (2,)), np.ones(shape),
        np.full(shape, 5.0), rng.integers(0, 3, shape), rng.integers(0, 3, shape),
        np.ones(shape, dtype=bool), rng.integers(0, 9, envs))


@pytest.fixture(scope="module")
def fleet_case():
    scenario = load_scenario()
    method = EXTENDED_METHOD._asdict()
    network = scripted(ProjectionValue, joint_state_size(scenario, EXTENDED_METHOD), method)
    fleet = random_fleet(np.random.default_rng(0))
    return scenario, network, fleet, jammed_raster_map(scenario, len(fleet))


# The one-step lookahead's choices on fleet_case, recorded with the numpy lookahead (then
# shared/policy.py) as of commit 2abe04e (before the deeper search existed).
ONE_STEP_ACTIONS = [28, 0, 45, 27, 45, 44, 38, 28, 37, 0, 38, 43, 2, 8, 36, 10, 10, 40, 44, 0,
                    1, 0, 45, 0, 0, 28, 38, 38, 45, 6, 37, 37, 37, 37, 45, 39, 37, 45, 9, 0, 7,
                    37, 0, 0, 0, 9, 39, 14]


def test_depth_one_decides_as_the_one_step_lookahead_did(fleet_case):
    scenario, network, fleet, radio_map = fleet_case
    policy = LookaheadPolicy(scenario, network, lookahead_depth=1,
                             others_model="constant_velocity")
    np.testing.assert_array_equal(policy.decide(fleet, radio_map).action, ONE_STEP_ACTIONS)


def test_the_papers_method_flies_as_published_whatever_the_scenario_says(fleet_case):
    scenario, _, fleet, radio_map = fleet_case
    # The shipped defaults, which the paper's method must not read.
    assert scenario.policy.lookahead_depth == 2
    assert scenario.policy.others_model == "reciprocal"
    paper = scripted(ProjectionValue, joint_state_size(scenario), {})
    published = LookaheadPolicy(scenario, paper, lookahead_depth=1,
                                others_model="constant_velocity").decide(fleet, radio_map)
    default = LookaheadPolicy(scenario, paper).decide(fleet, radio_map)
    deeper = LookaheadPolicy(scenario, paper, lookahead_depth=2).decide(fleet, radio_map)
    np.testing.assert_array_equal(default.action, published.action)
    assert np.any(deeper.action != published.action)  # the override still searches


def test_only_uavs_at_risk_decide_differently_at_depth_two(fleet_case):
    scenario, network, fleet, radio_map = fleet_case
    shallow = LookaheadPolicy(scenario, network, lookahead_depth=1).decide(fleet, radio_map)
    deep = LookaheadPolicy(scenario, network, lookahead_depth=2).decide(fleet, radio_map)
    # Connected now (level 2) and the one-step move stays connected: nothing to search for.
    move = shallow.speed[:, None] * np.stack([np.cos(shallow.heading),
                                              np.sin(shallow.heading)], axis=-1)
    landing = radio_map.level_at((fleet.position + move)[:, None])[:, 0]
    safe = (fleet.level == 2) & (landing == 2)
    assert 0 < safe.sum() < len(fleet)
    np.testing.assert_array_equal(deep.action[safe], shallow.action[safe])
    np.testing.assert_array_equal(deep.value[safe], shallow.value[safe])
    assert np.any(deep.action[~safe] != shallow.action[~safe])


@pytest.mark.parametrize("depth", ["0", "4", "1.5"])
def test_a_lookahead_depth_out_of_range_is_refused(tmp_path, depth):
    path = write_variant(tmp_path, "lookahead_depth = 2", f"lookahead_depth = {depth}")
    with pytest.raises(ScenarioError, match="policy.lookahead_depth"):
        load_scenario(path)


def test_an_override_below_one_is_refused(scenario):
    network = untrained(joint_state_size(scenario))
    with pytest.raises(ValueError, match="lookahead_depth"):
        LookaheadPolicy(scenario, network, lookahead_depth=0)
