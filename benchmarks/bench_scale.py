"""Scale: the city scenario (scenarios/city.toml, icc2021 tiled 4 x 4) flown in-process by
hundreds of UAVs with the shipped extended network on the true map, beside icc2021's 4 UAVs;
and what the world step, the lookahead and the route fields cost as the fleet grows."""

from __future__ import annotations

import time

import numpy as np

from benchmarks.common import Figure
from cloud_service.evaluation import load_policy
from cloud_service.rollout import (
    LookaheadController,
    RasterMaps,
    outcome_rates,
    perfect_maps,
    run_episodes,
)
from planning.maps import LevelRaster
from shared.paper import JammerSetting, jammer_params
from shared.scenario import Scenario, load_scenario
from shared.shipped import EXTENDED_VALUE_NET
from world_sim.core import VectorWorld, episode_seed

FLEETS = (4, 16, 64, 256, 1024)
TIMED_STEPS = 3


class _Counting:
    """A controller that counts the decisions it makes (one per active UAV per step)."""

    def __init__(self, inner: LookaheadController):
        self.inner = inner
        self.decisions = 0

    def act(self, world: VectorWorld) -> tuple[np.ndarray, np.ndarray]:
        self.decisions += int(world.active.sum())
        return self.inner.act(world)


def _setting(scenario: Scenario) -> JammerSetting:
    return JammerSetting(scenario.jammer.x, scenario.jammer.y, scenario.jammer.power_w)


def _flown(scenario: Scenario, uavs: int, episodes: int) -> tuple[float, float]:
    """Decisions/s over whole episodes (route fields included, the map's raster made before)
    and the success rate."""
    maps = perfect_maps(scenario)
    maps.raster(jammer_params(scenario, _setting(scenario)))
    controller = _Counting(LookaheadController(load_policy(scenario, EXTENDED_VALUE_NET), maps))
    start = time.perf_counter()
    results = run_episodes(scenario, controller, episodes, 0, _setting(scenario), uavs)
    rate = controller.decisions / (time.perf_counter() - start)
    return rate, outcome_rates(results.outcomes)["success_rate"]


def _costs(scenario: Scenario, maps: RasterMaps, uavs: int) -> tuple[float, float, float]:
    """Seconds of one world step, one lookahead step (route fields in hand) and the route
    fields of every UAV's destination (one Dijkstra each) for a fleet of ``uavs``."""
    controller = LookaheadController(load_policy(scenario, EXTENDED_VALUE_NET), maps)
    world = VectorWorld(scenario, 1, uavs)
    world.set_jammer([0], jammer_params(scenario, _setting(scenario)))
    world.reset([0], [episode_seed(0, 0)])
    raster = maps(world, np.arange(uavs)).first
    fresh = LevelRaster(raster.levels, raster.x0, raster.y0, raster.spacing).routes(scenario)
    start = time.perf_counter()
    fresh.distance(world.position[0][:, None], world.destination[0])
    fields = time.perf_counter() - start
    controller.act(world)  # the map's own route fields, made once
    lookahead = stepping = 0.0
    for _ in range(TIMED_STEPS):
        start = time.perf_counter()
        speed, heading = controller.act(world)
        lookahead += time.perf_counter() - start
        start = time.perf_counter()
        world.step(speed, heading)
        stepping += time.perf_counter() - start
    return stepping / TIMED_STEPS, lookahead / TIMED_STEPS, fields


def run() -> list[Figure]:
    city, icc2021 = load_scenario("city"), load_scenario("icc2021")
    figures = []
    rate, success = _flown(city, 256, 1)
    figures += [Figure("city, 256 UAVs: lookahead decisions/s (whole episode)", rate,
                       "decisions/s", 20_000),
                Figure("city, 256 UAVs: success rate, true map (%)", 100 * success, "%")]
    rate, success = _flown(icc2021, 4, 64)
    figures += [Figure("icc2021, 4 UAVs x 64 episodes: decisions/s", rate, "decisions/s"),
                Figure("icc2021, 4 UAVs x 64 episodes: success rate, true map (%)",
                       100 * success, "%")]
    maps = perfect_maps(city)
    for uavs in FLEETS:
        stepping, lookahead, fields = _costs(city, maps, uavs)
        figures += [Figure(f"city, J={uavs}: world step (ms)", 1e3 * stepping, "ms"),
                    Figure(f"city, J={uavs}: lookahead step (ms)", 1e3 * lookahead, "ms"),
                    Figure(f"city, J={uavs}: route fields, all destinations (ms)", 1e3 * fields,
                           "ms")]
    return figures
