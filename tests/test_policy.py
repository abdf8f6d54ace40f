from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cloud_service.rollout import LookaheadController, perfect_maps
from cloud_service.torch_networks import TorchValueNetwork
from planning.features import EXTENDED_METHOD, joint_state_size
from planning.maps import TrueMap
from planning.networks import ValueNetwork, load_network, value_architecture
from planning.reference import LookaheadPolicy, inside_safe_cells, smallest_gaps
from shared.kinematics import closest_approach, velocity_of
from shared.observation import CELL_CLEARANCE_M, Observation
from shared.outcomes import Outcome
from shared.radio import JammerParams, RadioModel
from shared.shipped import EXTENDED_VALUE_NET
from tests import float32_bounds as bounds
from world_sim.core import VectorWorld, episode_seed, fleet_observation


def untrained(size: int, method: dict | None = None) -> ValueNetwork:
    """A value network as training starts it (torch's initialization, seeded)."""
    torch.manual_seed(0)
    return TorchValueNetwork(size, 2.0, method).inference()


def scripted(kind: type[ValueNetwork], size: int, method: dict | None = None) -> ValueNetwork:
    """A value network whose values ``kind`` computes by a rule instead of by its layers."""
    return kind(value_architecture(size, 2.0, method), untrained(size, method).tensors)


class DistanceValue(ValueNetwork):
    """A value that only rewards being close to the destination (feature 4 = d_d)."""

    def __call__(self, states):
        return -0.05 * states[..., 4]


def lone_uav(heading, destination, position=(12.5, 0.0)):
    return Observation(
        position=np.array([position]),
        velocity=np.zeros((1, 2)),
        heading=np.array([heading]),
        destination=np.array([destination]),
        radius=np.ones(1),
        max_speed=np.full(1, 5.0),
        level=np.array([2]),
        below_steps=np.array([0]),
        step=np.array([1]),
        others_position=np.zeros((1, 0, 2)),
        others_velocity=np.zeros((1, 0, 2)),
        others_radius=np.zeros((1, 0)),
        others_present=np.zeros((1, 0), dtype=bool),
    )


def test_in_an_empty_world_the_policy_heads_to_the_goal(scenario):
    policy = LookaheadPolicy(scenario, scripted(DistanceValue, joint_state_size(scenario)))
    radio_map = TrueMap(RadioModel(scenario), None)
    for goal_angle in np.linspace(-math.pi, math.pi, 9):
        destination = (12.5 + 30 * math.cos(goal_angle), 30 * math.sin(goal_angle))
        decision = policy.decide(lone_uav(goal_angle, destination), radio_map)
        assert decision.speed[0] == scenario.uav.max_speed_mps
        assert abs((decision.heading[0] - goal_angle + math.pi) % (2 * math.pi) - math.pi) < 1e-9


def test_turn_limit_bounds_the_chosen_heading(scenario):
    policy = LookaheadPolicy(scenario, scripted(DistanceValue, joint_state_size(scenario)))
    decision = policy.decide(lone_uav(0.0, (12.5, 30.0)), TrueMap(RadioModel(scenario), None))
    assert math.isclose(decision.heading[0], math.radians(scenario.uav.turn_rate_deg_s))


def test_arrival_is_taken_when_within_reach(scenario):
    policy = LookaheadPolicy(scenario, scripted(DistanceValue, joint_state_size(scenario)))
    decision = policy.decide(lone_uav(0.0, (15.0, 0.0)), TrueMap(RadioModel(scenario), None))
    assert math.isclose(decision.value[0], scenario.rewards.arrival + scenario.rewards.step)


def test_batched_decisions_equal_one_by_one(scenario):
    policy = LookaheadPolicy(scenario, untrained(joint_state_size(scenario)))
    radio_map = TrueMap(RadioModel(scenario), None)
    rng = np.random.default_rng(0)
    active = np.ones((2, 3), dtype=bool)
    fleet = Observation.of_fleet(
        rng.uniform(-40, 40, (2, 3, 2)), rng.uniform(-3, 3, (2, 3, 2)),
        rng.uniform(-3, 3, (2, 3)), rng.uniform(-40, 40, (2, 3, 2)), np.ones((2, 3)),
        np.full((2, 3), 5.0), rng.integers(0, 3, (2, 3)), rng.integers(0, 2, (2, 3)), active,
        np.array([0, 1]),
    )
    together = policy.decide(fleet, radio_map)
    for row in range(len(fleet)):
        alone = policy.decide(fleet.select(np.array([row])), radio_map)
        assert alone.action[0] == together.action[row]


