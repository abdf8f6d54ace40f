"""The agent's outbox on disk: what an agent leaves in its file is what the next agent of its
UAV holds and sends, whatever moment the first one died at."""

from __future__ import annotations

import itertools
import logging
import struct
import tempfile
import threading
import time
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planning.measuring import SpotFilter, scenario_features
from shared.cloud_messages import MeasurementUpload
from shared.measurements import Measurement
from shared.topics import Topics
from shared.wire import decode
from shared.world_messages import AgentObservation
from tests.support import wait_until
from uav_agent import process, uploads
from uav_agent.process import main as agent_main
from uav_agent.uploads import DEFAULT_CAPACITY, Outbox, OutboxFile, open_outbox, outbox_path

LOG = logging.getLogger("test-uploads")


def measurements(first: int, count: int) -> list[tuple]:
    """Records as an agent gives them to its outbox (``uploads.FEATURES_DTYPE``): every other
    one with the SINR reported, as from a receiver that reports it."""
    return [(f"0-test-{n}", "uav-0", n, 1e9 + n, struct.pack("<3f", 0.5 * n, -1.0, 12.25), n % 3,
             None if n % 2 else 0.5 * n - 7.0)
            for n in range(first, first + count)]


def held(outbox: Outbox) -> list[tuple]:
    """Everything the outbox would upload, oldest first."""
    return [record for _, record in outbox.wait_batch(1, 0.0, timeout=0, flush=True)]


class Agents:
    """The agents of UAV 0, one after the other: each dies (its file descriptor closed,
    nothing else done) as the next one starts on the file it left."""

    def __init__(self, directory: Path, capacity: int = DEFAULT_CAPACITY):
        self.directory, self.capacity = directory, capacity
        self.file: OutboxFile | None = None

    def next(self) -> Outbox:
        self.die()
        self.file = OutboxFile(outbox_path(self.directory, 0), LOG)
        return Outbox(self.capacity, self.file)

    def die(self) -> None:
        if self.file is not None:
            self.file.close()


def test_the_next_agent_holds_what_had_no_receipt_under_the_same_ids_and_counts(tmp_path):
    agents = Agents(tmp_path)
    first = agents.next()
    taken = measurements(0, 10)
    first.add(taken[:6], batch=64)
    first.add(taken[6:], batch=64)
    first.acknowledge(3, duplicates=1)  # numbers 0..3

    second = agents.next()
    assert held(second) == taken[4:]
    ledger = second.ledger
    assert (ledger.taken, ledger.acknowledged, ledger.duplicates, ledger.overflowed) == (
        10, 4, 1, 0)
    # Its own measurements are numbered on, after the ones it took over.
    second.add(measurements(10, 2), batch=64)
    second.acknowledge(9, refused=2)
    assert held(second) == measurements(10, 2)

    third = agents.next()
    assert held(third) == measurements(10, 2)
    assert (third.ledger.taken, third.ledger.acknowledged, third.ledger.refused) == (12, 10, 2)
    agents.die()


def test_open_outbox_is_memory_only_without_a_directory_and_a_file_per_uav_with_one(tmp_path):
    memory = open_outbox(100, None, 3, LOG)
    memory.add(measurements(0, 3), batch=64)
    memory.close()
    assert len(memory) == 3 and list(tmp_path.iterdir()) == []
    durable = open_outbox(100, tmp_path, 3, LOG)
    durable.add(measurements(0, 3), batch=64)
    durable.close()
    assert [p.name for p in tmp_path.iterdir()] == ["uav-3.outbox"]
    assert held(open_outbox(100, tmp_path, 3, LOG)) == measurements(0, 3)


def test_a_full_outbox_drops_the_oldest_and_the_next_agent_counts_them(tmp_path):
    agents = Agents(tmp_path, capacity=5)
    outbox = agents.next()
    outbox.add(measurements(0, 8), batch=64)
    assert held(outbox) == measurements(3, 5) and outbox.ledger.overflowed == 3
    again = agents.next()
    assert held(again) == measurements(3, 5)
    assert (again.ledger.taken, again.ledger.overflowed) == (8, 3)
    agents.die()


