"""The compiled planner (planning.lookahead) against its reference, the numpy planner of
planning.reference: the same action and, within float32's rounding, the same scores, on states
recorded in flights of the shipped networks and on random states that exercise every part of
the lookahead (reciprocal others, safe cells, the deeper search)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from cloud_service.rollout import LookaheadController, perfect_maps
from cloud_service.torch_networks import TorchValueNetwork
from planning import PLANNER_VARIABLE, PlannerError
from planning.chosen import lookahead_policy
from planning.features import (
    ABSENT_DISTANCE,
    EXTENDED_METHOD,
    OTHER_FEATURES,
    OWN_FEATURES,
    MethodOptions,
    joint_state_size,
)
from planning.lookahead import CompiledLookahead
from planning.maps import RasterMap
from planning.networks import ValueNetwork, load_network
from planning.reference import LookaheadPolicy
from shared.observation import Observation
from shared.paper import TABLE_I_JAMMERS, jammer_params
from shared.shipped import EXTENDED_CROWD_VALUE_NET, EXTENDED_VALUE_NET, VALUE_NET
from tests import float32_bounds as bounds
from tests.test_policy import untrained
from world_sim.core import VectorWorld, episode_seed, fleet_observation

ROOT = Path(__file__).resolve().parent.parent

# Either planner's value of a state against exact arithmetic on the reference's float32 state
# (tests/float32_bounds.py: the standardization, the dense layers in any order of summation,
# tanh and the scale), with the planners' own features off by one float32 rounding (u |x|,
# u = 2^-24) of float64 values computed in up to 16 operations on quantities below 2^11 m,
# each off by half an ulp of 2^11 at most (FEATURE_SLACK); the features both copy (a UAV's
# radius, top speed, level, steps below T_s, the constant zeros, an absent other's block) are
# the same exactly. A score R + gamma V differs by gamma (or, searched deeper, gamma^2 <=
# gamma) times the two planners' value errors, plus the float64 rounding of the rewards:
# REWARD_SLACK.
FEATURE_SLACK = 16 * 2.0**-42
REWARD_SLACK = 1e-12


def value_error_bound(network: ValueNetwork, states: np.ndarray) -> np.ndarray:
    """The most either planner's value of each of ``states`` (K, F) can differ from exact
    (K,), the reference's float32 states standing in for the exact features."""
    rounded = np.where(computed_features(network, states),
                       bounds.UNIT_ROUNDOFF * np.abs(states.astype(np.float64))
                       + FEATURE_SLACK, 0.0)
    return bounds.values(network, states, rounded).bound


def computed_features(network: ValueNetwork, states: np.ndarray) -> np.ndarray:
    """Which features (K, F) the planners compute, rather than copy (see above)."""
    own, width = len(OWN_FEATURES), len(OTHER_FEATURES)
    others = (states.shape[1] - own - 1 - sum(
        MethodOptions.from_dict(network.method)[:2])) // width
    computed = np.ones(states.shape, dtype=bool)
    computed[:, [OWN_FEATURES.index(name) for name in
                 ("dest_y", "dest_azimuth", "radius", "max_speed")]] = False
    computed[:, own + width * others:] = False  # level, steps below, and the route distance:
    computed[:, -1] |= MethodOptions.from_dict(network.method).route_distance  # computed
    for k in range(others):
        block = states[:, own + k * width : own + (k + 1) * width]
        absent = (block[:, 0] == -ABSENT_DISTANCE) & (block[:, 1:4] == 0).all(axis=1)
        computed[absent, own + k * width : own + (k + 1) * width] = False
    return computed


def score_bound(scenario, network: ValueNetwork, asked: list[np.ndarray],
                searched: np.ndarray) -> np.ndarray:
    """How far the two planners' scores of each row may differ (N,): the reference asks for
    the one-step states of every row first (N x actions), then for the leaves of the deeper
    search, whose bound the rows ``searched`` deeper (N,) share."""
    one_step = value_error_bound(network, asked[0]).reshape(len(searched), -1).max(axis=1)
    deeper = max((value_error_bound(network, leaves).max() for leaves in asked[1:]),
                 default=0.0)
    values = np.where(searched, np.maximum(one_step, deeper), one_step)
    return scenario.policy.gamma * 2 * values + REWARD_SLACK


