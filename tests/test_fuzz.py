"""Fuzzing a running system: every topic of the bus gets 10,000 random or mutated payloads
(subscriptions as puts, queryables as queries) while the world, the cloud and the agents fly
episodes. Afterwards every role is alive and answers, the run goes on with sane outcomes, the
cloud's memory holds only well-formed measurements, and each refusal was counted where the
message was refused."""

from __future__ import annotations

import math
import random
import time
from collections import Counter

import msgpack
import numpy as np
import torch
import zenoh
from support import running, wait_until

from cloud_service.process import CLOCK_SKEW_S
from shared import bus
from shared.measurements import Measurement, MeasurementSpec, scenario_features
from shared.messages import (
    Action,
    AgentObservation,
    JammerChanged,
    JammerCommand,
    MeasurementUpload,
    MessageError,
    ProcessStatus,
    SinrMap,
    UavOutcomes,
    ValueWeights,
    WorldState,
    decode,
    encode,
)
from shared.networks import sha256

torch.set_num_threads(1)

PER_TOPIC = 10_000
IN_FLIGHT = 100  # queries sent before waiting for their replies
UAVS = 2


# -- payloads ----------------------------------------------------------------------------------
def random_value(rng: random.Random, depth: int = 0):
    """Any msgpack value: scalars of every kind (NaN and infinities included), nested a little."""
    roll = rng.random()
    if depth < 3 and roll < 0.15:
        return [random_value(rng, depth + 1) for _ in range(rng.randrange(6))]
    if depth < 3 and roll < 0.3:
        return {rng.choice(["uav", "step", "x", "data", "action", "type", "", "version"]):
                random_value(rng, depth + 1) for _ in range(rng.randrange(5))}
    return rng.choice([
        None, True, False, rng.randrange(-2**63 + 1, 2**63), rng.randrange(-3, 70),
        rng.uniform(-1e9, 1e9), float("nan"), float("inf"), -float("inf"), 1e308, -0.0,
        "".join(rng.choice("ab/*?\x00é") for _ in range(rng.randrange(12))),
        rng.randbytes(rng.randrange(40)), "set", "show", "off", "jammer_changed",
    ])


def mutate(rng: random.Random, template: dict) -> dict:
    """The template with one to three fields replaced, removed, added or blown up."""
    message = dict(template)
    for _ in range(rng.randrange(1, 4)):
        name = rng.choice(list(message) or ["x"])
        roll = rng.random()
        if roll < 0.5:
            message[name] = random_value(rng)
        elif roll < 0.65:
            message.pop(name, None)
        elif roll < 0.75:
            message[f"extra_{rng.randrange(9)}"] = random_value(rng)
        elif isinstance(message.get(name), list) and len(message[name]) < 100:
            message[name] = message[name] * rng.choice([0, 2, 70, 300])
        elif isinstance(message.get(name), int | float) and not isinstance(message[name], bool):
            message[name] = message[name] * rng.choice([-1, 1e6, 1e300, math.nan])
        else:
            message[name] = random_value(rng)
    return message


def payloads(rng: random.Random, template: dict, count: int) -> list[bytes]:
    """Random bytes, random msgpack, mutated messages and damaged encodings, mixed."""
    packed = msgpack.packb(template, use_bin_type=True)
    out = []
    for index in range(count):
        kind = index % 5
        if kind == 0:
            out.append(rng.randbytes(rng.randrange(0, 300)))
        elif kind == 1:
            out.append(msgpack.packb(random_value(rng), use_bin_type=True))
        elif kind in (2, 3):
            out.append(msgpack.packb(mutate(rng, template), use_bin_type=True))
        else:
            damaged = bytearray(packed)
            for _ in range(rng.randrange(1, 6)):
                damaged[rng.randrange(len(damaged))] = rng.randrange(256)
            out.append(bytes(damaged[:rng.randrange(1, len(damaged) + 1)]))
    out[::1000] = [rng.randbytes(2**20 + 1) for _ in out[::1000]]  # oversized
    return out


def templates(scenario) -> dict[str, dict]:
    """A valid message of each kind, as the dict that goes into msgpack."""
    spec = MeasurementSpec.of(scenario)
    weights = b"not safetensors"
    observation = AgentObservation(
        episode=0, step=3, uav=0, position=(1.0, 2.0), velocity=(0.5, 0.0), heading=0.1,
        destination=(30.0, 30.0), radius=1.0, max_speed=5.0, level=1, below_steps=0,
        others_position=[(5.0, 5.0)], others_velocity=[(0.0, 0.0)], others_radius=[1.0],
        others_present=[True])
    features = scenario_features(scenario, np.array([1.0, 2.0])).tolist()
    assert len(features) == spec.feature_size
    found = {
        "observation": observation,
        "action": Action(episode=0, step=3, uav=0, speed=2.0, heading=0.5),
        "state": WorldState(episode=0, step=1, clock="lockstep", t=time.time(),
                            position=[(0.0, 0.0)] * UAVS, velocity=[(0.0, 0.0)] * UAVS,
                            sinr_db=[3.0] * UAVS, level=[1] * UAVS, status=["active"] * UAVS),
        "value": ValueWeights(version=5, sha256=sha256(weights), data=weights),
        "sinr_map": SinrMap(version=5, sha256=sha256(weights), data=weights, mode="online"),
        "event": UavOutcomes(t=time.time(), source="world", episode=9, seed=1, steps=5,
                             outcomes=["success"] * UAVS),
        "jammer_event": JammerChanged(t=time.time(), source="world", jammer=None, episode=0,
                                      step=0),
        "upload": MeasurementUpload(uav=0, measurements=[Measurement(
            id="fuzz-0", source="uav-0", step=1, time=time.time(), features=features,
            level=1)]),
        "jammer": JammerCommand(action="show"),
    }
    return {name: msgpack.unpackb(encode(message)) for name, message in found.items()}


