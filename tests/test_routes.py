from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planning.routes import RouteGrid


def grid(covered, cost=4.0):
    return RouteGrid(np.asarray(covered, dtype=bool), 0.0, 0.0, 1.0, cost)


def test_open_map_gives_straight_line_distance_along_the_grid():
    routes = grid(np.ones((21, 21)))
    destination = np.array([[10.0, 10.0]])
    for x, y in [(0.0, 10.0), (10.0, 0.0), (0.0, 0.0), (20.0, 13.0)]:
        got = routes.distance(np.array([[[x, y]]]), destination)[0, 0]
        straight = math.hypot(x - 10, y - 10)
        # 8-connected moves: never shorter than straight, at most ~8 % longer.
        assert straight - 1e-5 <= got <= 1.09 * straight + 1e-5


def test_route_goes_round_an_uncovered_wall_through_its_gap():
    covered = np.ones((21, 21), dtype=bool)
    covered[0:18, 10] = False  # a wall at x = 10 from y = 0 to 17, open at the top
    routes = grid(covered, cost=50.0)
    start, goal = np.array([[[5.0, 0.0]]]), np.array([[15.0, 0.0]])
    detour = routes.distance(start, goal)[0, 0]
    # Up to the gap at y = 18 and back down: about 2 x hypot(5, 18).
    assert 2 * math.hypot(5, 18) - 1 < detour < 2 * math.hypot(5, 18) + 4
    # A cheap crossing cost makes flying through the wall shorter.
    assert grid(covered, cost=1.5).distance(start, goal)[0, 0] < detour


def test_rows_read_their_own_destination_and_fields_are_cached():
    routes = grid(np.ones((11, 11)))
    xy = np.zeros((2, 3, 2))
    destinations = np.array([[10.0, 0.0], [0.0, 10.0]])
    got = routes.distance(xy, destinations)
    np.testing.assert_allclose(got, 10.0, atol=1e-6)
    assert len(routes.cache) == 2
    routes.distance(xy, destinations)
    assert len(routes.cache) == 2


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(2, 24), cols=st.integers(2, 24), seed=st.integers(0, 2**32 - 1),
       cost=st.floats(1.0, 60.0), cell=st.sampled_from([0.5, 1.0, 2.0, 3.7]))
def test_the_numpy_sweeps_and_dijkstra_give_the_same_field_bit_for_bit(rows, cols, seed, cost,
                                                                      cell):
    """An agent's single destination is swept in numpy, a batch goes to scipy's Dijkstra: on
    any map they must agree exactly, or an agent would fly other routes than the evaluation."""
    rng = np.random.default_rng(seed)
    covered = rng.random((rows, cols)) < rng.uniform(0.3, 1.0)
    routes = RouteGrid(covered, 0.0, 0.0, cell, cost)
    destinations = rng.choice(rows * cols, size=min(3, rows * cols), replace=False).tolist()
    batch = routes._dijkstra(destinations)
    for node, expected in zip(destinations, batch, strict=True):
        np.testing.assert_array_equal(routes._swept_fields(node)[0].ravel(), expected)


def test_a_swept_field_is_the_route_round_a_wall_not_through_it():
    """Hand-computed: a 3 x 3 grid of 1 m cells whose centre is uncovered (cost 9). To the
    opposite corner: a step, a diagonal past the centre, a step (2 + sqrt 2), not through the
    centre (2 x sqrt 2 x (1 + 9) / 2). Into the centre: a step then a half-covered one
    (1 + (1 + 9) / 2 = 6), not the diagonal (sqrt 2 x 5 = 7.07)."""
    covered = np.ones((3, 3), dtype=bool)
    covered[1, 1] = False
    field = RouteGrid(covered, 0.0, 0.0, 1.0, 9.0)._swept_fields(0)[0]
    assert field[2, 2] == pytest.approx(2 + math.sqrt(2), abs=1e-12)
    assert field[1, 1] == 6.0
    assert field[0, 2] == 2.0


def test_a_field_swept_ahead_a_line_at_a_time_is_the_field_a_decision_would_sweep():
    """An agent sweeps its next destination's field between decisions, stopping whenever an
    observation waits: paused and resumed, the field it leaves in the cache is the one the
    decision would have swept, and a field already cached costs nothing."""
    rng = np.random.default_rng(4)
    covered = rng.random((17, 13)) < 0.7
    ahead, direct = grid(covered, cost=9.0), grid(covered, cost=9.0)
    destination = np.array([7.2, 11.6])
    sweep = ahead.sweep_ahead(destination)
    lines = 0
    for _ in sweep:  # paused after every line: a caller may stop anywhere
        lines += 1
        assert not ahead.cache  # nothing kept until the field is done
    # At least two rounds (one to spread, one to confirm), each a sweep of every row and
    # every column but the first.
    assert lines >= 2 * ((17 - 1) + (13 - 1))
    xy = rng.uniform(0, 12, size=(1, 40, 2))
    np.testing.assert_array_equal(ahead.distance(xy, destination[None]),
                                  direct.distance(xy, destination[None]))
    assert len(ahead.cache) == 1  # the decision found it: no second field
    assert list(ahead.sweep_ahead(destination)) == []


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), cost=st.floats(1.0, 20.0))
def test_fields_stopped_at_a_reach_read_as_whole_fields_even_beyond_it(seed, cost):
    """A batch of fields stops where routes grow longer than the trips asked about need
    (``REACH_FACTOR``). Whatever is read, near the destination or far beyond the reach, must
    be the whole field's value bit for bit: a field found short is computed whole."""
    rng = np.random.default_rng(seed)
    covered = rng.random((60, 60)) < rng.uniform(0.5, 1.0)
    reached = RouteGrid(covered, 0.0, 0.0, 2.0, cost)
    whole = RouteGrid(covered, 0.0, 0.0, 2.0, cost)
    destinations = rng.uniform(0, 118, size=(6, 2))
    nodes = list(dict.fromkeys(whole.node_of(destinations).tolist()))
    whole._compute(nodes, [np.inf] * len(nodes))
    near = destinations[:, None, :] + rng.uniform(-10, 10, size=(6, 5, 2))
    np.testing.assert_array_equal(reached.distance(near, destinations),
                                  whole.distance(near, destinations))
    assert reached._partial  # short trips: the batch stopped at a reach
    far = rng.uniform(0, 118, size=(6, 5, 2))
    np.testing.assert_array_equal(reached.distance(far, destinations),
                                  whole.distance(far, destinations))
