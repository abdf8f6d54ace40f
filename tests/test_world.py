from __future__ import annotations

import math

import numpy as np
import pytest

from shared.outcomes import Outcome
from shared.radio import RadioModel
from shared.scenario import load_scenario
from world_sim.core import VectorWorld, episode_seed

COVERED = (12.5, 0.0)  # next to a GBS: connected with or without the default jammer
UNCOVERED = (0.0, 0.0)  # between GBSs: below T_s even without the jammer


def placed(scenario, positions, destinations, headings, jammer=False):
    """A one-environment world with UAVs placed by hand."""
    world = VectorWorld(scenario if jammer else scenario.without_jammer(), 1, len(positions))
    world.reset([0], [1])
    world.position[0] = np.asarray(positions, dtype=float)
    world.destination[0] = np.asarray(destinations, dtype=float)
    world.heading[0] = np.asarray(headings, dtype=float)
    world.below_steps[:] = 0
    return world


def hover(world):
    return world.step(np.zeros((1, world.num_uavs)), world.heading.copy())


def test_head_on_pass_through_is_a_collision_for_both(scenario):
    # End points are 4 m apart (> 2 radii) but the UAVs pass through each other mid-step.
    world = placed(scenario, [(-3, 20), (3, 20)], [(40, 20), (-40, 20)], [0.0, math.pi])
    result = world.step(np.full((1, 2), 5.0), np.array([[0.0, math.pi]]))
    assert world.status[0].tolist() == [Outcome.COLLISION, Outcome.COLLISION]
    assert result.finished[0].all() and result.env_done[0]
    assert result.reward[0, 0] == pytest.approx(scenario.rewards.collision + scenario.rewards.step
                                                + _connectivity(world, scenario, 0))


def _connectivity(world, scenario, uav):
    # The first step has index 0, a connectivity check step: R_s depends on the new level.
    level = int(world.level[0, uav])
    return {0: scenario.rewards.disconnected, 1: scenario.rewards.marginal}.get(level, 0.0)


def test_near_miss_costs_the_discomfort_penalty_only(scenario):
    # Parallel tracks 2.1 m apart: gap 0.1 m, half of the 0.2 m discomfort band.
    world = placed(scenario, [(10, 0), (10, 2.1)], [(45, 0), (45, 2.1)], [0.0, 0.0])
    result = world.step(np.full((1, 2), 1.0), np.zeros((1, 2)))
    assert (world.status[0] == Outcome.ACTIVE).all()
    expected = 0.5 * scenario.rewards.collision + scenario.rewards.step
    assert result.reward[0, 0] == pytest.approx(expected + _connectivity(world, scenario, 0))


def test_arrival_within_the_step_is_a_success_at_the_destination(scenario):
    world = placed(scenario, [COVERED], [(COVERED[0] + 3.0, 0.0)], [0.0])
    result = world.step(np.array([[5.0]]), np.array([[0.0]]))
    assert world.status[0, 0] == Outcome.SUCCESS
    np.testing.assert_allclose(world.position[0, 0], world.destination[0, 0])
    assert result.reward[0, 0] == pytest.approx(scenario.rewards.arrival + scenario.rewards.step)
    # Final: further commands change nothing.
    hover(world)
    assert world.status[0, 0] == Outcome.SUCCESS


def test_disconnection_after_more_than_n_t_steps_below_threshold(scenario):
    limit = scenario.timing.disconnection_limit_steps
    world = placed(scenario, [UNCOVERED], [(40.0, 40.0)], [0.0])
    for _ in range(limit):
        hover(world)
        assert world.status[0, 0] == Outcome.ACTIVE
    hover(world)
    assert world.status[0, 0] == Outcome.DISCONNECTION


def test_timeout_at_the_episode_limit(scenario):
    world = placed(scenario, [COVERED], [(-40.0, -40.0)], [0.0])
    for _ in range(scenario.timing.episode_limit_steps - 1):
        hover(world)
    assert world.status[0, 0] == Outcome.ACTIVE
    result = hover(world)
    assert world.status[0, 0] == Outcome.TIMEOUT and result.env_done[0]


def test_outcomes_are_exclusive_and_final_under_random_commands(scenario):
    rng = np.random.default_rng(3)
    world = VectorWorld(scenario, 64, 6)
    world.reset(np.arange(64), [episode_seed(5, k) for k in range(64)])
    finished_count = np.zeros((64, 6), dtype=int)
    previous = world.status.copy()
    for _ in range(scenario.timing.episode_limit_steps):
        result = world.step(rng.uniform(0, 6, (64, 6)), rng.uniform(-4, 4, (64, 6)))
        ended = previous != Outcome.ACTIVE
        assert (world.status[ended] == previous[ended]).all()
        finished_count += result.finished
        previous = world.status.copy()
    assert (finished_count == 1).all()
    assert set(np.unique(world.status)) <= {int(o) for o in Outcome if o != Outcome.ACTIVE}


