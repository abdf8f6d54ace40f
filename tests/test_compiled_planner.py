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

from cloud_service.rollout import perfect_maps
from cloud_service.torch_networks import TorchValueNetwork
from planning import PLANNER_VARIABLE, PlannerError
from planning.chosen import lookahead_policy
from planning.compiled import THREADS_VARIABLE
from planning.features import (
    EXTENDED_METHOD,
    joint_state_size,
)
from planning.lookahead import CompiledLookahead
from planning.maps import RasterMap
from planning.networks import ValueNetwork, load_network
from planning.reference import LookaheadPolicy
from shared.observation import Observation
from shared.paper import TABLE_I_JAMMERS, jammer_params
from shared.shipped import EXTENDED_CROWD_VALUE_NET, EXTENDED_VALUE_NET, VALUE_NET
from tests.planner_agreement import Agreement, agreement, flown_states, table_one_jammers
from tests.test_policy import untrained

ROOT = Path(__file__).resolve().parent.parent


def compare(scenario, network: ValueNetwork, observation: Observation, radio_map: RasterMap,
            **options) -> Agreement:
    """Both planners on the same rows, none breaking the agreement rule."""
    counts = agreement(scenario, network, observation, radio_map, **options)
    assert not any(counts.broken().values()), counts
    return counts


@pytest.mark.parametrize("network_path", [EXTENDED_VALUE_NET, EXTENDED_CROWD_VALUE_NET,
                                          VALUE_NET])
def test_recorded_flights_are_decided_alike(scenario, network_path):
    network, _ = load_network(network_path)
    counts = Agreement()
    for observation, radio_map in flown_states(scenario, network, perfect_maps(scenario), 32,
                                               30, 7, table_one_jammers):
        counts += compare(scenario, network, observation, radio_map)
    assert counts.rows > 1500
    # The bound is a worst case, met only where every rounding errs one way: the scores of
    # the two planners lie far closer, and ties within it rarely change an action.
    assert counts.different * 1000 <= counts.rows
    if network_path != VALUE_NET:  # the paper's method searches one step only
        assert counts.searched_deeper > 0


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
    assert counts.different * 1000 <= n
    if options["lookahead_depth"] > 1:
        assert counts.searched_deeper > n // 20


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
import shared.source_digest
fault, module, asked = sys.argv[1:]
if fault == "missing":
    sys.modules[module] = None
else:
    shared.source_digest.source_digest = lambda root: "other source"
try:
    if asked == "radio":
        from shared.radio import RadioModel
        from shared.scenario import load_scenario
        RadioModel(load_scenario())
    elif asked == "planner":
        from planning.chosen import require_planner
        require_planner()
    elif asked == "regression":
        import torch
        from cloud_service.torch_networks import TorchValueNetwork
        from cloud_service.adam_step import adam_step
        net = TorchValueNetwork(4, 2.0)
        adam_step(net, torch.optim.Adam(net.parameters()))
    else:
        from planning.routes import RouteGrid
        RouteGrid(np.ones((3, 3), dtype=bool), 0.0, 0.0, 1.0, 4.0)
except Exception as exc:
    print(json.dumps([type(exc).__name__, str(exc)]))
"""


@pytest.mark.parametrize(("fault", "module", "asked"), [
    ("missing", "planning._lookahead", "planner"), ("missing", "planning._routes", "planner"),
    ("missing", "planning._routes", "routes"), ("stale", "planning._lookahead", "planner"),
    ("stale", "planning._routes", "routes"), ("missing", "planning._regression", "regression"),
    ("stale", "planning._regression", "regression"), ("missing", "shared._radio", "radio"),
    ("stale", "shared._radio", "radio")])
def test_a_missing_or_stale_core_is_an_error_naming_the_fix(fault, module, asked):
    """A process that asks for the compiled core is stopped as it starts, whichever module of
    it is at fault, and neither a route grid, a training step nor a radio reading is made by
    the reference instead."""
    done = subprocess.run([sys.executable, "-c", BROKEN_CORE, fault, module, asked], cwd=ROOT,
                          capture_output=True, text=True, timeout=60,
                          env={k: v for k, v in os.environ.items() if k != PLANNER_VARIABLE})
    kind, message = json.loads(done.stdout)
    assert kind == "CompiledCoreError" and "make install" in message and "\n" not in message
    if fault == "missing":
        assert module in message


def test_jamnav_reports_a_bad_planner_in_one_line():
    done = subprocess.run([sys.executable, "-m", "jamnav.cli", "eval", "--episodes", "1"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120,
                          env={**os.environ, PLANNER_VARIABLE: "fast"})
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and PLANNER_VARIABLE in done.stderr


def test_two_threads_decide_a_batch_as_one_does(scenario, monkeypatch):
    """A batch's halves decided on two threads at once (planning.compiled.on_two_cores): the
    same decisions, scores and safe cells, bit for bit."""
    rng = np.random.default_rng(6)
    network, _ = load_network(EXTENDED_VALUE_NET)
    fleet, radio_map = random_fleet(scenario, rng, 300, 5), jammed_map(scenario, rng, 300)
    scored = {}
    for threads in ("1", "2"):
        monkeypatch.setenv(THREADS_VARIABLE, threads)
        scored[threads] = CompiledLookahead(scenario, network).decide_scored(fleet, radio_map)
    for name in ("score", "allowed"):
        np.testing.assert_array_equal(getattr(scored["2"], name), getattr(scored["1"], name))
    for name in ("action", "speed", "heading", "value"):
        np.testing.assert_array_equal(getattr(scored["2"].decision, name),
                                      getattr(scored["1"].decision, name))
    monkeypatch.setenv(THREADS_VARIABLE, "4")
    with pytest.raises(PlannerError, match=THREADS_VARIABLE):
        CompiledLookahead(scenario, network).decide(fleet, radio_map)


# Starts a service with a module of the compiled core missing; the service's set-up must stop
# it before it connects anywhere.
SERVICE_WITHOUT = """
import sys
module, service = sys.argv[1:3]
sys.modules[module] = None
from importlib import import_module
sys.exit(import_module(service).main(sys.argv[3:]))
"""


@pytest.mark.parametrize(("module", "service"), [
    ("shared._radio", "world_sim.process"), ("shared._radio", "cloud_service.process"),
    ("planning._evidence", "cloud_service.process"), ("planning._lookahead", "uav_agent.process")])
def test_a_service_refuses_a_missing_core_in_one_line(module, service):
    # A port nothing listens on: a service that got past its set-up would wait for a router.
    done = subprocess.run([sys.executable, "-c", SERVICE_WITHOUT, module, service,
                           "--endpoint", "tcp/127.0.0.1:9"], cwd=ROOT, capture_output=True,
                          text=True, timeout=60,
                          env={k: v for k, v in os.environ.items() if k != PLANNER_VARIABLE})
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0
    assert module in done.stderr and "make install" in done.stderr
