from __future__ import annotations

import math

import numpy as np

from shared.routes import RouteGrid


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