def test_the_file_is_rewritten_as_receipts_come_and_stays_small(tmp_path):
    agents = Agents(tmp_path)
    outbox = agents.next()
    path = outbox_path(tmp_path, 0)
    empty = path.stat().st_size
    sizes = []
    with mock.patch.object(uploads, "REWRITE_AFTER", 200):
        for n in range(0, 5000, 10):
            outbox.add(measurements(n, 10), batch=64)
            if n % 50 == 40:  # a receipt for every 50
                outbox.acknowledge(n + 9)
                outbox.tidy()
            sizes.append(path.stat().st_size)
    record = (sizes[0] - empty) / 10
    # 5,000 measurements went through; the file never held many more than 200 of them.
    assert max(sizes) < empty + 300 * record
    assert [p.name for p in tmp_path.iterdir()] == ["uav-0.outbox"]
    outbox.close()  # a clean stop leaves the ledger alone
    assert path.stat().st_size < record
    again = agents.next()
    assert held(again) == [] and again.ledger.taken == again.ledger.acknowledged == 5000
    agents.die()


def test_an_outbox_written_before_reports_carried_the_sinr_loads_as_level_reports(tmp_path):
    """Records of seven fields (no SINR), as agents wrote them before, are held and sent as
    level reports: an upgrade loses nothing an agent had not yet delivered."""
    old = [record[:-1] for record in measurements(0, 3)]
    frames = b"".join(uploads._frame([0, number, *record]) for number, record in enumerate(old))
    outbox_path(tmp_path, 0).write_bytes(frames)
    agents = Agents(tmp_path)
    assert held(agents.next()) == [(*record, None) for record in old]
    agents.die()


@settings(max_examples=60, deadline=None)
@given(cut=st.integers(min_value=0, max_value=10_000), garbage=st.binary(max_size=12))
def test_a_file_cut_anywhere_loads_the_records_written_whole(cut, garbage):
    """An agent killed while writing leaves a file cut short, maybe with junk after the cut:
    the next one keeps every record written whole before it, warns, and writes on."""
    with tempfile.TemporaryDirectory() as tmp:
        agents = Agents(Path(tmp))
        outbox = agents.next()
        path = outbox_path(Path(tmp), 0)
        boundaries = [path.stat().st_size]  # the ledger's record, then each measurement's
        for measurement in measurements(0, 12):
            outbox.add([measurement], batch=64)
            boundaries.append(path.stat().st_size)
        data = path.read_bytes()
        cut %= len(data) + 1
        left = data[:cut] + (garbage if cut < len(data) else b"")
        path.write_bytes(left)
        # The junk may happen to be the bytes that were cut off: what is intact is the prefix
        # the file still shares with what was written.
        intact = next((i for i, (a, b) in enumerate(zip(left, data, strict=False))
                       if a != b),
                      min(len(left), len(data)))
        whole = max(0, sum(end <= intact for end in boundaries) - 1)  # written whole
        last_boundary = max([0] + [end for end in boundaries if end <= intact])

        with mock.patch.object(LOG, "warning") as warning:
            again = agents.next()
        assert held(again) == measurements(0, whole)
        assert again.ledger.taken == whole
        assert warning.called == (len(left) > last_boundary)
        again.add(measurements(100, 1), batch=64)
        assert held(agents.next()) == measurements(0, whole) + measurements(100, 1)
        agents.die()


@settings(max_examples=40, deadline=None)
@given(steps=st.lists(st.one_of(
    st.tuples(st.just("take"), st.integers(1, 12)),
    st.tuples(st.just("receipt"), st.integers(0, 15)),
    st.tuples(st.just("tidy"), st.just(0)),
    st.tuples(st.just("die"), st.just(0))), max_size=40))
def test_after_any_history_a_restarted_agent_holds_exactly_the_unacknowledged(steps):
    """A model of the outbox (a list of ids, oldest first, at most 20 of them) against the
    outbox run through takes, receipts for the oldest few, rewrites and deaths of its agent."""
    capacity = 20
    with tempfile.TemporaryDirectory() as tmp, mock.patch.object(uploads, "REWRITE_AFTER", 8):
        agents = Agents(Path(tmp), capacity)
        outbox = agents.next()
        pending: list[str] = []
        taken = acknowledged = overflowed = 0
        for action, n in steps:
            if action == "take":
                outbox.add(measurements(taken, n), batch=64)
                pending += [f"0-test-{i}" for i in range(taken, taken + n)]
                taken += n
                overflowed += max(len(pending) - capacity, 0)
                pending = pending[-capacity:]
            elif action == "receipt" and pending:
                numbered = outbox.wait_batch(1, 0.0, timeout=0, flush=True)
                outbox.acknowledge(numbered[min(n, len(numbered) - 1)][0])
                done = min(n + 1, len(pending))
                acknowledged += done
                pending = pending[done:]
            elif action == "tidy":
                outbox.tidy()
            elif action == "die":
                outbox = agents.next()
            assert [ident for ident, *_ in held(outbox)] == pending
        restarted = agents.next()
        assert [ident for ident, *_ in held(restarted)] == pending
        ledger = restarted.ledger
        assert (ledger.taken, ledger.acknowledged, ledger.overflowed) == (
            taken, acknowledged, overflowed)
        agents.die()