def test_raster_map_agrees_with_the_exact_map(scenario):
    from cloud_service.rollout import perfect_maps
    from planning.maps import MAP_SPACING_M
    from world_sim.core import VectorWorld

    world = VectorWorld(scenario, 2, 2)
    world.reset([0, 1], [3, 4])
    world.set_jammer([1], None)
    maps = perfect_maps(scenario)(world, np.arange(4))
    rng = np.random.default_rng(0)
    xy = rng.uniform(-50, 50, (4, 500, 2))
    radio = RadioModel(scenario)
    jammer = JammerParams(*(float(v[0, 0]) for v in world.jammer([0])[0]))
    exact = np.stack([radio.evaluate(xy[row], jammer if row < 2 else None).level
                      for row in range(4)])
    assert (maps.level_at(xy) == exact).mean() > 0.98
    # At grid nodes the raster is exact.
    node = np.array([[[MAP_SPACING_M * 20, -MAP_SPACING_M * 7]]] * 4)
    want = [radio.evaluate(node[0, 0], jammer).level] * 2 + [radio.evaluate(node[0, 0]).level] * 2
    np.testing.assert_array_equal(maps.level_at(node)[:, 0], want)


def test_a_value_network_of_the_wrong_input_size_is_refused(scenario):
    import pytest

    from planning.networks import WeightsError

    with pytest.raises(WeightsError, match="features"):
        LookaheadPolicy(scenario, untrained(joint_state_size(scenario) + 1))


def beside_another(other_offset):
    """A UAV heading east to a goal 30 m away, and a hovering UAV at ``other_offset``."""
    return dataclasses.replace(
        lone_uav(0.0, (42.5, 0.0)),
        others_position=np.array([[np.add((12.5, 0.0), other_offset)]]),
        others_velocity=np.zeros((1, 1, 2)), others_radius=np.ones((1, 1)),
        others_present=np.ones((1, 1), dtype=bool))


def gap_after(decision, observation) -> float:
    moved = observation.position[0] + 1.0 * decision.speed[0] * np.array(
        [math.cos(decision.heading[0]), math.sin(decision.heading[0])])
    return float(np.hypot(*(moved - observation.others_position[0, 0])) - 2.0)


class NearGoalValue(ValueNetwork):
    """Rewards being close to the destination, and never worse than a collision."""

    def __call__(self, states):
        return 1.0 - 0.01 * states[..., 4]


def test_inside_the_safety_margin_a_uav_moves_on_instead_of_hovering_for_ever(scenario):
    margin = {"collision_margin_m": 3.5}
    policy = LookaheadPolicy(scenario, scripted(NearGoalValue, joint_state_size(scenario), margin))
    radio_map = TrueMap(RadioModel(scenario), None)
    # 2.5 m to the side: a gap of 0.5 m, well inside the margin. Every move, hovering
    # included, passes closer than the margin, yet flying on to the goal opens the gap.
    side = beside_another((0.0, 2.5))
    decision = policy.decide(side, radio_map)
    assert decision.speed[0] == scenario.uav.max_speed_mps and decision.heading[0] == 0.0
    assert gap_after(decision, side) > 0.5
    # 4 m straight ahead (gap 2 m): flying on would close the gap, so the UAV does not.
    ahead = beside_another((4.0, 0.0))
    decision = policy.decide(ahead, radio_map)
    assert gap_after(decision, ahead) >= 2.0 - 0.01


def test_a_safe_cell_stops_a_uav_half_way_less_its_radius(scenario):
    # A hovering UAV 8 m ahead: the cell's edge is 8/2 - 1 = 3 m ahead. A constant-velocity
    # prediction alone lets the UAV fly the full 5 m (gap 1 m at the end).
    ahead = beside_another((8.0, 0.0))
    radio_map = TrueMap(RadioModel(scenario), None)
    advance = {}
    for safe in (False, True):
        network = scripted(NearGoalValue, joint_state_size(scenario), {"safe_cells": safe})
        decision = LookaheadPolicy(scenario, network).decide(ahead, radio_map)
        advance[safe] = decision.speed[0] * math.cos(decision.heading[0])
    assert advance[False] > 3.0
    assert 0.0 < advance[True] <= 3.0 - CELL_CLEARANCE_M + 1e-9


