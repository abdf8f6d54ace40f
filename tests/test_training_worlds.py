"""The worlds value-network training flies: 0 to ``training.jammer_count_max`` jammers per
period, a share of them driving, and the map its lookahead reads of a driving jammer."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from cloud_service.training_flight import training_jammers, training_maps
from cloud_service.value_training import train
from shared.jammer_motion import position_at
from tests.test_training import tiny
from world_sim.core import VectorWorld

PERIODS = 600


def many(scenario, share: float = 0.5):
    return scenario.changed({"training.jammer_count_max": 3,
                             "training.moving_jammer_share": share})


def binomial_within(count: int, n: int, p: float) -> bool:
    """``count`` of ``n`` draws of chance ``p`` within 5 standard deviations (a false alarm
    under 1e-6)."""
    return abs(count - n * p) <= 5 * np.sqrt(n * p * (1 - p))


def test_the_shipped_scenario_draws_one_still_jammer_at_most(scenario):
    drawn = [training_jammers(scenario, 0, period) for period in range(PERIODS)]
    assert all(len(jammers) <= 1 and all(j.still for j in jammers) for jammers in drawn)
    absent = sum(not jammers for jammers in drawn)
    assert binomial_within(absent, PERIODS, scenario.training.jammer_absent_probability)


def test_several_jammers_some_driving_inside_the_area(scenario):
    scenario = many(scenario)
    spec, area = scenario.training, scenario.area
    drawn = [training_jammers(scenario, 3, period) for period in range(PERIODS)]
    counts = np.bincount([len(jammers) for jammers in drawn], minlength=5)
    assert counts[4] == 0
    present = PERIODS - counts[0]
    # Each count from 1 to 3 equally likely where jammers are present.
    assert all(binomial_within(counts[k], present, 1 / 3) for k in (1, 2, 3))
    jammers = [jammer for period in drawn for jammer in period]
    driving = [jammer for jammer in jammers if jammer.path is not None]
    assert binomial_within(len(driving), len(jammers), 0.5)
    for jammer in jammers:
        points = [(jammer.x, jammer.y), *(jammer.path.waypoints if jammer.path else [])]
        assert all(area.x_min <= x <= area.x_max and area.y_min <= y <= area.y_max
                   for x, y in points)
        assert spec.jammer_power_range_w[0] <= jammer.power_w <= spec.jammer_power_range_w[1]
    low, high = spec.moving_jammer_speed_range_mps
    assert all(j.path.loop and low <= j.path.speed_mps <= high for j in driving)
    assert training_jammers(scenario, 3, 17) == drawn[17]
    assert training_jammers(scenario, 4, 17) != drawn[17]


def test_the_map_shows_a_driving_jammer_where_it_was_at_the_last_refresh(scenario):
    scenario = many(scenario, share=1.0)
    period = next(p for p in range(PERIODS) if len(training_jammers(scenario, 0, p)) == 1)
    jammer, = training_jammers(scenario, 0, period)
    world = VectorWorld(scenario, 1, 4)
    world.reset([0], [1])
    world.set_jammers([0], (jammer,))
    maps = training_maps(scenario)
    every = maps.moving_every_steps
    assert every == round(scenario.training.moving_map_every_s / scenario.timing.step_s) > 1
    rows = np.arange(4)
    for step in range(every + 2):
        # The world and the map place the jammer by position_at at the same times: the same
        # float64 arithmetic, so the same places exactly.
        refreshed_at = (step - step % every) * scenario.timing.step_s
        assert world.jammers_as_of(0, every)[0][:2] == position_at(jammer, refreshed_at)
        assert world.jammers_now(0)[0][:2] == position_at(jammer, step * scenario.timing.step_s)
        maps(world, rows)
        world.step(np.zeros((1, 4)), world.heading.copy())
    # One raster per refresh, not per step.
    assert len(maps.cache) == 2


@pytest.mark.parametrize(("key", "value"), [
    ("training.jammer_count_max", 5), ("training.jammer_count_max", 0),
    ("training.moving_jammer_share", 1.5),
    ("training.moving_jammer_speed_range_mps", (5.0, 1.0)),
    ("training.moving_jammer_speed_range_mps", (0.0, 1.0)),
    ("training.moving_map_every_s", 0.0)])
def test_bad_training_worlds_are_refused(scenario, key, value):
    with pytest.raises((ValidationError, ValueError)):
        scenario.changed({key: value})


def test_training_flies_several_driving_jammers(scenario, tmp_path):
    card = train(many(scenario), tiny(20), tmp_path)
    assert card["episodes"] == 20
