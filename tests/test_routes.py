from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from planning import PLANNER_VARIABLE
from planning.compiled import THREADS_VARIABLE, compiled_module
from planning.routes import EdgeWeights, RouteGrid, SweptFields


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


COMPILED = compiled_module("_routes")


def built(weights: EdgeWeights, nodes, limits, builder: str) -> np.ndarray:
    nodes = np.asarray(nodes, dtype=np.int64)
    limits = np.broadcast_to(np.asarray(limits, dtype=np.float64), nodes.shape).copy()
    if builder == "compiled":
        return COMPILED.route_fields(*weights, nodes, limits)
    return SweptFields(weights)(nodes, limits)


def cost_grid(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """Crossing costs of every kind a field meets: covered (1), uncovered (one dearer cost),
    costs of their own, and blocked cells (infinite) that may wall nodes off altogether."""
    kind = rng.choice(4, size=(rows, cols), p=rng.dirichlet(np.ones(4)))
    return np.choose(kind, [np.ones((rows, cols)), np.full((rows, cols), rng.uniform(1.5, 60)),
                            rng.uniform(1.0, 60.0, size=(rows, cols)),
                            np.full((rows, cols), np.inf)])


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 24), cols=st.integers(1, 24), seed=st.integers(0, 2**32 - 1),
       cell=st.sampled_from([0.5, 1.0, 2.0, 3.7]))
def test_compiled_fields_are_the_reference_fields_bit_for_bit(rows, cols, seed, cell):
    """The compiled Dijkstra and the numpy sweeps must agree exactly on any grid, whole or
    stopped at a limit, or the planners would fly other routes: both reach the one fixpoint of
    d[v] = min(d[v], d[u] + w(u, v)) by the same float64 additions. Several destinations in one
    call, the grid's corners among them; a limit at a node's exact distance keeps that node."""
    rng = np.random.default_rng(seed)
    weights = EdgeWeights.of(cost_grid(rng, rows, cols), cell)
    corners = [0, cols - 1, (rows - 1) * cols, rows * cols - 1]
    nodes = list(dict.fromkeys(corners + rng.integers(0, rows * cols, size=3).tolist()))
    whole = built(weights, nodes, np.inf, "compiled")
    np.testing.assert_array_equal(whole, built(weights, nodes, np.inf, "reference"))
    finite = whole[np.isfinite(whole)]
    limits = rng.choice(finite, size=len(nodes)) * rng.choice([1.0, 0.5], size=len(nodes))
    stopped = built(weights, nodes, limits, "compiled")
    np.testing.assert_array_equal(stopped, built(weights, nodes, limits, "reference"))
    beyond = whole > limits[:, None, None]
    np.testing.assert_array_equal(stopped, np.where(beyond, np.inf, whole))


@pytest.mark.parametrize("builder", ["compiled", "reference"])
def test_a_field_is_the_route_round_a_wall_not_through_it(builder):
    """Hand-computed: a 3 x 3 grid of 1 m cells whose centre is uncovered (cost 9). To the
    opposite corner: a step, a diagonal past the centre, a step (2 + sqrt 2), not through the
    centre (2 x sqrt 2 x (1 + 9) / 2). Into the centre: a step then a half-covered one
    (1 + (1 + 9) / 2 = 6), not the diagonal (sqrt 2 x 5 = 7.07)."""
    cost = np.ones((3, 3))
    cost[1, 1] = 9.0
    field = built(EdgeWeights.of(cost, 1.0), [0], np.inf, builder)[0]
    assert field[2, 2] == pytest.approx(2 + math.sqrt(2), abs=1e-12)
    assert field[1, 1] == 6.0
    assert field[0, 2] == 2.0
    # Stopped at 2 m: the corners two steps away are kept, the one past the centre is not.
    stopped = built(EdgeWeights.of(cost, 1.0), [0], 2.0, builder)[0]
    assert stopped[0, 2] == stopped[2, 0] == 2.0
    assert np.isinf(stopped[2, 2]) and np.isinf(stopped[1, 1])


@pytest.mark.parametrize("builder", ["compiled", "reference"])
def test_nodes_walled_off_by_blocked_cells_are_unreachable(builder):
    cost = np.ones((4, 5))
    cost[:, 2] = np.inf  # a wall of blocked cells down the middle column
    field = built(EdgeWeights.of(cost, 2.0), [0, 2], np.inf, builder)
    assert np.isfinite(field[0, :, :2]).all() and np.isinf(field[0, :, 2:]).all()
    # Three float64 edge weights of ~2-3 summed: a few ulps (~1e-15) off at most.
    assert field[0, 3, 1] == pytest.approx(2.0 * (2 + math.sqrt(2)), abs=1e-12)
    assert field[1, 0, 2] == 0.0 and np.isinf(np.delete(field[1].ravel(), 2)).all()


def test_the_compiled_builder_refuses_a_node_off_the_grid_and_mismatched_arguments():
    weights = EdgeWeights.of(np.ones((3, 4)), 1.0)
    with pytest.raises(ValueError, match="not a node of 3 x 4"):
        built(weights, [12], np.inf, "compiled")
    with pytest.raises(ValueError, match="1 destinations but 2 limits"):
        COMPILED.route_fields(*weights, np.array([0]), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="different grids"):
        COMPILED.route_fields(*weights[:3], weights.down_right[:, 1:].copy(), np.array([0]),
                              np.array([1.0]))


def test_the_planner_variable_chooses_the_builder_of_route_fields(monkeypatch):
    monkeypatch.delenv(PLANNER_VARIABLE, raising=False)
    assert grid(np.ones((3, 3)))._build.args[0].func is COMPILED.route_fields
    monkeypatch.setenv(PLANNER_VARIABLE, "reference")
    assert isinstance(grid(np.ones((3, 3)))._build, SweptFields)


def test_a_field_prepared_ahead_is_the_field_a_decision_would_build():
    """An agent builds its next destination's field between decisions: the decision then
    reads that field, the one it would have built, and builds none; a field already cached
    costs nothing."""
    rng = np.random.default_rng(4)
    covered = rng.random((17, 13)) < 0.7
    ahead, direct = grid(covered, cost=9.0), grid(covered, cost=9.0)
    destination = np.array([7.2, 11.6])
    ahead.prepare(destination)
    assert len(ahead.cache) == 1 and not ahead._partial  # whole: no reach is known ahead
    store = ahead.store.copy()
    xy = rng.uniform(0, 12, size=(1, 40, 2))
    np.testing.assert_array_equal(ahead.distance(xy, destination[None]),
                                  direct.distance(xy, destination[None]))
    assert len(ahead.cache) == 1
    ahead.prepare(destination)
    np.testing.assert_array_equal(ahead.store, store)


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
    # Short trips: the batch stopped at a reach, unless a route near a destination already ran
    # past it (a map mostly uncovered at a high crossing cost), which computed the fields whole.
    assume(reached._partial)
    far = rng.uniform(0, 118, size=(6, 5, 2))
    np.testing.assert_array_equal(reached.distance(far, destinations),
                                  whole.distance(far, destinations))


def test_two_threads_build_the_fields_one_does(monkeypatch):
    monkeypatch.setenv(THREADS_VARIABLE, "2")
    covered = np.random.default_rng(8).random((40, 30)) < 0.7
    routes = grid(covered, cost=9.0)
    nodes = np.arange(0, 1200, 37)
    limits = np.where(nodes % 2 == 0, np.inf, 20.0)
    np.testing.assert_array_equal(routes._build(nodes, limits),
                                  COMPILED.route_fields(*routes.weights, nodes, limits))