def refused_by(kind, payload: bytes, key_uav: int | None = None) -> bool:
    """What the receiver must make of ``payload``: True if it is not a valid ``kind``, is
    about another UAV than the key's, or (an upload) is stamped in the future."""
    try:
        message = decode(kind, payload)
    except MessageError:
        return True
    if isinstance(message, MeasurementUpload) and max(
            m.time for m in message.measurements) > time.time() + CLOCK_SKEW_S:
        return True
    return key_uav is not None and getattr(message, "uav", key_uav) != key_uav


# -- the test ----------------------------------------------------------------------------------
def test_ten_thousand_bad_payloads_per_topic_crash_nothing(scenario, tmp_path):
    rng = random.Random(20261122)
    with running(scenario, tmp_path, mode="online", uavs=UAVS, jammer=None,
                 episodes=None) as system:
        system.wait_for("uav_outcomes", 90)
        topics, session = system.topics, system.sessions[0]
        forms = templates(scenario)
        block = zenoh.CongestionControl.BLOCK  # every payload must arrive, none dropped

        # Subscriptions: puts. Expected refusals are counted here by the same decoder.
        expected_refusals = {}
        puts = [(topics.observation(0), "observation", AgentObservation, 0),
                (topics.action(1), "action", Action, 1),
                (topics.state, "state", WorldState, None),
                (topics.value_weights, "value", ValueWeights, None),
                (topics.sinr_map, "sinr_map", SinrMap, None),
                (topics.event("uav_outcomes"), "event", None, None),
                (topics.event("jammer_changed"), "jammer_event", None, None)]
        for key, form, kind, uav in puts:
            batch = payloads(rng, forms[form], PER_TOPIC)
            if kind is not None:
                expected_refusals[key] = sum(refused_by(kind, p, uav) for p in batch)
            for payload in batch:
                session.put(key, payload, congestion_control=block)

        # Queryables: queries with a payload, many in flight at once.
        queries = [(topics.measurements(0), "upload"), (topics.jammer_control, "jammer"),
                   (topics.value_weights, "value"), (topics.sinr_map, "sinr_map"),
                   (topics.status(), "state"), (topics.join, "action")]
        answers: Counter = Counter()  # of the uploads: (refused by our decoder, answer)
        for key, form in queries:
            batch = payloads(rng, forms[form], PER_TOPIC)
            for start in range(0, len(batch), IN_FLIGHT):
                sent = batch[start:start + IN_FLIGHT]
                pending = [session.get(key, payload=p, timeout=10, congestion_control=block)
                           for p in sent]
                for payload, replies in zip(sent, pending, strict=True):
                    got = tuple("receipt" if r.ok is not None else "error" for r in replies
                                if r.ok is not None
                                or r.err.payload.to_bytes().startswith(bus.REFUSAL))
                    if form == "upload":
                        answers[refused_by(MeasurementUpload, payload, 0), got] += 1

        # The refusals land where the messages were refused, each counted once.
        wait_until(lambda: system.agents[0].dropped.as_dict().get(topics.observation(0))
                   == expected_refusals[topics.observation(0)], 60, "the observations")
        wait_until(lambda: system.world.dropped.as_dict().get(topics.action("*"))
                   == expected_refusals[topics.action(1)], 60, "the actions")
        # Each upload was answered once, as the decoder says it should be, and each error
        # answer was counted. A few queries get no answer at all: zenoh drops what a busy
        # callback cannot take (an agent would send those again).
        assert set(answers) <= {(True, ("error",)), (False, ("receipt",)), (True, ()),
                                (False, ())}
        assert system.cloud.dropped.as_dict()[topics.measurements("*")] == answers[
            True, ("error",)]
        assert answers[True, ()] + answers[False, ()] < PER_TOPIC // 10
        assert system.world.dropped.as_dict()[topics.jammer_control] > PER_TOPIC // 2
        for agent in system.agents:
            dropped = agent.dropped.as_dict()
            assert dropped[topics.value_weights] >= expected_refusals[topics.value_weights]
            assert dropped[topics.sinr_map] >= expected_refusals[topics.sinr_map]

        # Every role is alive and the run goes on: two more episodes end.
        episode, seen = system.world.episode, len(system.events)
        wait_until(lambda: system.world.episode >= episode + 2, 120, "two more episodes")
        assert all(thread.is_alive() for thread in system.threads)
        assert all(agent.models.ready for agent in system.agents)
        statuses = bus.query(session, topics.status("*", "*"), ProcessStatus)
        assert statuses.pid > 0
        stored = system.cloud.memory.recent(100_000)
        real = [e for e in system.events[seen:] if e.type == "uav_outcomes"]
    assert {len(e.outcomes) for e in real} == {UAVS}
    assert set(e.outcomes[0] for e in real) <= {"success", "disconnection", "collision",
                                                "timeout"}
    assert np.isfinite(stored.features).all()
    assert (stored.times <= time.time()).all()
    assert set(stored.levels.tolist()) <= set(range(scenario.channel.level_count))