def test_an_outbox_directory_that_cannot_be_made_is_a_one_line_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert agent_main(["--uav", "0", "--outbox-dir", str(blocker / "outbox")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("agent: error: --outbox-dir") and err.count("\n") == 1


@pytest.mark.parametrize("uav", ["-1", "1024"])
def test_a_uav_outside_the_fleet_cap_is_a_one_line_error(uav, capsys):
    """Any UAV of a world up to the 1,024 cap may be asked for (--uav 70 flies a 100-UAV
    world); beyond it, one line."""
    assert agent_main(["--uav", uav]) == 2
    err = capsys.readouterr().err
    assert err == "agent: error: --uav must be between 0 and 1023\n"


class UnansweredSession:
    """A bus session whose queries nobody answers; it keeps the last payload sent."""

    payload: bytes | None = None

    def get(self, key, payload=None, timeout=None):
        self.payload = payload
        return []


def flight(steps: int, reports_db: bool) -> list[AgentObservation]:
    """Observations whose reports wander, hover (repeats the spot filter drops) and change
    level, with their SINRs if ``reports_db``."""
    rng = np.random.default_rng(4)
    xy = 100.0 + np.cumsum(rng.normal(0, 0.3, (steps * 10, 2)), axis=0).reshape(steps, 10, 2)
    levels = (np.cumsum(rng.random(steps * 10) < 0.1) % 4).reshape(steps, 10)
    sinr_db = np.round(rng.normal(0, 4, (steps, 10)) * 2) / 2 if reports_db else None
    return [AgentObservation(
        episode=0, step=step, uav=3, position=tuple(xy[step, -1]), velocity=(0.0, 0.0),
        heading=0.0, destination=(0.0, 0.0), radius=1.0, max_speed=5.0, level=0, below_steps=0,
        others_position=[], others_velocity=[], others_radius=[], others_present=[],
        measured=[(x, y, int(level)) for (x, y), level in zip(xy[step], levels[step],
                                                              strict=True)],
        measured_db=[] if sinr_db is None else sinr_db[step].tolist())
        for step in range(steps)]


@pytest.mark.parametrize("reports_db", [False, True], ids=["levels", "db"])
def test_the_agent_uploads_the_measurements_its_models_would_make(scenario, tmp_path,
                                                                  reports_db):
    """The flight loop queues rows, not models: the upload the uploader sends, valid as the
    cloud checks it, holds the very Measurements the models would make (the reports kept,
    their features, SINRs, ids, times), before and after a restart."""
    with (mock.patch.multiple(process.bus, reliable_publisher=mock.DEFAULT,
                              subscribe=mock.DEFAULT, serve_status=mock.DEFAULT),
          mock.patch.object(process.time, "time", return_value=1.7e9)):
        agent = process.AgentService(None, Topics("test"), scenario, 3, LOG, outbox_dir=tmp_path)
        observations = flight(6, reports_db)
        for observation in observations:
            agent._measure(observation)
    spots, numbers, expected = SpotFilter(scenario, 1), itertools.count(), []
    for observation in observations:
        reports = np.array(observation.measured)
        keep = spots.keep([0], reports[None, :, :2], reports[None, :, 2])[0]
        kept = reports[keep]
        sinr_db = (np.array(observation.measured_db)[keep].tolist() if reports_db
                   else [None] * len(kept))
        expected += [Measurement(id=f"3-{agent.nonce}-{next(numbers)}", source="uav-3",
                                 step=observation.step, time=1.7e9, features=row, level=level,
                                 sinr_db=db)
                     for row, level, db in zip(scenario_features(scenario, kept[:, :2]).tolist(),
                                               kept[:, 2].astype(int).tolist(), sinr_db,
                                               strict=True)]
    assert 10 < len(expected) < 60  # some reports dropped, all in one upload

    for outbox in (agent.outbox, open_outbox(100, tmp_path, 3, LOG)):  # and a restarted agent's
        agent.uploader.outbox, agent.uploader.session = outbox, UnansweredSession()
        assert not agent.uploader._send(outbox.wait_batch(1, 0.0, timeout=0, flush=True), 0.1)
        payload = agent.uploader.session.payload
        upload = decode(MeasurementUpload, payload)
        assert (upload.uav, upload.source, upload.round) == (3, "uav-3", None)
        assert upload.batch().records() == expected
        outbox.close()


def test_new_maps_are_built_beside_the_deciding_thread_and_never_replaced_by_older(scenario,
                                                                                    tmp_path):
    """A map's raster takes tens of milliseconds: the agent's "maps" thread builds it, and the
    deciding thread only swaps it in. A version built late never replaces a newer one."""
    from planning.networks import sha256
    from shared.cloud_messages import SinrMap
    from shared.survey_maps import sinr_map_for

    data = sinr_map_for(scenario).read_bytes()
    maps = [SinrMap(version=v, sha256=sha256(data), data=data, mode="online") for v in (1, 2, 3)]
    built_on = []
    real_raster = process.Models._raster

    def raster(self, update):
        built_on.append(threading.current_thread().name)
        return real_raster(self, update)

    with (mock.patch.multiple(process.bus, reliable_publisher=mock.DEFAULT,
                              subscribe=mock.DEFAULT, serve_status=mock.DEFAULT),
          mock.patch.object(process.Models, "_raster", raster)):
        agent = process.AgentService(None, Topics("test"), scenario, 0, LOG, outbox_dir=tmp_path)
        stop = threading.Event()
        helper = threading.Thread(target=agent._prepare_updates, args=(stop,), name="maps")
        helper.start()
        try:
            agent.updates.put(maps[1])
            wait_until(lambda: not agent.prepared.empty(), 30, "version 2 built")
            agent._take_updates()
            assert agent.models.sinr_version == 2 and built_on == ["maps"]
            agent.updates.put(maps[0])  # older than what flies: not even built
            agent.updates.put(maps[2])
            wait_until(lambda: agent.prepared.qsize() == 2, 30, "both handled")
        finally:
            stop.set()
            helper.join()
        agent._take_updates()
        assert agent.models.sinr_version == 3 and built_on == ["maps", "maps"]
        newest = agent.models.radio_map
        assert agent.models.prepare(maps[2]) is None  # not newer than what flies
        late = process.Models(scenario, LOG).prepare(maps[1])  # built before 3 was taken
        agent.models.commit(maps[1], late)
        assert agent.models.sinr_version == 3 and agent.models.radio_map is newest
        agent.outbox.close()


def test_a_map_version_named_before_it_arrived_is_asked_of_the_cloud_and_flown(scenario,
                                                                                tmp_path):
    """On the lockstep clock the world names the map version to fly; the map itself comes by
    another route and may not have arrived. The agent asks the cloud: its newest version is
    flown if it is the one named; a version the cloud has not published either (a forgery)
    is not waited for."""
    from planning.networks import sha256
    from shared.cloud_messages import SinrMap
    from shared.survey_maps import sinr_map_for

    data = sinr_map_for(scenario).read_bytes()
    newest = SinrMap(version=4, sha256=sha256(data), data=data, mode="online")
    asked = []

    def query(session, key, kind, timeout):
        asked.append(key)
        return newest

    with mock.patch.multiple(process.bus, reliable_publisher=mock.DEFAULT,
                             subscribe=mock.DEFAULT, serve_status=mock.DEFAULT):
        agent = process.AgentService(None, Topics("test"), scenario, 0, LOG, outbox_dir=tmp_path)
    stop = threading.Event()
    helper = threading.Thread(target=agent._prepare_updates, args=(stop,), name="maps")
    helper.start()
    try:
        with mock.patch.object(process.bus, "query", query):
            agent._fly_version(4)
            assert agent.models.sinr_version == 4 and asked == [Topics("test").sinr_map]
            started = time.monotonic()
            agent._fly_version(9)  # never published
            assert time.monotonic() - started < 5.0 and agent.models.sinr_version == 4
            assert len(asked) == 2
    finally:
        stop.set()
        helper.join(10)
