"""ORCA against physical expectations: no contact along simulated paths, goals reached, the speed
bound, the reciprocal guarantee for a pair, symmetries, lone and inactive agents."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from planning.orca import orca_velocities, preferred_velocity_toward

TOL = 1e-9


def simulate(start, goals, radii, max_speed, time_horizon, time_step, steps):
    """Positions (steps + 1, E, J, 2) of agents steered by ORCA toward their goals."""
    positions = np.array(start, dtype=np.float64)
    goals = np.asarray(goals, dtype=np.float64)
    velocities = np.zeros_like(positions)
    active = np.ones(positions.shape[:2], dtype=bool)
    path = [positions]
    for _ in range(steps):
        preferred = preferred_velocity_toward(positions, goals, max_speed, time_step)
        velocities = orca_velocities(
            positions, velocities, radii, preferred, max_speed, active, time_horizon, time_step
        )
        positions = positions + velocities * time_step
        path.append(positions)
    return np.stack(path)


def closest_approach(path):
    """Smallest centre distance (E, J, J) of every pair over the straight segments of ``path``."""
    rel = path[:, :, None, :, :] - path[:, :, :, None, :]
    start, move = rel[:-1], rel[1:] - rel[:-1]
    move_sq = np.sum(move**2, axis=-1)
    s = np.clip(-np.sum(start * move, axis=-1) / np.where(move_sq > 0, move_sq, 1.0), 0.0, 1.0)
    gap = np.linalg.norm(start + s[..., None] * move, axis=-1).min(axis=0)
    count = path.shape[2]
    return gap + np.where(np.eye(count, dtype=bool), np.inf, 0.0)


def test_head_on_pair_passes_without_contact():
    # An exactly collinear swap is an equilibrium of ORCA (both agents only slow down), so one
    # goal is offset by 5 cm, as the paper's experiments perturb their symmetric scenes.
    start = [[[-10.0, 0.0], [10.0, 0.05]]]
    goals = [[[10.0, 0.0], [-10.0, 0.05]]]
    path = simulate(start, goals, 1.0, 2.0, time_horizon=2.0, time_step=0.25, steps=120)
    assert closest_approach(path).min() >= 2.0 - TOL
    assert np.linalg.norm(path[-1] - goals, axis=-1).max() < 1e-6
    # They had to swerve: the straight line would have run them through each other.
    assert np.abs(path[..., 1]).max() > 0.5


def test_four_agent_crossing_resolves_in_every_world():
    # Three independent worlds, each a 4-agent antipodal swap with its own jitter of the start
    # angles. Opposite agents must not be almost exactly collinear: then ORCA only slows them
    # down (the cut-off circle case) and the four jam in the middle for a long time.
    jitter = np.array(
        [[0.03, -0.05, -0.09, -0.1], [0.0, 0.09, -0.07, 0.09], [-0.05, -0.04, 0.06, -0.08]]
    )
    angles = np.arange(4) * np.pi / 2 + jitter
    start = 10.0 * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    path = simulate(start, -start, 0.5, 2.0, time_horizon=5.0, time_step=0.25, steps=80)
    assert closest_approach(path).min() >= 1.0 - TOL
    assert np.linalg.norm(path[-1] + start, axis=-1).max() < 1e-6


@st.composite
def worlds(draw, max_agents=8):
    """Random batches, crowded enough that agents often overlap and programs are infeasible."""
    e = draw(st.integers(1, 3))
    j = draw(st.integers(1, max_agents))
    coord = st.floats(-4, 4, allow_nan=False)
    speed = st.floats(-3, 3, allow_nan=False)
    return dict(
        positions=draw(arrays(np.float64, (e, j, 2), elements=coord)),
        velocities=draw(arrays(np.float64, (e, j, 2), elements=speed)),
        radii=draw(arrays(np.float64, (e, j), elements=st.floats(0.05, 1.5))),
        preferred_velocities=draw(arrays(np.float64, (e, j, 2), elements=speed)),
        max_speeds=draw(arrays(np.float64, (e, j), elements=st.floats(0.0, 3.0))),
        active=draw(arrays(np.bool_, (e, j), elements=st.booleans())),
        time_horizon=draw(st.floats(0.2, 10.0)),
        time_step=draw(st.floats(0.01, 1.0)),
    )


@settings(max_examples=150, deadline=None)
@given(worlds())
def test_speed_never_exceeds_max_and_inactive_are_zero(world):
    result = orca_velocities(**world)
    assert result.shape == world["positions"].shape
    assert np.all(np.isfinite(result))
    speed = np.linalg.norm(result, axis=-1)
    assert np.all(speed <= world["max_speeds"] + TOL)
    assert np.all(result[~world["active"]] == 0.0)


@settings(max_examples=150, deadline=None)
@given(
    arrays(np.float64, (2, 2), elements=st.floats(-5, 5)),
    arrays(np.float64, (2, 2), elements=st.floats(-3, 3)),
    arrays(np.float64, (2, 2), elements=st.floats(-3, 3)),
    arrays(np.float64, 2, elements=st.floats(0.1, 1.0)),
    st.floats(0.5, 5.0),
)
def test_pair_stays_apart_for_the_time_horizon(positions, velocities, preferred, radii, tau):
    """Both agents in their half-planes keep the pair out of contact for tau (the paper's
    guarantee); a huge speed disc makes the program feasible."""
    gap = np.linalg.norm(positions[1] - positions[0])
    combined = radii.sum()
    if gap <= combined * (1 + 1e-6):
        return
    new = orca_velocities(
        positions[None], velocities[None], radii[None], preferred[None], 1e3, True, tau, 0.1
    )[0]
    rel_pos, rel_vel = positions[1] - positions[0], new[1] - new[0]
    t = np.clip(-rel_pos @ rel_vel / max(rel_vel @ rel_vel, 1e-300), 0.0, tau)
    assert np.linalg.norm(rel_pos + t * rel_vel) >= combined - 1e-9 * max(1.0, gap)


def random_crowds(seed, worlds=40, agents=6):
    rng = np.random.default_rng(seed)
    return dict(
        positions=rng.uniform(-4, 4, (worlds, agents, 2)),
        velocities=rng.uniform(-2, 2, (worlds, agents, 2)),
        radii=rng.uniform(0.3, 1.2, (worlds, agents)),
        preferred_velocities=rng.uniform(-2, 2, (worlds, agents, 2)),
        max_speeds=rng.uniform(0.5, 2.5, (worlds, agents)),
        active=rng.random((worlds, agents)) < 0.9,
        time_horizon=3.0,
        time_step=0.2,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mirroring_the_scene_mirrors_the_answer(seed):
    world = random_crowds(seed)
    result = orca_velocities(**world)
    flip = np.array([-1.0, 1.0])
    mirrored = dict(world)
    for key in ("positions", "velocities", "preferred_velocities"):
        mirrored[key] = world[key] * flip
    np.testing.assert_allclose(orca_velocities(**mirrored), result * flip, atol=1e-9)
    np.testing.assert_array_equal(orca_velocities(**world), result)  # deterministic


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_reordering_agents_reorders_the_answer(seed):
    world = random_crowds(seed)
    result = orca_velocities(**world)
    order = np.random.default_rng(seed).permutation(world["positions"].shape[1])
    permuted = {
        key: value[:, order] if isinstance(value, np.ndarray) else value
        for key, value in world.items()
    }
    np.testing.assert_allclose(orca_velocities(**permuted), result[:, order], atol=1e-9)


@pytest.mark.parametrize(
    ("preferred", "max_speed", "expected"),
    [
        ([0.3, -0.4], 1.0, [0.3, -0.4]),
        ([3.0, 4.0], 2.0, [1.2, 1.6]),
        ([0.0, 0.0], 1.0, [0.0, 0.0]),
        ([0.6, 0.8], 1.0, [0.6, 0.8]),
        ([1.0, 1.0], 0.0, [0.0, 0.0]),
    ],
)
def test_lone_agent_gets_its_preferred_velocity(preferred, max_speed, expected):
    result = orca_velocities(
        [[[5.0, -2.0]]], [[[1.0, 1.0]]], 1.0, [[preferred]], max_speed, True, 2.0, 0.1
    )
    np.testing.assert_allclose(result[0, 0], expected, rtol=1e-15, atol=0.0)


def test_agents_far_apart_keep_their_preferred_velocities():
    positions = np.array([[[0.0, 0.0], [50.0, 0.0], [0.0, 50.0]]])
    preferred = np.array([[[1.0, 0.0], [1.0, 0.5], [-0.5, 0.5]]])
    result = orca_velocities(positions, preferred, 1.0, preferred, 2.0, True, 5.0, 0.1)
    np.testing.assert_array_equal(result, preferred)


def test_packed_ring_falls_back_to_least_violation():
    # Eight neighbours overlap the centre agent from all sides: each demands that it move away
    # from that neighbour at a positive speed, which no single velocity can do, so the 2-D
    # program is infeasible. By symmetry the least-violating velocity of the centre is zero.
    angles = np.arange(8) * np.pi / 4
    ring = 1.5 * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    positions = np.concatenate([[[0.0, 0.0]], ring])[None]
    velocities = np.zeros_like(positions)
    preferred = np.zeros_like(positions)
    preferred[0, 0] = [1.0, 0.3]
    max_speeds = np.full((1, 9), 2.0)
    result = orca_velocities(positions, velocities, 1.0, preferred, max_speeds, True, 2.0, 0.1)
    assert np.all(np.isfinite(result))
    assert np.all(np.linalg.norm(result, axis=-1) <= max_speeds + TOL)
    np.testing.assert_allclose(result[0, 0], [0.0, 0.0], atol=1e-9)
    # The ring, squeezed between the centre and its neighbours, moves outward.
    assert np.all(np.sum(result[0, 1:] * ring, axis=-1) > 0.0)


def test_inactive_agents_get_zero_and_are_ignored():
    rng = np.random.default_rng(7)
    active_world = dict(
        positions=rng.uniform(-3, 3, (1, 3, 2)),
        velocities=rng.uniform(-1, 1, (1, 3, 2)),
        radii=np.full((1, 3), 0.6),
        preferred_velocities=rng.uniform(-1, 1, (1, 3, 2)),
        max_speeds=np.full((1, 3), 1.5),
    )
    expected = orca_velocities(**active_world, active=True, time_horizon=2.0, time_step=0.1)
    # Interleave two inactive agents, one right on top of an active one, moving fast.
    order = [0, 3, 1, 4, 2]
    padded = {}
    for key, value in active_world.items():
        extra = np.repeat(value[:, :1], 2, axis=1) * 3.0
        padded[key] = np.concatenate([value, extra], axis=1)[:, order]
    active = np.array([[True, False, True, False, True]])
    result = orca_velocities(**padded, active=active, time_horizon=2.0, time_step=0.1)
    np.testing.assert_array_equal(result[:, [1, 3]], 0.0)
    np.testing.assert_array_equal(result[:, [0, 2, 4]], expected)


def test_preferred_velocity_toward_does_not_overshoot():
    positions = np.array([[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]])
    destinations = np.array([[[10.0, 0.0], [1.0, 1.3], [2.0, 2.0]]])
    result = preferred_velocity_toward(positions, destinations, [[2.0, 2.0, 2.0]], 0.5)
    np.testing.assert_allclose(result[0, 0], [2.0, 0.0])
    np.testing.assert_allclose(result[0, 1], [0.0, 0.6])  # 0.3 m in one 0.5 s step
    np.testing.assert_array_equal(result[0, 2], [0.0, 0.0])
