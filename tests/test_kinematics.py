from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.kinematics import ActionSet, closest_approach, velocity_of, wrap_angle

angle = st.floats(-10, 10, allow_nan=False)


def test_action_set_shape_and_bounds(scenario):
    actions = ActionSet(scenario)
    uav = scenario.uav
    assert len(actions) == uav.speed_choices * uav.heading_choices + 1
    assert actions.speeds[0] == 0.0 and actions.turns[0] == 0.0
    assert math.isclose(actions.speeds.max(), uav.max_speed_mps)
    limit = math.radians(uav.turn_rate_deg_s) * scenario.timing.step_s
    assert math.isclose(np.abs(actions.turns).max(), limit)


@settings(max_examples=200, deadline=None)
@given(heading=angle)
def test_every_candidate_is_permissible(scenario, heading):
    actions = ActionSet(scenario)
    speeds, headings = actions.candidates(np.array(heading))
    assert np.all((speeds >= 0) & (speeds <= scenario.uav.max_speed_mps + 1e-12))
    assert np.all(np.abs(wrap_angle(headings - heading)) <= actions.max_turn + 1e-9)


@settings(max_examples=100, deadline=None)
@given(headings=st.lists(angle, min_size=1, max_size=12))
def test_moves_are_the_candidates_velocities_to_the_bit(scenario, headings):
    actions = ActionSet(scenario)
    heading = np.array(headings).reshape(-1, 1)
    speeds, turned, velocity = actions.moves(heading)
    expected_speeds, expected_headings = actions.candidates(heading)
    assert np.array_equal(speeds, expected_speeds)
    assert np.array_equal(turned, wrap_angle(heading[..., None] + actions.turns))
    assert np.array_equal(turned, expected_headings)
    assert np.array_equal(velocity, velocity_of(speeds, turned))


@settings(max_examples=300, deadline=None)
@given(current=angle, speed=st.floats(-100, 100) | st.just(math.nan), wanted=angle)
def test_clip_enforces_p1d_and_p1e(scenario, current, speed, wanted):
    actions = ActionSet(scenario)
    got_speed, got_heading = actions.clip(np.array(speed), np.array(wanted), np.array(current))
    assert 0.0 <= got_speed <= scenario.uav.max_speed_mps
    assert abs(wrap_angle(got_heading - current)) <= actions.max_turn + 1e-9


def test_closest_approach_by_hand():
    # Passing each other 2 m apart at the middle of the step.
    got = closest_approach(np.array([-5.0, 2.0]), np.array([10.0, 0.0]), 1.0)
    assert math.isclose(float(got), 2.0)
    # Moving apart: the start is the closest point.
    assert math.isclose(float(closest_approach(np.array([3.0, 4.0]), np.array([1.0, 0.0]), 1.0)),
                        5.0)
    # Not reaching the closest point within the step.
    assert math.isclose(float(closest_approach(np.array([-10.0, 0.0]), np.array([4.0, 0.0]), 1.0)),
                        6.0)
