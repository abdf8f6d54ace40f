"""Lookahead decisions/s, the compiled planner beside its numpy reference in the same run
(their ratio: the speed-up on this CPU, whichever it is): full evaluation of every permissible
action for 256 UAVs at once (64 environments x 4 UAVs), true map with a jammer, value network
on one CPU thread; for the paper's method (one step), and for the shipped extended network
(route distances, safe cells, reciprocal others, and the scenario's deeper search for UAVs
whose one-step choice is a trap). One UAV's decision alone, as an agent makes it: its time,
and the Python and numpy calls the reference makes, whose fixed cost sets a floor under it.
And what an agent's first decision of an episode adds: the route field to its new
destination."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import numpy as np

from benchmarks.common import Figure, best_rate
from cloud_service.rollout import LookaheadController, RasterMaps, perfect_maps
from cloud_service.torch_networks import TorchValueNetwork
from planning.features import joint_state_size
from planning.lookahead import CompiledLookahead
from planning.maps import MAP_SPACING_M, LevelRaster, TrueMap
from planning.networks import load_network
from planning.reference import LookaheadPolicy
from shared.paper import TABLE_I_JAMMERS, jammer_params
from shared.radio import RadioModel
from shared.scenario import Scenario, load_scenario
from shared.shipped import EXTENDED_VALUE_NET
from world_sim.core import VectorWorld, episode_seed, fleet_observation

PLANNERS = {"reference": LookaheadPolicy, "compiled": CompiledLookahead}


def run() -> list[Figure]:
    scenario = load_scenario()
    world = VectorWorld(scenario, 64, 4)
    world.reset(np.arange(64), [episode_seed(0, k) for k in range(64)])
    networks = {
        "paper's method": TorchValueNetwork(joint_state_size(scenario), 2.0).inference(),
        "extended": load_network(EXTENDED_VALUE_NET)[0],
    }
    figures = []
    for name, network in networks.items():
        rates = {}
        for planner, kind in PLANNERS.items():
            controller = LookaheadController(kind(scenario, network), perfect_maps(scenario))

            def decide(controller: LookaheadController = controller) -> int:
                controller.act(world)
                return int(world.active.sum())

            rates[planner] = best_rate(decide, repeats=3, min_seconds=1.0)
            figures.append(Figure(f"lookahead decisions/s, {name}, {planner} (256 UAVs x all "
                                  "actions, batched)", rates[planner], "decisions/s", 20_000))
        figures.append(Figure("  compiled / reference", rates["compiled"] / rates["reference"],
                              "x", 3))
    extended = {planner: kind(scenario, networks["extended"])
                for planner, kind in PLANNERS.items()}
    figures += single_uav_figures(extended, world, perfect_maps(scenario))
    figures.append(Figure("route field to one new destination, as an agent sweeps it, ms",
                          single_route_field_ms(scenario), "ms", lower_is_better=True))
    return figures


SINGLE_UAV_REPEATS = 20


def single_uav_figures(policies: dict[str, LookaheadPolicy], world: VectorWorld,
                       maps: RasterMaps) -> list[Figure]:
    """Each of the world's UAVs decided alone, as its agent would, by each planner in turn:
    the median and 99th percentile of the time of one decision (the mean of
    SINGLE_UAV_REPEATS in a warm loop), their ratios, and the fewest and most function calls
    (Python's and numpy's) a reference decision makes, counted by the interpreter's profiling
    hook."""
    observation = fleet_observation(world)
    radio_map = maps(world, np.arange(len(observation)))
    alone = [(observation.select(row), radio_map.for_rows(row))
             for row in np.arange(len(observation))[:, None]]
    figures, percentiles = [], {}
    for planner, policy in policies.items():
        times = []
        for case in alone:
            policy.decide(*case)
            start = time.perf_counter()
            for _ in range(SINGLE_UAV_REPEATS):
                policy.decide(*case)
            times.append(1e6 * (time.perf_counter() - start) / SINGLE_UAV_REPEATS)
        percentiles[planner] = np.percentile(times, [50, 99])
        figures += [
            Figure(f"one UAV's decision alone, {planner} (each of the 256 above), median, us",
                   float(percentiles[planner][0]), "us", 500, lower_is_better=True),
            Figure("  99th percentile, us", float(percentiles[planner][1]), "us", 500,
                   lower_is_better=True),
        ]
    speedup = percentiles["reference"] / percentiles["compiled"]
    reference = policies["reference"]
    calls = [_calls(lambda case=case: reference.decide(*case)) for case in alone]
    return figures + [
        Figure("  reference / compiled, median", float(speedup[0]), "x", 10),
        Figure("  reference / compiled, 99th percentile", float(speedup[1]), "x", 10),
        Figure("  function calls of a reference decision, fewest (one step)", min(calls),
               "calls"),
        Figure("  most (the deeper search)", max(calls), "calls"),
    ]


def _calls(work: Callable[[], object]) -> int:
    count = 0

    def hook(frame, event, arg) -> None:
        nonlocal count
        count += event in ("call", "c_call")

    sys.setprofile(hook)
    try:
        work()
    finally:
        sys.setprofile(None)
    return count


ROUTE_DESTINATIONS = 200


def single_route_field_ms(scenario: Scenario) -> float:
    """Mean time of the route field to each of ROUTE_DESTINATIONS distinct destinations, one at
    a time (the numpy sweep an agent runs at its first decision of an episode), on the true
    map with Table I's first jammer."""
    truth = TrueMap(RadioModel(scenario), jammer_params(scenario, TABLE_I_JAMMERS[0]))
    routes = LevelRaster.sample(scenario, truth.level_at, MAP_SPACING_M).routes(scenario)
    nodes = np.random.default_rng(0).choice(routes.rows * routes.cols, ROUTE_DESTINATIONS,
                                            replace=False)
    start = time.perf_counter()
    for node in nodes:
        routes.slots(node[None])  # each a new destination: swept, then cached
    return 1000.0 * (time.perf_counter() - start) / ROUTE_DESTINATIONS
