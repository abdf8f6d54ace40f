"""A large fleet on the bus: each agent is sent only the others that can change its decision,
so an observation's size does not grow with the fleet, and the decision is the one the whole
fleet's observation gives."""

from __future__ import annotations

import logging
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jamnav.cli_runtime import _describe_agents
from jamnav.run_report import agents_line
from jamnav.supervisor import fleet_line
from planning.maps import MAP_SPACING_M, LevelRaster, RasterMap
from planning.networks import load_network
from planning.reference import LookaheadPolicy
from shared.observation import Observation, decision_reach, decision_relevant
from shared.process_status import ProcessStatus
from shared.radio import RadioModel
from shared.shipped import VALUE_NETS
from shared.wire import decode, encode
from shared.world_messages import AgentObservation, WorldState
from world_sim import process as world_process
from world_sim.core import VectorWorld, episode_seed
from world_sim.process import WorldConfig, WorldService, observation_sent


def sent_sizes(scenario, uavs: int, trimmed: bool = True) -> list[int]:
    """Encoded size of every observation the world sends in the first steps of episodes."""
    world = VectorWorld(scenario, 1, uavs)
    sizes = []
    for episode in range(3):
        world.reset([0], [episode_seed(0, episode)])
        for _ in range(5):
            if trimmed:
                observation, relevant = observation_sent(world)
            else:
                observation, relevant = whole_fleet(world), [None] * uavs
            sizes += [len(encode(AgentObservation.of_row(
                observation, uav, episode, uav, others=relevant[uav]))) for uav in range(uavs)]
            world.step(np.full((1, uavs), scenario.uav.max_speed_mps), world.heading)
    return sizes


def test_an_observation_stays_as_small_with_64_uavs_as_with_8(scenario):
    few, many = sent_sizes(scenario, 8), sent_sizes(scenario, 64)
    # The J_n nearest on average, a few more in a crowd; the whole fleet would be eight times
    # the others, so the bound is the trimming's doing.
    assert np.mean(many) < 1.1 * np.mean(few) and max(many) < 2 * max(few)
    assert min(sent_sizes(scenario, 64, trimmed=False)) > 4 * max(few)


def test_the_others_sent_are_the_nearest_and_those_in_reach(scenario):
    world = VectorWorld(scenario, 1, 64)
    world.reset([0], [episode_seed(0, 1)])
    world.status[0, ::7] = 1  # a few have finished: never sent
    observation, relevant = observation_sent(world)
    count = scenario.policy.observed_uavs
    reach = decision_reach(scenario, np.array([scenario.uav.radius_m]))[0]
    for uav in range(64):
        others = [k for k in range(64) if k != uav and world.active[0, k]]
        distance = {k: float(np.linalg.norm(world.position[0, k] - world.position[0, uav]))
                    for k in others}
        nearest = sorted(others, key=lambda k: distance[k])[:count]
        wanted = sorted(set(nearest) | {k for k in others if distance[k] <= reach})
        message = AgentObservation.of_row(observation, uav, 0, uav, others=relevant[uav])
        sent = [k for k in range(64) if k != uav
                and tuple(world.position[0, k].tolist()) in message.others_position]
        assert sent == wanted
        assert all(message.others_present)


@pytest.fixture(scope="module")
def radio_map(scenario):
    radio = RadioModel(scenario)
    raster = LevelRaster.sample(scenario, lambda grid: radio.evaluate(grid).level,
                                MAP_SPACING_M)
    return RasterMap(scenario, [raster], np.zeros(1, dtype=np.int64))


@pytest.fixture(scope="module")
def policies(scenario):
    return [LookaheadPolicy(scenario, load_network(path)[0]) for path in VALUE_NETS.values()]


