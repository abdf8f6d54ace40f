"""Fuzzing a running system: ``jamnav up`` starts the router, the world, the cloud and the
agents, each its own OS process, and every topic of the bus gets 10,000 random or mutated
payloads (subscriptions as puts, queryables as queries) while they fly episodes. Afterwards
every process is the one that was there before (none crashed) and answers, every query was
answered, the run goes on with sane outcomes, the cloud's memory holds only well-formed
measurements, and each refusal was counted where the message was refused (as the processes'
status replies say)."""

from __future__ import annotations

import json
import math
import random
import signal
import time
from collections import Counter

import msgpack
import numpy as np
import zenoh

from cloud_service.process import CLOCK_SKEW_S
from cloud_service.sinr_memory import RUN_DIR_FILE, SinrMemory
from planning.measuring import scenario_features
from planning.networks import sha256
from shared import bus
from shared.cloud_messages import MeasurementUpload, SinrMap, ValueWeights
from shared.events import JammerChanged, UavOutcomes, decode_event
from shared.jammer_messages import JammerCommand
from shared.measurements import Measurement, MeasurementSpec
from shared.topics import Topics
from shared.wire import MessageError, decode, encode
from shared.world_messages import (
    Action,
    AgentObservation,
    MeasurementRound,
    RoundClosed,
    RoundOpened,
    WorldState,
)
from tests.support import Drained, free_endpoint, gone, statuses, upload_of, wait_until

PER_TOPIC = 10_000
IN_FLIGHT = 100  # queries sent before waiting for their replies
# The longest a process may take to have counted the flood's refusals once it is sent: the wait
# ends as soon as the count is right, so only a failing run waits it out.
FLOOD_SETTLE_S = 180
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
        "jammer_event": JammerChanged(t=time.time(), source="world", jammers=[], episode=0,
                                      step=0),
        "upload": upload_of(0, [Measurement(id="fuzz-0", source="uav-0", step=1,
                                            time=time.time(), features=features, level=1)]),
        "jammer": JammerCommand(action="show"),
        "measurement_round": MeasurementRound(round=7, episode=0, step=3, uav=0, flown_s=3.0,
                                              measured=[(1.0, 2.0, 1)]),
        "round_opened": RoundOpened(round=7, flown_s=3.0, uavs=[0, 1]),
        "round_closed": RoundClosed(round=7, serving=0, pending=[(9, 1)]),
    }
    return {name: msgpack.unpackb(encode(message)) for name, message in found.items()}


def refused_by(kind, payload: bytes, key_uav: int | None = None) -> bool:
    """What the receiver must make of ``payload``: True if it is not a valid ``kind`` (any
    event, for ``kind`` None), is about another UAV than the key's, or (an upload) is
    stamped in the future. (The system under test runs lockstep with the online map, so the
    cloud takes an upload of a round as well.)"""
    try:
        message = decode_event(payload) if kind is None else decode(kind, payload)
    except MessageError:
        return True
    if isinstance(message, MeasurementUpload) and (
            message.newest() > time.time() + CLOCK_SKEW_S):
        return True
    return key_uav is not None and getattr(message, "uav", key_uav) != key_uav


# -- the test ----------------------------------------------------------------------------------
BLOCK = zenoh.CongestionControl.BLOCK  # every payload must arrive, none dropped on the way


def fuzz_subscriptions(session, topics: Topics, forms: dict[str, dict], rng: random.Random
                       ) -> dict[str, int]:
    """Puts on every subscribed key; the refusals our own decoder expects, per key."""
    expected_refusals = {}
    puts = [(topics.observation(0), "observation", AgentObservation, 0),
            (topics.action(1), "action", Action, 1),
            (topics.state, "state", WorldState, None),
            (topics.value_weights, "value", ValueWeights, None),
            (topics.sinr_map, "sinr_map", SinrMap, None),
            (topics.event("uav_outcomes"), "event", None, None),
            (topics.event("jammer_changed"), "jammer_event", None, None),
            (topics.measurement_round(0), "measurement_round", MeasurementRound, 0),
            (topics.round_opened, "round_opened", RoundOpened, None),
            (topics.round_closed, "round_closed", RoundClosed, None)]
    for key, form, kind, uav in puts:
        batch = payloads(rng, forms[form], PER_TOPIC)
        expected_refusals[key] = sum(refused_by(kind, p, uav) for p in batch)
        for payload in batch:
            session.put(key, payload, congestion_control=BLOCK)
    return expected_refusals


def fuzz_queryables(session, topics: Topics, forms: dict[str, dict], rng: random.Random
                    ) -> tuple[Counter, Counter]:
    """Queries to every queryable, many in flight at once. Returns the answers to the uploads,
    as (refused by our decoder, answers), and the queries left without any answer, per key.
    An answer is a reply or a refusal of ours; zenoh's own errors (a timeout) are none."""
    queries = [(topics.measurements(0), "upload"), (topics.jammer_control, "jammer"),
               (topics.value_weights, "value"), (topics.sinr_map, "sinr_map"),
               (topics.status(), "state"), (topics.join, "action")]
    uploads: Counter = Counter()
    unanswered: Counter = Counter()
    for key, form in queries:
        batch = payloads(rng, forms[form], PER_TOPIC)
        for start in range(0, len(batch), IN_FLIGHT):
            sent = batch[start:start + IN_FLIGHT]
            pending = [session.get(key, payload=p, timeout=10, congestion_control=BLOCK)
                       for p in sent]
            for payload, replies in zip(sent, pending, strict=True):
                got = tuple("receipt" if r.ok is not None else "error" for r in replies
                            if r.ok is not None
                            or r.err.payload.to_bytes().startswith(bus.REFUSAL))
                unanswered[key] += not got
                if form == "upload":
                    uploads[refused_by(MeasurementUpload, payload, 0), got] += 1
    return uploads, +unanswered