class Recording(ValueNetwork):
    """A network's own values, keeping every state the planner asks about."""

    def __init__(self, network: ValueNetwork):
        super().__init__(network.architecture(), network.tensors)
        self.network = network
        self.states: list[np.ndarray] = []

    def __call__(self, states):
        self.states.append(states.reshape(-1, states.shape[-1]))
        return self.network(states)


def compare(scenario, network: ValueNetwork, observation: Observation, radio_map: RasterMap,
            **options) -> dict[str, int]:
    """Both planners on the same rows: every score within the bound (and the same moves
    ruled out), so the same action wherever the reference's two best scores are further
    apart than twice the bound (the tie margin), and the chosen values within the bound.
    Counts of the rows, of those within the tie margin, and of different actions."""
    recording = Recording(network)
    reference = LookaheadPolicy(scenario, recording, **options)
    _, want, _ = reference.scored(observation, radio_map)
    got = CompiledLookahead(scenario, network, **options).decide_scored(observation, radio_map)
    searched = (~np.isfinite(want) & got.allowed).any(axis=1)
    bound = score_bound(scenario, network, recording.states, searched)
    finite = np.isfinite(want)
    np.testing.assert_array_equal(np.isfinite(got.score), finite)
    row_bound = np.broadcast_to(bound[:, None], want.shape)
    assert np.all(np.abs(got.score[finite] - want[finite]) <= row_bound[finite])
    top_two = -np.sort(-want, axis=1)[:, :2]
    tied = top_two[:, 0] - top_two[:, 1] <= 2 * bound
    chosen = want.argmax(axis=1)
    assert np.array_equal(got.decision.action[~tied], chosen[~tied])
    rows = np.arange(len(observation))
    assert np.all(np.abs(got.decision.value - want[rows, got.decision.action]) <= bound)
    return {"rows": len(observation), "tied": int(tied.sum()),
            "different": int((got.decision.action != chosen).sum()),
            "searched deeper": int(searched.sum()), "bound": float(bound.max())}


def flown_states(scenario, network_path: Path, envs: int, steps: int, seed: int):
    """Every step's observations of a fleet flown by the reference planner with the shipped
    network at ``network_path`` on Table I's jammers, and its maps."""
    network, _ = load_network(network_path)
    controller = LookaheadController(LookaheadPolicy(scenario, network), perfect_maps(scenario))
    world = VectorWorld(scenario, envs, 4)
    world.reset(np.arange(envs), [episode_seed(seed, k) for k in range(envs)])
    for env in range(envs):
        world.set_jammer([env], jammer_params(scenario, TABLE_I_JAMMERS[env % 4]))
    for _ in range(steps):
        rows = np.flatnonzero(world.active.ravel())
        if rows.size == 0:
            return
        yield network, fleet_observation(world).select(rows), controller.map_for(world, rows)
        world.step(*controller.act(world))


@pytest.mark.parametrize("network_path", [EXTENDED_VALUE_NET, EXTENDED_CROWD_VALUE_NET,
                                          VALUE_NET])
def test_recorded_flights_are_decided_alike(scenario, network_path):
    counts = {"rows": 0, "tied": 0, "different": 0, "searched deeper": 0, "bound": 0.0}
    for network, observation, radio_map in flown_states(scenario, network_path, 32, 30, 7):
        for key, value in compare(scenario, network, observation, radio_map).items():
            counts[key] = max(counts[key], value) if key == "bound" else counts[key] + value
    assert counts["rows"] > 1500
    # The bound is a worst case, met only where every rounding errs one way: the scores of
    # the two planners lie far closer, and ties within it rarely change an action.
    assert counts["different"] * 1000 <= counts["rows"]
    if network_path != VALUE_NET:  # the paper's method searches one step only
        assert counts["searched deeper"] > 0


