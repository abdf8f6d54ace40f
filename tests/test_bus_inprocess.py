"""The runtime on the bus with every role in this process: a router and one client session per
role on a free loopback port, multicast scouting off. Checks determinism against ``jamnav
eval``, the jammer control topic, refusal of invalid messages, and the online map's answer to
a live jammer swap."""

from __future__ import annotations

import json
import math

import msgpack
import numpy as np
import pytest
import torch

from cloud_service.change_handling import RetrainConfig
from jamnav.cli import main as jamnav
from planning.networks import load_network, save_bytes, sha256
from planning.routes import RouteGrid
from shared.cloud_messages import ValueWeights
from shared.jammer_messages import JammerCommand, JammerEstimate, JammerInfo
from shared.shipped import VALUE_NET
from shared.wire import decode, encode
from shared.world_messages import AgentObservation
from tests.support import running, wait_until

torch.set_num_threads(1)


def eval_outcomes(capsys, method: str, episodes: int, uavs: int, seed: int, jammer: str):
    assert jamnav(["eval", "--method", method, "--episodes", str(episodes), "--uavs", str(uavs),
                   "--seed", str(seed), "--jammer", jammer, "--per-episode", "--json"]) == 0
    return json.loads(capsys.readouterr().out)["outcomes"]


@pytest.mark.parametrize("method", ["perfect", "outdated"])
def test_lockstep_over_the_bus_gives_the_outcomes_of_jamnav_eval(scenario, tmp_path, capsys,
                                                                  method):
    jammer = JammerInfo(x=0.0, y=0.0, power_w=1.0, height_m=scenario.jammer.height_m)
    episodes, uavs, seed = 4, 4, 11
    with running(scenario, tmp_path, mode=method, uavs=uavs, jammer=jammer, episodes=episodes,
                 seed=seed) as system:
        finished = system.wait_for("run_finished", 120)
        outcomes = {e.episode: e.outcomes for e in system.of_type("uav_outcomes")}
    assert finished.episodes == episodes and finished.missed_deadlines == 0
    assert sorted(outcomes) == list(range(episodes))
    bus_outcomes = [outcomes[episode] for episode in range(episodes)]
    assert bus_outcomes == eval_outcomes(capsys, method, episodes, uavs, seed, "0,0,1")


def test_jammer_control_replies_and_invalid_messages_are_refused_and_counted(scenario,
                                                                            tmp_path):
    jammer = JammerInfo(x=0.0, y=0.0, power_w=1.0, height_m=30.0)
    with running(scenario, tmp_path, mode="perfect", uavs=2, jammer=jammer,
                 episodes=None) as system:
        system.wait_for("uav_outcomes", 60)
        shown = system.jammer(JammerCommand(action="show"))
        assert shown.accepted and shown.jammers == [jammer]

        far = system.jammer(JammerCommand(action="set", x=500.0, y=0.0, power_w=1.0))
        assert not far.accepted and "outside the area" in far.reason
        assert far.jammers == [jammer]
        nan = system.jammer(msgpack.packb({"action": "set", "x": 0.0, "y": 0.0,
                                           "power_w": float("nan")}))
        assert not nan.accepted and "finite" in nan.reason
        negative = system.jammer(msgpack.packb({"action": "set", "x": 0.0, "y": 0.0,
                                                "power_w": -1.0}))
        assert not negative.accepted and "power_w" in negative.reason
        assert not system.of_type("jammer_changed")

        seen = len(system.events)
        moved = system.jammer(JammerCommand(action="set", x=25.0, y=-10.0, power_w=0.5))
        assert moved.accepted and [j.power_w for j in moved.jammers] == [0.5]
        changed = system.wait_for("jammer_changed", 10, after=seen)
        assert changed.jammers == moved.jammers and changed.jammers[0].height_m == 30.0
        off = system.jammer(JammerCommand(action="off"))
        assert off.accepted and off.jammers == []
        wait_until(lambda: len(system.of_type("jammer_changed")) == 2, 10)
        assert system.of_type("jammer_changed")[-1].jammers == []
        # Switching off what is off, or setting what is set, is accepted and changes nothing.
        assert system.jammer(JammerCommand(action="off")).accepted
        assert system.jammer(JammerCommand(action="set", x=1.0, y=1.0, power_w=0.0)).accepted

        # The true map follows both changes: versions 2 and 3 reach every agent.
        wait_until(lambda: all(a.models.sinr_version == 3 for a in system.agents), 20)
        assert len(system.of_type("jammer_changed")) == 2

        session = system.sessions[0]
        session.put(system.topics.action(0), b"\x93\x01\x02")  # msgpack, but not a map
        session.put(system.topics.action(1), msgpack.packb({"episode": 0, "step": 0, "uav": 1,
                                                            "speed": float("inf"),
                                                            "heading": 0.0}))
        wait_until(lambda: system.world.dropped.as_dict().get(system.topics.action("*")) == 2,
                   5)
        dropped = system.world.dropped.as_dict()
    assert dropped[system.topics.jammer_control] == 2
    assert dropped[system.topics.action("*")] == 2