def crowd(seed: int, uavs: int, side: float, scenario) -> VectorWorld:
    """A world whose random fleet is packed into a square of ``side`` metres, some finished."""
    rng = np.random.default_rng(seed)
    world = VectorWorld(scenario, 1, uavs)
    shape = (1, uavs)
    world.position = rng.uniform(-side / 2, side / 2, shape + (2,))
    world.velocity = rng.uniform(-3.5, 3.5, shape + (2,))
    world.heading = rng.uniform(-np.pi, np.pi, shape)
    world.destination = rng.uniform(-45, 45, shape + (2,))
    world.level = rng.integers(0, 4, shape).astype(np.int8)
    world.below_steps = rng.integers(0, 3, shape)
    world.status = np.where(rng.random(shape) < 0.9, 0, 1).astype(np.int8)
    world.steps = rng.integers(0, 60, 1)
    return world


def whole_fleet(world: VectorWorld) -> Observation:
    w = world
    return Observation.of_fleet(w.position, w.velocity, w.heading, w.destination, w.radius,
                                w.max_speed, w.level, w.below_steps, w.active, w.steps)


def decisions(policy, radio_map, observation: Observation, rows) -> list[tuple]:
    return [tuple(np.asarray(field)[0].tolist() for field in policy.decide(
        observation(row), radio_map)) for row in rows]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), uavs=st.integers(2, 40), side=st.floats(10.0, 90.0))
def test_the_trimmed_observation_decides_as_the_whole_fleet(scenario, radio_map, policies,
                                                           seed, uavs, side):
    world = crowd(seed, uavs, side, scenario)
    fleet = whole_fleet(world)
    observation, relevant = observation_sent(world)
    rows = np.flatnonzero(world.active[0]).tolist()

    def whole(row):
        return fleet.select(np.array([row]))

    def sent(row):
        message = AgentObservation.of_row(observation, row, 0, row, others=relevant[row])
        return decode(AgentObservation, encode(message)).observation()

    for policy in policies:
        assert decisions(policy, radio_map, sent, rows) == decisions(policy, radio_map, whole,
                                                                     rows)


def test_without_the_reach_the_safe_cells_decide_otherwise(scenario, radio_map, policies):
    """The reach is needed: the J_n nearest alone change some decisions of a crowd."""
    fleet = whole_fleet(crowd(3, 40, 30.0, scenario))
    nearest_only = decision_relevant(fleet, scenario.policy.observed_uavs, np.zeros(40))

    def sent(row):
        return AgentObservation.of_row(fleet, row, 0, row, others=nearest_only[row]).observation()

    extended = policies[0]
    assert extended.safe_cells
    assert decisions(extended, radio_map, sent, range(40)) != decisions(
        extended, radio_map, lambda row: fleet.select(np.array([row])), range(40))


def test_fifty_uavs_make_one_progress_line_one_status_line_and_one_summary_line():
    statuses = ["active"] * 46 + ["success"] * 3 + ["collision"]
    sinr = [5.0] * 50
    sinr[7] = -2.4
    state = WorldState(episode=2, step=9, clock="lockstep", t=1.0, position=[(0.0, 0.0)] * 50,
                       velocity=[(0.0, 0.0)] * 50, sinr_db=sinr, level=[1] * 50,
                       status=statuses, destination=[(1.0, 1.0)] * 50)
    assert fleet_line(state) == "50 UAVs: 46 acti (weakest -2dB), 1 coll, 3 succ"
    few = state.model_copy(update={"status": ["active", "success", "success", "collision"],
                                   "sinr_db": [1.0, 2.0, 3.0, 4.0]})
    assert fleet_line(few) == "u0:+1dB u1:succ u2:succ u3:coll"

    agents = {str(i): {"decisions": 100, "decision_p99_us": 1000.0 + i} for i in range(50)}
    assert agents_line(agents) == ("50 reported, 5000 decisions, decision p99 median 1024 us, "
                                   "worst 1049 us (agent 49)")

    def status(i: int) -> ProcessStatus:
        return ProcessStatus(role="agent", ident=str(i), pid=100 + i, t=0.0, episode=3,
                             step=40 - (i == 17), value_version=1, sinr_version=2 + (i > 40),
                             details={"decisions": 10, "decision_p99_us": 500.0 + (i == 5)})

    idents = [str(i) for i in range(50)]
    line = _describe_agents(idents, {("agent", str(i)): status(i) for i in range(49)})
    assert "\n" not in line and line.startswith("agents            50  live (1 not answering)")
    assert ("value net v1, map v2..v3, 490 decisions, decision p99 worst 501 us (agent-5), "
            "furthest behind agent-17 at episode 3 step 39") in line