def random_fleet(scenario, rng: np.random.Generator, n: int, others: int) -> Observation:
    """UAVs anywhere in the area, in any state, each with up to ``others`` others nearby:
    crowded enough for collisions, safe cells and reciprocal avoidance to matter."""
    area, top = scenario.area, scenario.uav.max_speed_mps
    position = np.column_stack([rng.uniform(area.x_min, area.x_max, n),
                                rng.uniform(area.y_min, area.y_max, n)])
    nearby = position[:, None] + rng.uniform(-12.0, 12.0, (n, others, 2))
    return Observation(
        position=position, velocity=rng.uniform(-top, top, (n, 2)) / math.sqrt(2),
        heading=rng.uniform(-math.pi, math.pi, n),
        destination=np.column_stack([rng.uniform(area.x_min, area.x_max, n),
                                     rng.uniform(area.y_min, area.y_max, n)]),
        radius=rng.uniform(0.5, 1.5, n), max_speed=np.full(n, top),
        level=rng.integers(0, scenario.channel.level_count, n),
        below_steps=rng.integers(0, scenario.timing.disconnection_limit_steps + 1, n),
        step=rng.integers(0, 100, n), others_position=nearby,
        others_velocity=rng.uniform(-top, top, (n, others, 2)) / math.sqrt(2),
        others_radius=rng.uniform(0.5, 1.5, (n, others)),
        others_present=rng.random((n, others)) < 0.7)


def jammed_map(scenario, rng: np.random.Generator, n: int) -> RasterMap:
    """Each row on one of Table I's jammed maps."""
    maps = perfect_maps(scenario)
    rasters = [maps.raster(jammer_params(scenario, setting)) for setting in TABLE_I_JAMMERS]
    return RasterMap(scenario, rasters, rng.integers(0, len(rasters), n))


@pytest.mark.parametrize("options", [
    {"lookahead_depth": 2, "others_model": "reciprocal"},
    {"lookahead_depth": 3, "others_model": "constant_velocity"},
    {"lookahead_depth": 1, "others_model": "reciprocal", "shield": False},
])
def test_random_states_are_decided_alike(scenario, options):
    rng = np.random.default_rng(11)
    network = untrained(joint_state_size(scenario, EXTENDED_METHOD), EXTENDED_METHOD._asdict())
    n = 150 if options["lookahead_depth"] == 3 else 600
    counts = compare(scenario, network, random_fleet(scenario, rng, n, 6),
                     jammed_map(scenario, rng, n), **options)
    assert counts["different"] * 1000 <= n
    if options["lookahead_depth"] > 1:
        assert counts["searched deeper"] > n // 20


def test_a_batch_is_decided_as_its_rows_one_by_one(scenario):
    """The batched entry and the one-UAV entry (an agent's) give the same decisions, bit
    for bit: one core decides each row alone."""
    rng = np.random.default_rng(3)
    network, _ = load_network(EXTENDED_VALUE_NET)
    policy = CompiledLookahead(scenario, network)
    fleet, radio_map = random_fleet(scenario, rng, 40, 5), jammed_map(scenario, rng, 40)
    together = policy.decide(fleet, radio_map)
    for row in range(40):
        alone = policy.decide(fleet.select(np.array([row])), radio_map.for_rows(np.array([row])))
        assert (alone.action[0], alone.value[0]) == (together.action[row], together.value[row])


def test_exploration_draws_as_the_reference_does(scenario):
    rng = np.random.default_rng(5)
    network = untrained(joint_state_size(scenario, EXTENDED_METHOD), EXTENDED_METHOD._asdict())
    fleet, radio_map = random_fleet(scenario, rng, 200, 4), jammed_map(scenario, rng, 200)
    decisions = [policy.decide(fleet, radio_map, 0.3, np.random.default_rng(9))
                 for policy in (LookaheadPolicy(scenario, network),
                                CompiledLookahead(scenario, network))]
    explored = np.isnan(decisions[0].value)
    assert explored.any()
    np.testing.assert_array_equal(np.isnan(decisions[1].value), explored)
    np.testing.assert_array_equal(decisions[1].action[explored], decisions[0].action[explored])
    np.testing.assert_array_equal(decisions[1].heading[explored],
                                  decisions[0].heading[explored])


