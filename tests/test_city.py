"""The city scenario: icc2021's world tiled 4 x 4, flown by hundreds of UAVs in-process."""

import numpy as np
import pytest

from cloud_service.evaluation import load_policy
from cloud_service.rollout import LookaheadController, perfect_maps
from cloud_service.upload_positions import positions_from_features
from planning.measuring import scenario_features
from shared.observation import Observation
from shared.outcomes import Outcome
from shared.radio import RadioModel
from shared.scenario import Scenario, load_scenario
from shared.shipped import EXTENDED_VALUE_NET, SINR_MAP_NO_JAMMER_CITY
from shared.survey_maps import sinr_map_for
from tests import float32_bounds as bounds
from world_sim.core import VectorWorld, fleet_observation, near_pairs

BLOCK_CENTRES = (-150.0, -50.0, 50.0, 150.0)


@pytest.fixture(scope="module")
def city() -> Scenario:
    return load_scenario("city")


@pytest.fixture(scope="module")
def icc2021() -> Scenario:
    return load_scenario("icc2021")


def covered_shares(scenario: Scenario, gbs: list[tuple[float, float]]) -> np.ndarray:
    """Share of each GBS's own 25 m x 33 m cell with SINR >= T_s, no jammer (0.5 m raster)."""
    xs, ys = np.arange(-12.25, 12.5, 0.5), np.arange(-16.25, 16.5, 0.5)
    cell = np.stack(np.meshgrid(xs, ys), axis=-1)
    grid = np.asarray(gbs)[:, None, None, :] + cell
    return (RadioModel(scenario).evaluate(grid, None).level > 0).mean(axis=(1, 2))


def test_city_is_icc2021_tiled_with_its_density_of_uavs(city, icc2021):
    assert (city.area.x_max - city.area.x_min, city.area.y_max - city.area.y_min) == (400, 400)
    assert city.missions.uav_count == 4 * 16 == icc2021.missions.uav_count * 16
    # Trips as long as icc2021's at most: the diagonal of its mission square.
    side = icc2021.area.x_max - icc2021.area.x_min - 2 * icc2021.missions.margin_m
    assert city.missions.max_trip_m == pytest.approx(np.hypot(side, side), abs=0.05)
    # Only the mission's time limit grows with the area.
    for section in ("uav", "channel", "jammer", "rewards", "timing"):
        exclude = {"episode_limit_s"} if section == "timing" else None
        assert (getattr(city, section).model_dump(exclude=exclude)
                == getattr(icc2021, section).model_dump(exclude=exclude)), section
    assert city.gbs.model_dump(exclude={"positions", "channels"}) == icc2021.gbs.model_dump(
        exclude={"positions", "channels"})
    tiled = {(x + bx, y + by) for bx in BLOCK_CENTRES for by in BLOCK_CENTRES
             for x, y in icc2021.gbs.positions}
    assert set(map(tuple, city.gbs.positions)) == tiled
    assert len(city.gbs.positions) == 192
    assert sinr_map_for(city) == SINR_MAP_NO_JAMMER_CITY and SINR_MAP_NO_JAMMER_CITY.is_file()


