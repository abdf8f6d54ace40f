"""Lookahead decisions/s, the compiled planner beside its numpy reference in the same run
(their ratio: the speed-up on this CPU, whichever it is): full evaluation of every permissible
action for 256 UAVs at once (64 environments x 4 UAVs), true map with a jammer, value network
on one CPU thread; for the paper's method (one step), and for the shipped extended network
(route distances, safe cells, reciprocal others, and the scenario's deeper search for UAVs
whose one-step choice is a trap). One UAV's decision alone, as an agent makes it: its time,
and the Python and numpy calls the reference makes, whose fixed cost sets a floor under it.
And the route fields the extended method reads, by each builder (``route_field_figures``)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from benchmarks.common import Figure, best_rate
from cloud_service.rollout import LookaheadController, RasterMaps, perfect_maps
from cloud_service.torch_networks import TorchValueNetwork
from planning.compiled import compiled_module
from planning.features import joint_state_size
from planning.lookahead import CompiledLookahead
from planning.maps import MAP_SPACING_M, LevelRaster, TrueMap
from planning.networks import load_network
from planning.reference import LookaheadPolicy
from planning.routes import EdgeWeights, FieldBuilder, SweptFields
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
    return figures + route_field_figures()


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


def route_field_figures() -> list[Figure]:
    """The route fields to ROUTE_DESTINATIONS distinct destinations on the true map with
    Table I's first jammer, by the compiled core, by the numpy sweeps of the reference and by
    scipy's Dijkstra (which built the batches before the compiled core), in the same run: one
    at a time on icc2021's grid, as an agent builds the field to its next destination, and all
    in one call on the city's, as a batch of the in-process flights. Whole fields; each mean
    time of a field the best of 3 repeats; the three builders' fields checked equal."""
    figures = []
    for name, one_at_a_time, label in (
            ("icc2021", True, "route field, icc2021, one destination a call"),
            ("city", False, f"route fields, city, {ROUTE_DESTINATIONS} destinations in one call")):
        weights, nodes = _route_grid(load_scenario(name))
        builders = {"compiled": partial(compiled_module("_routes").route_fields, *weights),
                    "reference": SweptFields(weights), "scipy": _scipy_fields(weights)}
        fields = [builder(nodes, np.full(len(nodes), np.inf)) for builder in builders.values()]
        if not all(np.array_equal(other, fields[0]) for other in fields[1:]):
            raise AssertionError(f"{name}: the builders' route fields differ")
        us = {builder: _field_us(build, nodes, one_at_a_time)
              for builder, build in builders.items()}
        figures += [Figure(f"{label}, compiled, us", us["compiled"], "us", lower_is_better=True),
                    Figure("  reference (numpy sweeps), us", us["reference"], "us",
                           lower_is_better=True),
                    Figure("  scipy's Dijkstra, us", us["scipy"], "us", lower_is_better=True),
                    Figure("  reference / compiled", us["reference"] / us["compiled"], "x"),
                    Figure("  scipy / compiled", us["scipy"] / us["compiled"], "x")]
    return figures


def _route_grid(scenario: Scenario) -> tuple[EdgeWeights, np.ndarray]:
    """The edge weights of the scenario's routing grid on the true map with Table I's first
    jammer, and ROUTE_DESTINATIONS distinct nodes of it."""
    truth = TrueMap(RadioModel(scenario), jammer_params(scenario, TABLE_I_JAMMERS[0]))
    routes = LevelRaster.sample(scenario, truth.level_at, MAP_SPACING_M).routes(scenario)
    nodes = np.random.default_rng(0).choice(routes.rows * routes.cols, ROUTE_DESTINATIONS,
                                            replace=False)
    return routes.weights, nodes.astype(np.int64)


def _scipy_fields(weights: EdgeWeights) -> FieldBuilder:
    """scipy's Dijkstra on the same edges and weights, its sparse graph built beforehand."""
    from scipy.sparse import coo_matrix  # noqa: PLC0415 (only this row needs scipy)
    from scipy.sparse.csgraph import dijkstra  # noqa: PLC0415

    rows, cols = weights.right.shape[0], weights.down.shape[1]
    index = np.arange(rows * cols).reshape(rows, cols)
    ends = ((index[:-1, :], index[1:, :], weights.down),
            (index[:, :-1], index[:, 1:], weights.right),
            (index[:-1, :-1], index[1:, 1:], weights.down_right),
            (index[:-1, 1:], index[1:, :-1], weights.down_left))
    graph = coo_matrix((np.concatenate([w.ravel() for _, _, w in ends]),
                        (np.concatenate([a.ravel() for a, _, _ in ends]),
                         np.concatenate([b.ravel() for _, b, _ in ends]))),
                       shape=(rows * cols, rows * cols)).tocsr()

    def build(nodes: np.ndarray, limits: np.ndarray) -> np.ndarray:
        fields = dijkstra(graph, directed=False, indices=nodes, limit=float(limits.max()))
        return fields.reshape(len(nodes), rows, cols)

    return build


def _field_us(build: FieldBuilder, nodes: np.ndarray, one_at_a_time: bool) -> float:
    whole = np.full(len(nodes), np.inf)

    def fields() -> int:
        if one_at_a_time:
            for node, limit in zip(nodes, whole, strict=True):
                build(node[None], limit[None])
        else:
            build(nodes, whole)
        return len(nodes)

    return 1e6 / best_rate(fields, repeats=3, min_seconds=0.5)