def test_an_episodes_missed_deadlines_are_named_by_step_and_uav(scenario, caplog):
    """A live agent whose action is late costs its UAV its command, and the episode's warning
    names each step with a miss and whose; a UAV without an agent is no miss."""
    log = logging.getLogger("test-world")
    with mock.patch.multiple(world_process.bus, reliable_publisher=mock.DEFAULT,
                             recoverable_publisher=mock.DEFAULT, subscribe=mock.DEFAULT,
                             serve_status=mock.DEFAULT, declare_alive=mock.DEFAULT):
        world = WorldService(mock.MagicMock(), world_process.Topics("t"), scenario,
                             WorldConfig(uavs=4), (), log)
    world.world.reset([0], [episode_seed(0, 3)])
    world.episode = 3
    for uav in (0, 2, 3):
        world.mailbox.on_presence(mock.Mock(key_expr=f"t/alive/agent/{uav}",
                                            kind=world_process.zenoh.SampleKind.PUT))
    late = {1: world_process.Action(episode=3, step=0, uav=1, speed=1.0, heading=0.0),
            3: world_process.Action(episode=3, step=0, uav=3, speed=1.0, heading=0.0)}
    commands = world._commands(late, {0, 1, 2, 3})
    assert commands[0][0, 1] == commands[0][0, 3] == 1.0
    assert commands[0][0, 0] == commands[0][0, 2] == 0.0  # still at the start
    world.world.step(*commands)
    world._commands({}, {1, 2})
    with caplog.at_level(logging.WARNING, logger="test-world"):
        world._log_misses()
        world._log_misses()  # said once
    assert (world.missed, world.unattended) == (3, 1)
    assert caplog.messages == [
        "episode 3: 3 missed deadlines, at steps 0 (UAVs 0, 2); 1 (UAV 2)"]


class _Publisher:
    """A publisher whose subscriber shows up after ``polls`` looks (never, for None)."""

    def __init__(self, polls: int | None):
        self.polls = polls

    @property
    def matching_status(self):
        if self.polls is not None:
            self.polls -= 1
        return mock.Mock(matching=self.polls is not None and self.polls < 0)


def test_the_world_waits_for_its_joined_agents_subscriptions_together():
    """Each publisher is watched until its subscriber shows up or the time is out, and the
    moment a put needs after a match is waited once for all: a hundred agents joining at once
    cost the first step 5 s, a twentieth of a second each."""
    clock = [0.0]
    slept = []

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        clock[0] += seconds

    with (mock.patch.object(world_process.bus.time, "monotonic", lambda: clock[0]),
          mock.patch.object(world_process.bus.time, "sleep", sleep)):
        matched = world_process.bus.wait_matching(
            [_Publisher(0), _Publisher(3), _Publisher(None), _Publisher(1)], 0.5)
        assert matched == [True, True, False, True]
        assert slept.count(world_process.bus.MATCH_SETTLE_S) == 1
        assert 0.5 <= clock[0] <= 0.5 + world_process.bus.MATCH_SETTLE_S + 0.01
        slept.clear()
        assert world_process.bus.wait_matching([_Publisher(None)], 0.1) == [False]
        assert world_process.bus.MATCH_SETTLE_S not in slept
        slept.clear()
        assert world_process.bus.wait_matching([], 1.0) == [] and slept == []