@settings(max_examples=300, deadline=None)
@given(
    st.tuples(*[st.floats(-8.0, 8.0)] * 4),  # B's offset from A, A's and B's moves
    st.tuples(*[st.floats(-5.0, 5.0)] * 4),
    st.floats(0.5, 2.0),
    st.floats(0.5, 2.0),
)
def test_two_uavs_inside_their_cells_never_touch(offsets, moves, radius_a, radius_b):
    b = np.array(offsets[:2])
    # Each starts inside its own cell, half their distance less its radius and the clearance
    # (with unequal radii that asks more than r_a + r_b apart: the cells split the gap at its
    # middle, as every scenario's UAVs share one radius).
    assume(np.hypot(*b) / 2 > max(radius_a, radius_b) + CELL_CLEARANCE_M)
    move_a, move_b = np.array(moves[:2]), np.array(moves[2:])
    a = np.zeros(2)
    inside_a = inside_safe_cells(a[None], (a + move_a)[None, None], np.array([radius_a]),
                                 b[None, None], np.ones((1, 1), bool))[0, 0]
    inside_b = inside_safe_cells(b[None], (b + move_b)[None, None], np.array([radius_b]),
                                 a[None, None], np.ones((1, 1), bool))[0, 0]
    if inside_a and inside_b:
        assert closest_approach(b - a, move_b - move_a, 1.0) > radius_a + radius_b


def test_a_crowd_keeping_to_its_cells_has_no_collision(scenario):
    """Six UAVs packed into a 16 m square, hovering or flying in random directions, steered
    by an untrained network: in the world's own collision check, keeping to the cells must
    avoid every collision that the same crowd has without them."""
    envs, uavs = 100, 6
    rng = np.random.default_rng(3)
    start = np.zeros((envs, uavs, 2))
    for env in range(envs):
        placed = 0
        while placed < uavs:
            candidate = rng.uniform(-8.0, 8.0, 2)
            if np.all(np.hypot(*(start[env, :placed] - candidate).T) > 2.05):
                start[env, placed] = candidate
                placed += 1
    heading = rng.uniform(-math.pi, math.pi, (envs, uavs))
    speed = rng.choice([0.0, scenario.uav.max_speed_mps], (envs, uavs))
    destination = rng.uniform(-40.0, 40.0, (envs, uavs, 2))
    collisions = {}
    for safe in (False, True):
        options = EXTENDED_METHOD._replace(safe_cells=safe)._asdict()
        network = untrained(joint_state_size(scenario, EXTENDED_METHOD), options)
        controller = LookaheadController(LookaheadPolicy(scenario, network),
                                         perfect_maps(scenario))
        world = VectorWorld(scenario, envs, uavs)
        world.reset(np.arange(envs), np.arange(envs))
        world.position, world.heading = start.copy(), heading.copy()
        world.velocity = velocity_of(speed, heading)
        world.destination = destination.copy()
        for _ in range(10):
            world.step(*controller.act(world))
        collisions[safe] = int(np.count_nonzero(world.status == Outcome.COLLISION))
    assert collisions[False] > 0
    assert collisions[True] == 0


def test_gaps_left_out_are_those_no_reward_reads(scenario):
    """A crowd in a 40 m square flying every action: the lookahead's gaps agree with every
    pair's closest approach wherever R_c or a collision reads them (under the discomfort
    distance), and the pairs it leaves out are farther than that."""
    policy = LookaheadPolicy(scenario, untrained(joint_state_size(scenario, EXTENDED_METHOD),
                                                 EXTENDED_METHOD._asdict()))
    rng = np.random.default_rng(5)
    envs, uavs = 50, 6
    fleet = Observation.of_fleet(
        rng.uniform(-20, 20, (envs, uavs, 2)), rng.uniform(-5, 5, (envs, uavs, 2)),
        rng.uniform(-3, 3, (envs, uavs)), rng.uniform(-40, 40, (envs, uavs, 2)),
        rng.uniform(0.5, 1.5, (envs, uavs)), np.full((envs, uavs), 5.0),
        np.full((envs, uavs), 2), np.zeros((envs, uavs)), rng.random((envs, uavs)) < 0.9,
        np.zeros(envs, dtype=int),
    )
    _, _, velocity = policy.actions.moves(fleet.heading)
    got = policy._gaps(fleet, velocity, fleet.others_velocity)
    every_pair = smallest_gaps(fleet.position[:, None], velocity, fleet.radius[:, None],
                               fleet.others_position[:, None], fleet.others_velocity[:, None],
                               fleet.others_radius[:, None], fleet.others_present[:, None],
                               scenario.timing.step_s, policy._margins(fleet)[:, None])
    read = every_pair < scenario.rewards.discomfort_distance_m
    assert read.any() and (~read).any() and np.isinf(got).any()
    assert np.array_equal(got[read], every_pair[read])
    assert np.all(got[~read] >= scenario.rewards.discomfort_distance_m)


