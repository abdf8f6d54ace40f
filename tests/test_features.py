from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from planning.features import OTHER_FEATURES, OWN_FEATURES, joint_state_size, observation_state
from shared.observation import Observation


def fleet(rng, uavs=5):
    active = np.ones((1, uavs), dtype=bool)
    active[0, -1] = False  # one finished UAV: must not be seen
    heading = rng.uniform(-math.pi, math.pi, (1, uavs))
    return dict(
        position=rng.uniform(-40, 40, (1, uavs, 2)),
        velocity=rng.uniform(-5, 5, (1, uavs, 2)),
        heading=heading,
        destination=rng.uniform(-40, 40, (1, uavs, 2)),
        radius=np.full((1, uavs), 1.0),
        max_speed=np.full((1, uavs), 5.0),
        level=rng.integers(0, 3, (1, uavs)),
        below_steps=rng.integers(0, 3, (1, uavs)),
        active=active,
        step=np.zeros(1, dtype=int),
    )


def transformed(arrays, angle, shift):
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    out = dict(arrays)
    for name in ("position", "destination"):
        out[name] = arrays[name] @ rotation.T + shift
    out["velocity"] = arrays["velocity"] @ rotation.T
    out["heading"] = arrays["heading"] + angle
    return out


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10_000), angle=st.floats(-math.pi, math.pi),
       dx=st.floats(-100, 100), dy=st.floats(-100, 100))
def test_rotating_and_translating_the_world_changes_nothing(scenario, seed, angle, dx, dy):
    arrays = fleet(np.random.default_rng(seed))
    before = observation_state(Observation.of_fleet(**arrays), scenario)
    after = observation_state(
        Observation.of_fleet(**transformed(arrays, angle, (dx, dy))), scenario
    )
    np.testing.assert_allclose(after, before, atol=2e-3, rtol=1e-4)


def test_layout_by_hand(scenario):
    # UAV 0 at the origin heading north, destination due north 10 m; UAV 1 3 m east.
    arrays = dict(
        position=np.array([[[0.0, 0.0], [3.0, 0.0]]]),
        velocity=np.array([[[0.0, 2.0], [0.0, 0.0]]]),
        heading=np.array([[math.pi / 2, 0.0]]),
        destination=np.array([[[0.0, 10.0], [20.0, 0.0]]]),
        radius=np.ones((1, 2)),
        max_speed=np.full((1, 2), 5.0),
        level=np.array([[2, 0]]),
        below_steps=np.array([[0, 1]]),
        active=np.ones((1, 2), dtype=bool),
        step=np.zeros(1, dtype=int),
    )
    state = observation_state(Observation.of_fleet(**arrays), scenario)
    assert state.shape == (2, joint_state_size(scenario))
    own = dict(zip(OWN_FEATURES, state[0, : len(OWN_FEATURES)], strict=True))
    # Frame turned so +x points north: own velocity (2, 0), destination (10, 0), heading 0.
    assert own["v_x"] == 2.0 and abs(own["v_y"]) < 1e-6
    assert own["dest_x"] == 10.0 and own["dest_distance"] == 10.0 and abs(own["heading"]) < 1e-6
    first = dict(zip(OTHER_FEATURES, state[0, len(OWN_FEATURES): len(OWN_FEATURES) + 6],
                     strict=True))
    # East is on the right of a north-facing UAV: (0, -3) in its frame.
    assert abs(first["p_x"]) < 1e-6 and first["p_y"] == -3.0 and first["distance"] == 3.0
    assert state[0, -1] == 2 and state[1, -1] == 0
    # Padding: three absent neighbours, far behind.
    padding = state[0, len(OWN_FEATURES) + 6 : -1].reshape(3, 6)
    assert (padding[:, 4] >= 999).all()


def test_finished_uavs_are_not_neighbours(scenario):
    arrays = fleet(np.random.default_rng(1))
    state = observation_state(Observation.of_fleet(**arrays), scenario)
    distances = state[0, len(OWN_FEATURES) + 4 : -1 : 6]
    assert np.count_nonzero(distances < 999) == 3  # 5 UAVs, itself and the finished one out