def test_world_enforces_kinematic_limits(scenario):
    rng = np.random.default_rng(4)
    world = VectorWorld(scenario, 32, 4)
    world.reset(np.arange(32), np.arange(32))
    limit = math.radians(scenario.uav.turn_rate_deg_s) * scenario.timing.step_s
    for _ in range(10):
        before, heading, active = world.position.copy(), world.heading.copy(), world.active
        world.step(rng.uniform(-20, 20, (32, 4)), rng.uniform(-9, 9, (32, 4)))
        moved = np.linalg.norm(world.position - before, axis=-1)
        moving = active & (world.status == Outcome.ACTIVE)
        assert (moved[moving] <= scenario.uav.max_speed_mps * scenario.timing.step_s + 1e-9).all()
        turn = np.abs((world.heading - heading + np.pi) % (2 * np.pi) - np.pi)
        assert (turn[active] <= limit + 1e-9).all()


def test_episode_seed_alone_decides_the_missions(scenario):
    seeds = [episode_seed(11, k) for k in range(6)]
    batch = VectorWorld(scenario, 6, 4)
    batch.reset(np.arange(6), seeds)
    single = VectorWorld(scenario, 1, 4)
    single.reset([0], [seeds[4]])
    np.testing.assert_array_equal(batch.position[4], single.position[0])
    np.testing.assert_array_equal(batch.destination[4], single.destination[0])
    trips = np.linalg.norm(batch.destination - batch.position, axis=-1)
    assert (trips >= scenario.missions.min_trip_m).all()


def test_jammer_is_settable_per_environment(scenario):
    world = VectorWorld(scenario, 2, 1)
    world.reset([0, 1], [1, 1])
    world.position[:, 0] = (4.0, 0.0)
    world.set_jammer([1], None)
    world.step(np.zeros((2, 1)), world.heading.copy())
    assert world.sinr_db[0, 0] < world.sinr_db[1, 0]


def test_an_ended_mission_leaves_the_others_readings_and_reports_as_they_were():
    """The radio is evaluated for active UAVs only, but every receiver's noise is drawn: the
    other UAVs read and report what they would have with that one still flying, noise
    included, in the shadowed world (independently: the radio at their new positions)."""
    shadowed = load_scenario("icc2021-shadowed")
    worlds = [VectorWorld(shadowed, 2, 4, record_measurements=True) for _ in range(2)]
    for world in worlds:
        world.reset([0, 1], [episode_seed(5, 0), episode_seed(5, 1)])
    worlds[1].status[0, 2] = Outcome.SUCCESS  # its mission ended the step before
    rng = np.random.default_rng(0)
    for _ in range(3):
        speed = rng.uniform(0.0, shadowed.uav.max_speed_mps, (2, 4))
        heading = worlds[0].heading + rng.uniform(-0.5, 0.5, (2, 4))
        for world in worlds:
            world.step(speed, heading)
        flying = worlds[1].active & worlds[0].active
        assert flying.sum() >= 6
        for field in ("sinr_db", "level", "measured_level", "measured_xy"):
            np.testing.assert_array_equal(getattr(worlds[1], field)[flying],
                                          getattr(worlds[0], field)[flying])
        truth = RadioModel(shadowed).evaluate(worlds[1].position, worlds[1].jammer()).sinr_db
        np.testing.assert_allclose(worlds[1].sinr_db[flying], truth[flying], rtol=1e-12)
    assert not worlds[1].measured[0, 2]


def test_a_world_that_reports_the_sinr_reports_the_same_levels_beside_it():
    """dB reports add to level reports: the same seed gives the same levels, draw for draw,
    each beside its SINR in half-dB steps within a quarter step of the SINR its level came
    from, and that SINR within a few receiver-noise sds of the true one."""
    shadowed = load_scenario("icc2021-shadowed")
    reporting = shadowed.changed({"uav.report": "db"})
    worlds = [VectorWorld(s, 2, 4, record_measurements=True) for s in (shadowed, reporting)]
    rng = np.random.default_rng(3)
    for world in worlds:
        world.reset([0, 1], [5, 6])
    for _ in range(6):
        speed, heading = rng.uniform(0, 5, (2, 4)), rng.uniform(-np.pi, np.pi, (2, 4))
        for world in worlds:
            world.step(speed, heading)
        levels, reporting_world = worlds[0], worlds[1]
        np.testing.assert_array_equal(levels.measured_level, reporting_world.measured_level)
        assert np.isnan(levels.measured_sinr_db).all()
        reported = reporting_world.measured_sinr_db[reporting_world.measured]
        assert np.isfinite(reported).all()
        np.testing.assert_array_equal(reported * 2, np.round(reported * 2))
        radio = RadioModel(reporting)
        level = reporting_world.measured_level[reporting_world.measured]
        assert np.all(radio.level_of(reported - 0.25) <= level)
        assert np.all(level <= radio.level_of(reported + 0.25))
        truth = radio.evaluate(reporting_world.measured_xy[reporting_world.measured],
                               radio.default_jammers).sinr_db
        assert np.abs(reported - truth).max() < 6 * reporting.uav.measurement_noise_db + 0.25