class TorchForward(ValueNetwork):
    """The values of a network's torch module, as training computes them."""

    def __init__(self, network: ValueNetwork):
        super().__init__(network.architecture(), network.tensors)
        self.module = TorchValueNetwork(network.input_size, network.value_scale, network.method)
        self.module.assign(network)

    def __call__(self, states):
        with torch.inference_mode():
            return self.module(torch.from_numpy(states)).numpy()


class ExactForward(ValueNetwork):
    """A network's exact (float64) values; ``bound`` is the largest float32 bound
    (tests/float32_bounds.py) of any value it gave."""

    def __init__(self, network: ValueNetwork):
        super().__init__(network.architecture(), network.tensors)
        self.network, self.bound = network, 0.0

    def __call__(self, states):
        values = bounds.values(self.network, states)
        self.bound = max(self.bound, float(values.bound.max()))
        return values.exact


def test_the_numpy_and_torch_forwards_decide_as_the_exact_values_do(scenario):
    """The shipped extended network over a fleet in flight, one step ahead: with numpy's
    forward and the torch module's, every UAV takes the action the exact values give it and
    scores it within float32's bound, but for a tie: two actions whose exact scores, R +
    gamma V, are closer than the two values' float32 bounds together."""
    network, _ = load_network(EXTENDED_VALUE_NET)
    exact_values = ExactForward(network)
    policies = [LookaheadPolicy(scenario, forward, lookahead_depth=1)
                for forward in (network, TorchForward(network), exact_values)]
    exact_policy = policies[-1]
    maps = perfect_maps(scenario)
    world = VectorWorld(scenario, 16, 4)
    world.reset(np.arange(16), [episode_seed(5, k) for k in range(16)])
    decided, ties = 0, 0
    for _ in range(8):
        rows = np.flatnonzero(world.active.ravel())
        seen, radio_map = fleet_observation(world).select(rows), maps(world, rows)
        exact = exact_policy.decide(seen, radio_map)
        every = exact_policy.leaf_scores(exact_policy.expand(
            seen.nearest_neighbours(exact_policy.observed_uavs), radio_map))
        margin = exact_policy.gamma * exact_values.bound
        uav = np.arange(rows.size)
        for policy in policies[:2]:
            got = policy.decide(seen, radio_map)
            same = got.action == exact.action
            tie = np.abs(every[uav, got.action] - every[uav, exact.action]) <= 2 * margin
            assert (same | tie).all()
            assert (np.abs(got.value - exact.value)[same] <= margin).all()
            ties += int((~same).sum())
        decided += rows.size
        world.step(*LookaheadController(policies[0], maps).act(world))
    assert decided > 400 and ties <= 0.01 * decided


def test_raster_maps_keep_the_recent_settings_and_never_one_in_flight(scenario):
    """A long run meets hundreds of jammer settings: only the most recent stay cached, and a
    setting evicted and met again gives the same raster."""
    maps = perfect_maps(scenario)
    maps.kept = 2
    settings = [JammerParams(x, 0.0, 1.0, scenario.jammer.height_m) for x in (-20.0, 0.0, 20.0)]
    first = maps.raster(settings[0]).levels.copy()
    for setting in settings[1:]:
        maps.raster(setting)
    assert list(maps.cache) == [(tuple(settings[1]),), (tuple(settings[2]),)]
    np.testing.assert_array_equal(maps.raster(settings[0]).levels, first)
    assert len(maps.cache) == 2

    world = VectorWorld(scenario, 3, 2)  # three environments, three settings in flight
    world.reset(np.arange(3), [episode_seed(0, k) for k in range(3)])
    for env, setting in enumerate(settings):
        world.set_jammer([env], setting)
    maps(world, np.arange(6))
    assert len(maps.cache) == 3 and maps.kept >= 3