def test_ten_thousand_bad_payloads_per_topic_crash_nothing(supervisor, scenario, tmp_path):
    rng = random.Random(20261122)
    endpoint, run_dir, topics = free_endpoint(), tmp_path / "run", Topics()
    # The supervisor reports every valid event it hears, fakes included: drain what it says.
    up = Drained(supervisor("--uavs", str(UAVS), "--map", "online", "--no-jammer",
                            "--no-figures", "--endpoint", endpoint, "--run-dir", str(run_dir)))
    with bus.open_session("client", endpoint) as session:
        events: list = []
        session.declare_subscriber(topics.event("uav_outcomes"), lambda sample: events.append(
            sample.payload.to_bytes()))
        wait_until(lambda: events, 120, "the first episode")
        before = statuses(session, topics)
        assert sorted(before) == ["agent-0", "agent-1", "cloud-0", "world-0"]

        expected_refusals = fuzz_subscriptions(session, topics, templates(scenario), rng)
        uploads, unanswered = fuzz_queryables(session, topics, templates(scenario), rng)

        def dropped(name: str, key: str) -> int | None:
            """What ``name`` counts as refused on ``key``; None while it is still too busy
            refusing the flood to answer a status query in time (the pids are checked below:
            a process that died and came back fails there)."""
            status = statuses(session, topics).get(name)
            return None if status is None else status.dropped.get(key, 0)

        def counted_once(name: str, key: str, expected: int) -> None:
            """Waits for ``name``'s count of refusals on ``key`` to reach ``expected``. A
            process works through the flood's valid messages too (an observation is planned
            on), so under load the count may settle long after the last put; a count that
            never settles is reported with the last one seen."""
            seen: list[int | None] = []

            def settled() -> bool:
                seen.append(dropped(name, key))
                return seen[-1] == expected
            try:
                wait_until(settled, FLOOD_SETTLE_S, f"{name}'s refusals on {key}")
            except AssertionError as exc:
                raise AssertionError(f"{exc}: {seen[-1]} counted, {expected} expected") from None

        # The refusals land where the messages were refused, each counted once.
        counted_once("agent-0", topics.observation(0), expected_refusals[topics.observation(0)])
        counted_once("world-0", topics.action("*"), expected_refusals[topics.action(1)])
        for name, key in (("agent-0", topics.measurement_round(0)),
                          ("cloud-0", topics.round_opened), ("world-0", topics.round_closed)):
            counted_once(name, key, expected_refusals[key])
        # Every query was answered: the puts and queries block rather than drop, and this
        # zenoh build keeps no drop counters of its own (the router's metrics hold none) that
        # could explain a missing answer. Each upload was answered once, as our decoder says
        # it should be, and each error answer was counted by the cloud (which may count more:
        # a forged round a fuzzed MeasurementRound handed agent 0 makes it upload reports
        # stamped at the forgery's flight time, which the cloud may refuse in turn).
        assert unanswered == Counter()
        assert set(uploads) <= {(True, ("error",)), (False, ("receipt",))}
        assert dropped("cloud-0", topics.measurements("*")) >= uploads[True, ("error",)]
        assert dropped("world-0", topics.jammer_control) > PER_TOPIC // 2
        for uav in range(UAVS):
            for key in (topics.value_weights, topics.sinr_map):
                assert dropped(f"agent-{uav}", key) >= expected_refusals[key]

        # Every role is alive, the same process as before, and the run goes on: two more
        # episodes end, with outcomes of every UAV.
        seen = len(events)
        wait_until(lambda: len(events) >= seen + 2, 120, "two more episodes' outcomes")
        after = statuses(session, topics)
        assert {n: s.pid for n, s in after.items()} == {n: s.pid for n, s in before.items()}
        assert all(after[f"agent-{uav}"].details["ready"] for uav in range(UAVS))
        assert list(session.liveliness().get(topics.alive("router"), timeout=2))
        real = [decode(UavOutcomes, payload) for payload in events[seen:]]
    up.process.send_signal(signal.SIGINT)
    _, err = up.wait(60)
    assert up.process.returncode == 0, err[-2000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["restarts"] == {"router": 0, "world": 0, "cloud": 0, "agent": 0}
    # The supervisor hears every event: it refused the fakes on both keys, and counted them.
    assert report["dropped_messages"][topics.event("*")] == sum(
        expected_refusals[topics.event(kind)] for kind in ("uav_outcomes", "jammer_changed"))
    assert all(gone(p["pid"]) for p in report["processes"])
    assert len(real) >= 2 and {len(e.outcomes) for e in real} == {UAVS}
    assert {o for e in real for o in e.outcomes} <= {"success", "disconnection", "collision",
                                                     "timeout"}
    with SinrMemory(run_dir / RUN_DIR_FILE, MeasurementSpec.of(scenario)) as memory:
        stored = memory.recent(memory.count())
    assert len(stored) > 0
    assert np.isfinite(stored.features).all()
    assert (stored.times <= time.time()).all()
    assert set(stored.levels.tolist()) <= set(range(scenario.channel.level_count))
