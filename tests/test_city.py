"""The city scenario: icc2021's world tiled 4 x 4, flown by hundreds of UAVs in-process."""

import numpy as np
import pytest

from cloud_service.evaluation import load_policy
from cloud_service.rollout import LookaheadController, fleet_observation, perfect_maps
from shared.features import Observation
from shared.outcomes import Outcome
from shared.radio import RadioModel
from shared.scenario import Scenario, load_scenario
from shared.shipped import EXTENDED_VALUE_NET, SINR_MAP_NO_JAMMER_CITY, sinr_map_for
from world_sim.core import VectorWorld, near_pairs

BLOCK_CENTRES = (-150.0, -50.0, 50.0, 150.0)


@pytest.fixture(scope="module")
def city() -> Scenario:
    return load_scenario("city")


@pytest.fixture(scope="module")
def icc2021() -> Scenario:
    return load_scenario("icc2021")


def covered_share(scenario: Scenario, gbs: tuple[float, float]) -> float:
    """Share of a GBS's own 25 m x 33 m cell with SINR >= T_s, no jammer (0.5 m raster)."""
    xs = gbs[0] + np.arange(-12.25, 12.5, 0.5)
    ys = gbs[1] + np.arange(-16.25, 16.5, 0.5)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1)
    return float((RadioModel(scenario).evaluate(grid, None).level > 0).mean())


def with_gbs(scenario: Scenario, positions: list[tuple[float, float]]) -> Scenario:
    data = scenario.model_dump()
    data["gbs"]["positions"] = positions
    return Scenario.model_validate(data)


def test_city_is_icc2021_tiled_with_its_density_of_uavs(city, icc2021):
    assert (city.area.x_max - city.area.x_min, city.area.y_max - city.area.y_min) == (400, 400)
    assert city.missions.uav_count == 4 * 16 == icc2021.missions.uav_count * 16
    # Only the mission's time limit grows with the area.
    for section in ("uav", "channel", "jammer", "rewards", "timing"):
        exclude = {"episode_limit_s"} if section == "timing" else None
        assert (getattr(city, section).model_dump(exclude=exclude)
                == getattr(icc2021, section).model_dump(exclude=exclude)), section
    assert city.gbs.model_dump(exclude={"positions"}) == icc2021.gbs.model_dump(
        exclude={"positions"})
    tiled = {(x + bx, y + by) for bx in BLOCK_CENTRES for by in BLOCK_CENTRES
             for x, y in icc2021.gbs.positions}
    assert set(map(tuple, city.gbs.positions)) == tiled
    assert len(city.gbs.positions) == 192
    assert sinr_map_for("city") == SINR_MAP_NO_JAMMER_CITY and SINR_MAP_NO_JAMMER_CITY.is_file()


def test_a_blocks_cells_cover_as_icc2021s_and_interior_cells_alike(city, icc2021):
    # One 100 m block alone is icc2021 moved: each GBS's own cell is covered alike.
    block = [(x + 50.0, y - 50.0) for x, y in icc2021.gbs.positions]
    alone = with_gbs(city, block)
    for (x, y), (bx, by) in zip(icc2021.gbs.positions, block, strict=True):
        assert covered_share(alone, (bx, by)) == pytest.approx(covered_share(icc2021, (x, y)),
                                                               abs=0.005)
    # In the whole city every interior cell is alike, and less covered than icc2021's interior
    # ones: 180 more GBSs interfere.
    interior = [(-112.5, 17.0), (87.5, -83.0), (-37.5, -50.0), (62.5, 117.0), (12.5, 83.0)]
    shares = [covered_share(city, gbs) for gbs in interior]
    assert max(shares) - min(shares) < 0.06
    assert max(shares) < covered_share(icc2021, (-12.5, 0.0)) - 0.15


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
    # or, starting in one of the city's wide uncovered streets, been below T_s too long.
    assert np.isin(world.status, [Outcome.ACTIVE, Outcome.DISCONNECTION]).all()
    lost = world.status == Outcome.DISCONNECTION
    assert (world.below_steps[lost] > city.timing.disconnection_limit_steps).all()
    assert (world.status == Outcome.ACTIVE).mean() > 0.5
