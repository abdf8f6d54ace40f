"""A UAV's reports on board: the compiled features and spot filter against their numpy
reference, and the planner variable choosing between them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planning import PLANNER_VARIABLE
from planning.compiled import compiled_module
from planning.measuring import SpotFilter, scenario_features
from shared.scenario import load_scenario

SCENARIOS = {name: load_scenario(name) for name in ("icc2021", "city")}


def by_each_planner(compute):
    """``compute()`` under the numpy reference, then under the compiled core."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(PLANNER_VARIABLE, "reference")
        reference = compute()
        patch.setenv(PLANNER_VARIABLE, "compiled")
        return reference, compute()


def points_in(scenario, rng: np.random.Generator, count: int, spread_m: float | None):
    """``count`` points anywhere in the area, or a block of them within ``spread_m`` of one
    (an agent's reports along a step)."""
    area = scenario.area
    anywhere = np.stack([rng.uniform(area.x_min, area.x_max, count),
                         rng.uniform(area.y_min, area.y_max, count)], axis=-1)
    if spread_m is None:
        return anywhere
    return anywhere[:1] + rng.uniform(-spread_m, spread_m, (count, 2))


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(sorted(SCENARIOS)), seed=st.integers(0, 2**32 - 1),
       count=st.integers(0, 300), spread=st.sampled_from([None, 0.5, 5.0, 40.0]),
       on_a_gbs=st.booleans())
def test_compiled_features_are_the_references_within_one_float32_step(name, seed, count,
                                                                      spread, on_a_gbs):
    scenario = SCENARIOS[name]
    rng = np.random.default_rng(seed)
    xy = points_in(scenario, rng, count, spread)
    if on_a_gbs and count:
        # Points on a GBS, and midway between two (tied distances, chosen in index order).
        gbs = scenario.gbs.xy
        xy[: count // 2 + 1] = gbs[rng.integers(len(gbs))]
        xy[count // 2:] = (gbs[0] + gbs[1]) / 2
    reference, compiled = by_each_planner(lambda: scenario_features(scenario, xy))
    assert compiled.dtype == reference.dtype == np.float32
    assert compiled.shape == reference.shape == (count, reference.shape[-1])
    # Both compute each feature in float64 by the same operations and round it to float32,
    # but the angles come from libm's atan2 in the core and, on some CPUs, from numpy's own
    # vector atan2 (a few float64 ulps apart): rounded to float32 they are equal or
    # neighbours, one float32 step apart. Every other column (the GBSs chosen, their dx, dy
    # and distance, channel flags, the nearest GBS's position) is the same bit for bit.
    per_gbs = 5 + int(scenario.gbs.channels is not None)
    angle = np.zeros(reference.shape[-1], dtype=bool)
    for column in (3, 4):
        angle[column: per_gbs * scenario.policy.nearby_gbs: per_gbs] = True
    np.testing.assert_array_equal(compiled[:, ~angle], reference[:, ~angle])
    step = np.spacing(np.abs(reference[:, angle]))
    assert np.all(np.abs(compiled[:, angle] - reference[:, angle]) <= step)


def test_features_keep_the_leading_shape_of_the_points():
    scenario = SCENARIOS["icc2021"]
    xy = points_in(scenario, np.random.default_rng(3), 12, None).reshape(3, 4, 2)
    reference, compiled = by_each_planner(lambda: scenario_features(scenario, xy))
    assert compiled.shape == reference.shape == (3, 4, reference.shape[-1])
    np.testing.assert_array_equal(compiled[1, 2], scenario_features(scenario, xy[1, 2]))


def test_the_compiled_features_refuse_more_nearby_gbss_than_there_are():
    core = compiled_module("_measuring")
    gbs = np.zeros((3, 2))
    with pytest.raises(ValueError, match="4 nearby GBSs of 3"):
        core.nearby_gbs_features(np.zeros((1, 2)), gbs, np.empty(0, dtype=np.int64), 4, 50.0,
                                 30.0, False, np.empty((1, 20), dtype=np.float32))


def walks(rng: np.random.Generator, uavs: int, steps: int, reports: int):
    """Reports along random walks: small moves (many within the spacing) and levels that stay
    a while and change, as a receiver's do."""
    xy = np.cumsum(rng.normal(0.0, 0.8, (uavs, steps * reports, 2)), axis=1)
    levels = np.cumsum(rng.random((uavs, steps * reports)) < 0.1, axis=1) % 3
    return xy.reshape(uavs, steps, reports, 2), levels.reshape(uavs, steps, reports)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), uavs=st.integers(1, 6), reports=st.integers(1, 12))
def test_the_compiled_spot_filter_keeps_the_references_reports(seed, uavs, reports):
    scenario = SCENARIOS["icc2021"]
    rng = np.random.default_rng(seed)
    xy, levels = walks(rng, uavs, 8, reports)
    # Each step some of the UAVs report, in any order (the fleet's rows as the world sends).
    rows = [rng.permutation(uavs)[: rng.integers(1, uavs + 1)] for _ in range(8)]

    def kept():
        spots = SpotFilter(scenario, uavs)
        masks = [spots.keep(row, xy[row, step], levels[row, step])
                 for step, row in enumerate(rows)]
        return masks, spots.last_xy.copy(), spots.last_level.copy()

    (reference, ref_xy, ref_level), (compiled, got_xy, got_level) = by_each_planner(kept)
    for expected, got in zip(reference, compiled, strict=True):
        assert got.dtype == bool
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got_xy, ref_xy)
    np.testing.assert_array_equal(got_level, ref_level)


def test_the_compiled_spot_filter_refuses_a_uav_it_does_not_hold():
    spots = SpotFilter(SCENARIOS["icc2021"], 2)
    with pytest.raises(IndexError, match="uav 2 of 2"):
        spots.keep(np.array([2]), np.zeros((1, 3, 2)), np.zeros((1, 3), dtype=np.int64))