def test_reuse_gives_each_block_a_channel_shared_only_300_m_away(city):
    centre = {gbs: ((gbs[0] + 200) // 100, (gbs[1] + 200) // 100)
              for gbs in map(tuple, city.gbs.positions)}
    channel_of_block = {}
    for gbs, channel in zip(map(tuple, city.gbs.positions), city.gbs.channels, strict=True):
        assert channel_of_block.setdefault(centre[gbs], channel) == channel
    assert len(channel_of_block) == 16 and len(set(channel_of_block.values())) == 9
    for a, channel_a in channel_of_block.items():
        for b, channel_b in channel_of_block.items():
            if a != b and channel_a == channel_b:
                assert max(abs(a[0] - b[0]), abs(a[1] - b[1])) == 3


def test_every_gbs_covers_its_cell_as_its_icc2021_counterpart(city, icc2021):
    # A GBS's counterpart: the icc2021 GBS at the same place in its 100 m block.
    counterpart = [(x - (x + 200) // 100 * 100 + 150, y - (y + 200) // 100 * 100 + 150)
                   for x, y in city.gbs.positions]
    assert set(counterpart) == set(map(tuple, icc2021.gbs.positions))
    shares = dict(zip(map(tuple, icc2021.gbs.positions),
                      covered_shares(icc2021, icc2021.gbs.positions), strict=True))
    expected = np.array([shares[gbs] for gbs in counterpart])
    city_shares = covered_shares(city, city.gbs.positions)
    np.testing.assert_allclose(city_shares, expected, atol=0.02)
    # One channel for all: 180 more GBSs interfere with every cell.
    one_channel = city.model_copy(update={"gbs": city.gbs.model_copy(update={"channels": None})})
    assert (covered_shares(one_channel, city.gbs.positions) < expected - 0.1).mean() > 0.9


def test_near_pairs_finds_every_pair_within_reach():
    rng = np.random.default_rng(4)
    position = rng.uniform(-200, 200, size=(2, 300, 2))
    active = rng.random((2, 300)) < 0.9
    env, first, second = near_pairs(position, active, 12.0)
    found = set(zip(env.tolist(), first.tolist(), second.tolist(), strict=True))
    expected = {(e, i, k) for e in range(2) for i in range(300) for k in range(i + 1, 300)
                if active[e, i] and active[e, k]
                and np.hypot(*(position[e, i] - position[e, k])) <= 12.0}
    assert found == expected and len(expected) > 100


def test_256_uavs_fly_the_city_and_decide_as_if_they_saw_everyone(city):
    policy = load_policy(city, EXTENDED_VALUE_NET)
    maps = perfect_maps(city)
    controller = LookaheadController(policy, maps)
    world = VectorWorld(city, 1, 256)
    world.reset([0], [5])
    rows = np.arange(256)
    for _ in range(3):
        near = fleet_observation(world)
        w = world
        everyone = Observation.of_fleet(w.position, w.velocity, w.heading, w.destination,
                                        w.radius, w.max_speed, w.level, w.below_steps,
                                        w.active, w.steps)
        assert near.others_present.shape[1] < 40 < everyone.others_present.shape[1]
        radio_map = maps(world, rows)
        np.testing.assert_array_equal(policy.decide(near, radio_map).action,
                                      policy.decide(everyone, radio_map).action)
        before = world.position.copy()
        speed, heading = controller.act(world)
        world.step(speed, heading)
        moved = np.hypot(*(world.position - before).reshape(-1, 2).T)
        assert np.all(moved <= city.uav.max_speed_mps * city.timing.step_s + 1e-9)
    # No trip is that short, and the safe cells keep every pair apart: a UAV has either flown on
    # or, starting between coverage islands, been below T_s too long.
    assert np.isin(world.status, [Outcome.ACTIVE, Outcome.DISCONNECTION]).all()
    lost = world.status == Outcome.DISCONNECTION
    assert (world.below_steps[lost] > city.timing.disconnection_limit_steps).all()
    assert (world.status == Outcome.ACTIVE).mean() > 0.5


def test_the_cloud_places_every_city_measurement_by_its_named_gbs(city):
    xy = np.random.default_rng(3).uniform(-200, 200, size=(500, 2))
    features = scenario_features(city, xy)
    # A position is a GBS's (named in float32) less a float32 offset: two roundings at most.
    read = np.abs(features[:, list(range(2)) + [-2, -1]]).max()
    np.testing.assert_allclose(positions_from_features(city, features), xy,
                               atol=2 * bounds.rounded_once(read))
    # A measurement naming a place where no GBS stands is refused.
    moved = features.copy()
    moved[:, -2] += 12.5
    assert np.isnan(positions_from_features(city, moved)).all()
    # Offsets alone fit several places of the repeated layout: most cannot be placed.
    unnamed = city.changed({"policy.nearest_gbs_position": False})
    placed = ~np.isnan(positions_from_features(unnamed, scenario_features(unnamed, xy))[:, 0])
    assert placed.mean() < 0.2