def test_a_live_jammer_swap_is_detected_located_and_answered_with_a_new_map(scenario,
                                                                          tmp_path):
    # The DNN-only path waits for far more measurements than the estimate needs.
    retrain = RetrainConfig(min_samples=100_000, steps=600, max_seconds=2.0)
    with running(scenario, tmp_path, mode="online", uavs=4, jammer=None, episodes=None,
                 retrain=retrain) as system:
        estimates = []
        system.sessions[0].declare_subscriber(
            system.topics.jammer_estimate,
            lambda sample: estimates.append(decode(JammerEstimate, sample.payload.to_bytes())))
        system.wait_for("uav_outcomes", 60)
        assert [a.models.sinr_version for a in system.agents] == [0, 0, 0, 0]
        seen = len(system.events)
        reply = system.jammer(JammerCommand(action="set", x=0.0, y=0.0, power_w=1.0))
        assert reply.accepted
        changed = system.wait_for("jammer_changed", 10, after=seen)
        detected = system.wait_for("change_detected", 90, after=seen)
        estimated = system.wait_for("jammer_estimated", 90, after=seen)
        first = system.wait_for("sinr_weights_published", 30, after=seen)
        assert changed.t <= detected.t <= first.t and first.version == 1
        # Provisional maps (no estimate) may go out while the estimate converges; the map the
        # estimate corrected follows it.
        wait_until(lambda: any(e.version == estimated.estimate.map_version
                               for e in system.of_type("sinr_weights_published")), 30)
        maps = system.of_type("sinr_weights_published")
        published = next(e for e in maps if e.version == estimated.estimate.map_version)
        assert estimated.t <= published.t and not published.provisional
        assert all(e.provisional for e in maps if e.version < published.version)
        assert detected.version == 0
        estimate = estimated.estimate
        assert estimate.present and math.hypot(estimate.x, estimate.y) <= 3 * max(
            estimate.sd_x_m, estimate.sd_y_m, 2.0)
        wait_until(lambda: estimates, 10, "the estimate on its topic")
        assert estimates[0] == estimate
        saved = tmp_path / "sinr_maps" / f"sinr_map_v{published.version}.safetensors"
        assert published.path == str(saved.resolve()) and saved.is_file()
        wait_until(lambda: all(a.models.sinr_version >= published.version
                               for a in system.agents), 20)
        cloud = system.cloud.status().details
        assert cloud["map_phase"] in ("refining", "watching") and "+-" in cloud["estimate"]


def test_an_agent_refuses_bad_weights_flies_on_with_the_old_ones_and_reports_it(scenario,
                                                                               tmp_path):
    with running(scenario, tmp_path, mode="perfect", uavs=1, jammer=None,
                 episodes=None) as system:
        system.wait_for("uav_outcomes", 60)
        agent, session = system.agents[0], system.sessions[0]
        served = load_network(VALUE_NET)[0]
        good = served.tensors
        metadata = {"architecture": json.dumps(served.architecture())}
        first = next(iter(good))

        def payload(tensors: dict, version: int) -> bytes:
            data = save_bytes(tensors, metadata=metadata)
            return encode(ValueWeights(version=version, sha256=sha256(data), data=data))

        tampered = msgpack.unpackb(payload(good, 7))
        tampered["data"] = tampered["data"][:-1] + b"\x00"  # one byte altered in transit
        session.put(system.topics.value_weights, msgpack.packb(tampered))
        session.put(system.topics.value_weights,
                    payload({**good, first: np.concatenate([good[first], good[first][:1]])}, 8))
        session.put(system.topics.value_weights,
                    payload({**good, first: good[first].astype(np.float64)}, 9))  # wrong dtype
        wait_until(lambda: len(system.of_type("weights_refused")) == 3, 20)
        decisions = agent.decisions
        wait_until(lambda: agent.decisions > decisions + 20, 20)  # still flying
        assert agent.models.value_version == 1
        assert agent.status().dropped[system.topics.value_weights] == 3
    refusals = system.of_type("weights_refused")
    assert [(r.version, r.weights, r.flying_on, r.uav) for r in refusals] == [
        (None, "value", 1, 0), (8, "value", 1, 0), (9, "value", 1, 0)]
    assert "sha256" in refusals[0].reason
    assert "(35,)" in refusals[1].reason and "float64" in refusals[2].reason


def test_an_agent_told_its_next_mission_has_that_route_ready_before_its_first_decision(
        scenario, tmp_path, monkeypatch):
    """The world announces each UAV's next destination with its observations, and the agent
    builds that route field between decisions: with one map all run long, only the very first
    decision builds a field itself (three episodes: three such fields without it)."""
    decision_builds = []
    slots = RouteGrid.slots

    def counted(self, nodes, reach_m=None):
        decision_builds.extend(node for node in nodes.tolist() if node not in self.cache)
        return slots(self, nodes, reach_m)

    monkeypatch.setattr(RouteGrid, "slots", counted)
    announced, flown = {}, {}
    with running(scenario, tmp_path, mode="perfect", uavs=1, jammer=None,
                 episodes=3) as system:
        def seen(sample) -> None:
            observation = decode(AgentObservation, sample.payload.to_bytes())
            announced.setdefault(observation.episode, observation.next_destination)
            flown.setdefault(observation.episode, observation.destination)

        system.sessions[0].declare_subscriber(system.topics.observation(0), seen)
        wait_until(lambda: system.world.finished, 120)
    assert len(decision_builds) == 1
    # What was announced is what was flown next: missions come from each episode's seed.
    pairs = [(announced[episode], flown[episode + 1]) for episode in announced
             if episode + 1 in flown]
    assert pairs and all(told == next_flown for told, next_flown in pairs)
