"""The lookahead's reciprocal model of the others' next move (policy.others_model)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from planning.features import EXTENDED_METHOD, joint_state_size
from planning.reference import LookaheadPolicy, reciprocal_velocities
from shared.observation import Observation
from shared.scenario import ScenarioError, load_scenario
from tests.conftest import variant, write_variant
from tests.test_lookahead_depth import ProjectionValue, scripted

RADIUS = 1.0
MAX_SPEED = 5.0


def pair_observation(positions: np.ndarray, velocities: np.ndarray) -> Observation:
    """Two UAVs, rows in the given order, each seeing the other."""
    positions, velocities = np.asarray(positions, float), np.asarray(velocities, float)
    return Observation(
        position=positions, velocity=velocities, heading=np.zeros(2),
        destination=np.zeros((2, 2)), radius=np.full(2, RADIUS),
        max_speed=np.full(2, MAX_SPEED), level=np.full(2, 2), below_steps=np.zeros(2, int),
        step=np.ones(2, int), others_position=positions[::-1, None],
        others_velocity=velocities[::-1, None], others_radius=np.full((2, 1), RADIUS),
        others_present=np.ones((2, 1), dtype=bool))


def test_head_on_each_predicts_the_other_to_take_half_the_turn_to_its_right(scenario):
    """10 m apart at 5 m/s each, head on: within the 2 s horizon they would meet. The relative
    velocity's shortest way out of the collision cone is onto its tangent, at angle
    asin((r_a + r_b) / d) to the line of centres, a distance |v_rel| sin of it away; each
    UAV takes half, both to their right (the passing side ORCA picks for both on a tie)."""
    distance, speed = 10.0, 5.0
    observation = pair_observation([[0.0, 0.0], [distance, 0.0]],
                                   [[speed, 0.0], [-speed, 0.0]])
    predicted = reciprocal_velocities(observation, scenario.policy.orca_time_horizon_s,
                                      scenario.timing.step_s)[:, 0]
    sin = 2 * RADIUS / distance
    half = 2 * speed * sin / 2
    cos = math.sqrt(1 - sin**2)
    # Row 0 (heading east) predicts row 1 (heading west), and row 1 predicts row 0.
    np.testing.assert_allclose(predicted[0], [-speed + half * sin, half * cos], atol=1e-9)
    np.testing.assert_allclose(predicted[1], [speed - half * sin, -half * cos], atol=1e-9)
    turn = predicted - observation.others_velocity[:, 0]
    heading = observation.others_velocity[:, 0]
    assert np.all(heading[:, 0] * turn[:, 1] - heading[:, 1] * turn[:, 0] < 0)  # to the right


def test_a_uav_on_no_collision_course_is_predicted_at_its_velocity(scenario):
    observation = pair_observation([[0.0, 0.0], [10.0, 0.0]], [[0.0, 3.0], [0.0, -3.0]])
    predicted = reciprocal_velocities(observation, scenario.policy.orca_time_horizon_s,
                                      scenario.timing.step_s)
    np.testing.assert_array_equal(predicted, observation.others_velocity)


coordinate = st.floats(-6.0, 6.0)
slow = st.floats(-1.5, 1.5)  # slow enough that no prediction reaches the top speed


@settings(max_examples=200, deadline=None)
@given(st.tuples(coordinate, coordinate, coordinate, coordinate),
       st.tuples(slow, slow, slow, slow))
def test_two_uavs_swapped_give_swapped_mirrored_predictions(positions, velocities):
    positions = np.reshape(positions, (2, 2))
    velocities = np.reshape(velocities, (2, 2))
    # UAVs at one point (to rounding) collided long ago; ORCA parts those by agent order.
    assume(np.hypot(*(positions[0] - positions[1])) > 1e-6)
    forward = reciprocal_velocities(pair_observation(positions, velocities), 2.0, 1.0)[:, 0]
    swapped = reciprocal_velocities(pair_observation(positions[::-1], velocities[::-1]),
                                    2.0, 1.0)[:, 0]
    np.testing.assert_array_equal(swapped, forward[::-1])
    # Reciprocity: what UAV 0 expects UAV 1 to change is the opposite of what UAV 1 expects
    # UAV 0 to change, so the two expected turns make up one avoidance between them.
    change = forward - velocities[::-1]
    np.testing.assert_allclose(change[0], -change[1], atol=1e-9)


def crowd(seed: int = 4, envs: int = 6, uavs: int = 5) -> Observation:
    """Fleets packed into a 16 m square, flying toward each other: the others' next move
    decides many of their moves."""
    rng = np.random.default_rng(seed)
    shape = (envs, uavs)
    return Observation.of_fleet(
        rng.uniform(-8.0, 8.0, shape + (2,)), rng.uniform(-4.0, 4.0, shape + (2,)),
        rng.uniform(-math.pi, math.pi, shape), rng.uniform(-40.0, 40.0, shape + (2,)),
        np.ones(shape), np.full(shape, MAX_SPEED), rng.integers(0, 3, shape),
        np.zeros(shape, int), np.ones(shape, dtype=bool), np.ones(envs, int))


class ConnectedMap:
    """Connected everywhere; no route distances."""

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        return np.full(xy.shape[:-1], 2)

    def for_rows(self, rows: np.ndarray) -> ConnectedMap:
        return self


# The actions of the crowd, recorded with the policy as it was before others_model existed.
CONSTANT_VELOCITY_ACTIONS = [0, 42, 0, 0, 0, 0, 31, 0, 28, 6, 0, 10, 45, 0, 14,
                             0, 19, 19, 0, 41, 27, 0, 9, 1, 36, 20, 0, 13, 27, 0]


def crowd_actions(others_model: str) -> np.ndarray:
    scenario = variant(load_scenario(), policy={"others_model": others_model})
    method = EXTENDED_METHOD._replace(route_distance=False)
    network = scripted(ProjectionValue, joint_state_size(scenario, method), method._asdict())
    return LookaheadPolicy(scenario, network).decide(crowd(), ConnectedMap()).action


def test_constant_velocity_decides_as_before_and_reciprocal_does_not():
    np.testing.assert_array_equal(crowd_actions("constant_velocity"), CONSTANT_VELOCITY_ACTIONS)
    assert np.any(crowd_actions("reciprocal") != CONSTANT_VELOCITY_ACTIONS)


def test_the_reciprocal_model_moves_the_others_in_the_expansion(scenario):
    reciprocal = variant(scenario, policy={"others_model": "reciprocal"})
    method = EXTENDED_METHOD._replace(route_distance=False)
    network = scripted(ProjectionValue, joint_state_size(scenario, method), method._asdict())
    observation = pair_observation([[0.0, 0.0], [10.0, 0.0]], [[5.0, 0.0], [-5.0, 0.0]])
    expansion = LookaheadPolicy(reciprocal, network).expand(observation, ConnectedMap())
    expected = reciprocal_velocities(observation, scenario.policy.orca_time_horizon_s,
                                     scenario.timing.step_s)
    np.testing.assert_allclose(expansion.others_position,
                               observation.others_position + expected * scenario.timing.step_s)


def test_an_unknown_others_model_is_refused_by_name(tmp_path):
    path = write_variant(tmp_path, 'others_model = "reciprocal"', 'others_model = "telepathic"')
    with pytest.raises(ScenarioError, match="others_model"):
        load_scenario(path)