def test_training_updates_reach_the_compiled_planner(scenario):
    """Training flies a network over its torch module's memory: a step of the optimizer,
    in place, reaches a compiled planner built before it."""
    torch.manual_seed(1)
    module = TorchValueNetwork(joint_state_size(scenario, EXTENDED_METHOD), 2.0,
                               EXTENDED_METHOD._asdict())
    network = module.inference()
    compiled = CompiledLookahead(scenario, network)
    rng = np.random.default_rng(8)
    fleet, radio_map = random_fleet(scenario, rng, 50, 4), jammed_map(scenario, rng, 50)
    before = compiled.decide(fleet, radio_map).value
    with torch.no_grad():
        for parameter in module.body.parameters():
            parameter.mul_(1.5)
    after = compiled.decide(fleet, radio_map).value
    assert not np.array_equal(after, before)
    built_after = CompiledLookahead(scenario, network).decide(fleet, radio_map).value
    np.testing.assert_array_equal(after, built_after)


def test_the_environment_chooses_the_planner(scenario, monkeypatch):
    network, _ = load_network(VALUE_NET)
    monkeypatch.delenv(PLANNER_VARIABLE, raising=False)
    assert type(lookahead_policy(scenario, network)) is CompiledLookahead
    monkeypatch.setenv(PLANNER_VARIABLE, "reference")
    assert type(lookahead_policy(scenario, network)) is LookaheadPolicy
    monkeypatch.setenv(PLANNER_VARIABLE, "fast")
    with pytest.raises(PlannerError, match="reference"):
        lookahead_policy(scenario, network)


def test_a_scripted_network_is_refused_by_the_compiled_planner(scenario):
    class Scripted(ValueNetwork):
        def __call__(self, states):
            return states[..., 0]

    network, _ = load_network(VALUE_NET)
    with pytest.raises(TypeError, match="Scripted"):
        CompiledLookahead(scenario, Scripted(network.architecture(), network.tensors))


# Asks for the compiled planner, or a route grid, with a module of the core missing or stamped
# from other source; prints the error's one line.
BROKEN_CORE = """
import json, sys
import numpy as np
import planning.source_digest
fault, module, asked = sys.argv[1:]
if fault == "missing":
    sys.modules[f"planning.{module}"] = None
else:
    planning.source_digest.source_digest = lambda directory: "other source"
try:
    if asked == "planner":
        from planning.chosen import require_planner
        require_planner()
    else:
        from planning.routes import RouteGrid
        RouteGrid(np.ones((3, 3), dtype=bool), 0.0, 0.0, 1.0, 4.0)
except Exception as exc:
    print(json.dumps([type(exc).__name__, str(exc)]))
"""


@pytest.mark.parametrize(("fault", "module", "asked"), [
    ("missing", "_lookahead", "planner"), ("missing", "_routes", "planner"),
    ("missing", "_routes", "routes"), ("stale", "_lookahead", "planner"),
    ("stale", "_routes", "routes")])
def test_a_missing_or_stale_core_is_an_error_naming_the_fix(fault, module, asked):
    """A process that asks for the compiled planner is stopped as it starts, whichever module
    of its core is at fault, and a route grid is never built by the reference instead."""
    done = subprocess.run([sys.executable, "-c", BROKEN_CORE, fault, module, asked], cwd=ROOT,
                          capture_output=True, text=True, timeout=60,
                          env={k: v for k, v in os.environ.items() if k != PLANNER_VARIABLE})
    kind, message = json.loads(done.stdout)
    assert kind == "PlannerError" and "make install" in message and "\n" not in message
    if fault == "missing":
        assert module in message


def test_jamnav_reports_a_bad_planner_in_one_line():
    done = subprocess.run([sys.executable, "-m", "jamnav.cli", "eval", "--episodes", "1"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120,
                          env={**os.environ, PLANNER_VARIABLE: "fast"})
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and PLANNER_VARIABLE in done.stderr
