"""Runs recorded as MCAP files and replayed: ``jamnav up --record`` during a real lockstep run,
``jamnav record`` and ``jamnav replay`` as the separate processes a user starts."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import msgpack
import pytest
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from jamnav.cli import main as jamnav
from jamnav.recording import Recording, RecordingError, RecordingWriter
from shared import access, bus
from shared.cloud_messages import ValueWeights
from shared.events import UavOutcomes
from shared.topics import Topics
from shared.wire import MessageError, encode
from shared.world_messages import Action, WorldState
from tests.support import Drained, free_endpoint, wait_until

ROOT = Path(__file__).resolve().parent.parent
UAVS = 2


def jamnav_process(*argv: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "jamnav.cli", *argv], cwd=ROOT,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)), text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory) -> tuple[Path, dict]:
    """A short lockstep run of the whole system, recorded: the file and the run's report.
    Secure, so that the router's rules, which deny what no role needs, let the recorder hear
    everything; ``jamnav record`` below records a system without them."""
    run_dir = tmp_path_factory.mktemp("recorded") / "run"
    process = jamnav_process("up", "--uavs", str(UAVS), "--episodes", "2", "--lockstep",
                             "--map", "perfect", "--seed", "4", "--no-figures", "--endpoint",
                             free_endpoint(), "--run-dir", str(run_dir), "--secure",
                             "--record", str(run_dir / "run.mcap"))
    out, err = Drained(process).wait(120)
    assert process.returncode == 0, err[-2000:]
    assert f"recording: {run_dir / 'run.mcap'}" in out
    return run_dir / "run.mcap", json.loads((run_dir / "report.json").read_text())


def test_a_recording_holds_the_events_and_outcomes_of_the_live_run(recorded_run):
    path, report = recorded_run
    with Recording(path) as recording:
        assert recording.prefix == "jamnav"
        items = list(recording.messages())
    events = [item.message.model_dump(mode="json") for item in items
              if item.key.startswith("jamnav/event/")]
    assert events == report["events"]
    outcomes = [event["outcomes"] for event in events if event["type"] == "uav_outcomes"]
    assert outcomes == report["outcomes"] and len(outcomes) == 2
    keys = {item.key for item in items}
    for uav in range(UAVS):
        assert {f"jamnav/uav/{uav}/observation", f"jamnav/uav/{uav}/action"} <= keys
    assert {"jamnav/world/state", "jamnav/cloud/weights/value",
            "jamnav/cloud/weights/sinr_map"} <= keys
    # Every state says which jammer is in force (the scenario's), so that a replay of any
    # stretch of the recording shows it.
    jammer = {"x": 0.0, "y": 0.0, "power_w": 1.0, "height_m": 30.0}
    assert all(item.message.jammer_known and [j.model_dump(include=set(jammer))
                                              for j in item.message.jammers_in_force] == [jammer]
               for item in items if item.key == "jamnav/world/state")
    # Every step the world flew was recorded from the first: one action per observation.
    observations = [item.message for item in items if item.key.endswith("/observation")]
    assert min(o.step for o in observations if o.episode == 0) == 0
    assert len(observations) == sum(item.key.endswith("/action") for item in items)


def test_a_replay_puts_the_same_payloads_in_the_same_order_under_another_prefix(
        recorded_run, tmp_path):
    original_path, _ = recorded_run
    endpoint, copy_path, speed = free_endpoint(), tmp_path / "copy.mcap", 4.0
    with bus.open_session("router", endpoint), bus.open_session("client", endpoint) as watch:
        recorder = jamnav_process("record", "--endpoint", endpoint, "--prefix", "replayed",
                                  "--out", str(copy_path))
        try:
            wait_until(lambda: list(watch.liveliness().get("replayed/alive/recorder/*",
                                                           timeout=0.5)), 30, "the recorder")
            replay = jamnav_process("replay", str(original_path), "--endpoint", endpoint,
                                    "--prefix", "replayed", "--speed", str(speed))
            _, err = Drained(replay).wait(60)
            assert replay.returncode == 0, err
        finally:
            recorder.send_signal(signal.SIGINT)  # Ctrl-C: the file is closed all the same
            _, recorder_err = Drained(recorder).wait(30)
    assert recorder.returncode == 0, recorder_err
    with Recording(original_path) as original, Recording(copy_path) as copy:
        sent, received = list(original.messages()), list(copy.messages())
    assert copy.prefix == "replayed"
    assert [("replayed" + m.key.removeprefix("jamnav"), m.payload) for m in sent] == [
        (m.key, m.payload) for m in received]
    assert f"replayed {len(sent)} messages" in err

    def span(items) -> float:
        return (items[-1].log_time_ns - items[0].log_time_ns) / 1e9

    assert span(received) >= 0.8 * span(sent) / speed  # the recorded pace, not at once


def test_payloads_are_kept_exactly_even_from_another_encoder(tmp_path):
    data = b"\x00\xff safetensors bytes"
    weights = encode(ValueWeights(version=3, sha256=hashlib.sha256(data).hexdigest(),
                                  data=data))
    canonical = encode(Action(episode=1, step=2, uav=0, speed=1.5, heading=0.25))
    # The same action from an encoder that writes integral floats as ints, keys reordered.
    foreign = msgpack.packb({"uav": 0, "episode": 1, "step": 3, "speed": 2, "heading": 0})
    path = tmp_path / "r.mcap"
    writer = RecordingWriter(path, "jamnav")
    try:
        writer.write("jamnav/cloud/weights/value", ValueWeights, weights, 10)
        writer.write("jamnav/uav/0/action", Action, canonical, 20)
        writer.write("jamnav/uav/0/action", Action, foreign, 30)
        with pytest.raises(MessageError):
            writer.write("jamnav/uav/0/action", Action, b"\xc1", 40)
    finally:
        writer.close()
    with Recording(path) as recording:
        items = list(recording.messages())
    assert [(m.key, m.payload, m.log_time_ns) for m in items] == [
        ("jamnav/cloud/weights/value", weights, 10), ("jamnav/uav/0/action", canonical, 20),
        ("jamnav/uav/0/action", foreign, 30)]
    assert items[0].message.data == data and items[2].message.speed == 2.0


def test_a_missing_or_damaged_recording_is_one_line_and_exit_2(recorded_run, tmp_path,
                                                               capsys):
    good = recorded_run[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good[: len(good) // 2])
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as stream:
        writer = Writer(stream)
        writer.start()
        writer.finish()
    for path, reason in ((tmp_path / "absent.mcap", "No such file"),
                         (cut, "truncated or damaged MCAP file"), (junk, "not an MCAP file"),
                         (foreign, "not a jamnav recording")):
        code = jamnav(["replay", str(path), "--endpoint", free_endpoint()])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and reason in err, err
        assert err.startswith(f"jamnav: error: recording {path}")


def test_a_credentials_file_without_a_recorder_login_is_one_line(tmp_path, capsys):
    path = tmp_path / "credentials.json"
    access.save(access.generate(2).only(["operator", "world", "cloud", "agent-*"]), path)
    code = jamnav(["up", "--uavs", "2", "--credentials", str(path), "--record",
                   str(tmp_path / "r.mcap"), "--endpoint", free_endpoint(),
                   "--run-dir", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "no login for role 'recorder'" in err
    assert not (tmp_path / "run").exists()


def test_on_a_secure_system_the_recorder_hears_everything_and_may_send_nothing(tmp_path):
    credentials, endpoint, topics = access.generate(1), free_endpoint(), Topics()
    access.save(credentials, tmp_path / "credentials.json")
    outcome = encode(UavOutcomes(t=1.0, source="world", episode=0, seed=0, steps=3,
                                 outcomes=["success"]))
    state = encode(WorldState(episode=0, step=1, clock="lockstep", t=1.0, position=[(0, 0)],
                              velocity=[(0, 0)], sinr_db=[1.0], level=[1], status=["active"]))
    action = encode(Action(episode=0, step=1, uav=0, speed=1.0, heading=0.0))
    with bus.open_session("router", endpoint, guard=access.Guard(credentials, "jamnav")), \
            bus.open_session("client", endpoint, login=credentials.login("world")) as world, \
            bus.open_session("client", endpoint, login=credentials.login("agent-0")) as agent:
        recorder = jamnav_process("record", "--endpoint", endpoint, "--credentials",
                                  str(tmp_path / "credentials.json"), "--duration", "6",
                                  "--out", str(tmp_path / "secure.mcap"))
        with bus.open_session("client", endpoint, login=credentials.login("operator")) as op:
            wait_until(lambda: list(op.liveliness().get(topics.alive(access.RECORDER),
                                                        timeout=0.5)), 30, "the recorder")
        with bus.open_session("client", endpoint,
                              login=credentials.login(access.RECORDER)) as impostor:
            impostor.put(topics.state, state)  # denied: a recorder only listens
        world.put(topics.event("uav_outcomes"), outcome)
        world.put(topics.state, state)
        agent.put(topics.action(0), action)
        out, err = Drained(recorder).wait(30)
    assert recorder.returncode == 0, err
    with Recording(tmp_path / "secure.mcap") as recording:
        recorded = [(item.key, item.payload) for item in recording.messages()]
    assert sorted(recorded) == sorted([(topics.event("uav_outcomes"), outcome),
                                       (topics.state, state), (topics.action(0), action)])


def small_recording(path: Path) -> bytes:
    """A recording of a few messages, one of them kept verbatim (an attachment): its bytes."""
    writer = RecordingWriter(path, "jamnav")
    try:
        for step in range(5):
            writer.write("jamnav/uav/0/action", Action,
                         encode(Action(episode=0, step=step, uav=0, speed=1.0, heading=0.5)),
                         step * 10**8)
        writer.write("jamnav/uav/0/action", Action,
                     msgpack.packb({"uav": 0, "episode": 0, "step": 5, "speed": 2,
                                    "heading": 0}), 6 * 10**8)
    finally:
        writer.close()
    return path.read_bytes()


# A run that the check it should stop at lets through ends soon, and fails the test.
BRIEF_UP = ("--duration", "1", "--no-web", "--no-figures")


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("jamnav: error: ") and err.count("\n") == 1, err
    return err


def test_an_existing_recording_is_never_written_over(tmp_path, capsys):
    kept = small_recording(tmp_path / "u1.mcap")
    # No router listens there: a refusal that came after connecting would be exit 1, later.
    code = jamnav(["record", "--out", str(tmp_path / "u1.mcap"), "--duration", "2",
                   "--endpoint", free_endpoint()])
    assert code == 2 and "exists; choose another name or remove it" in one_error_line(capsys)
    code = jamnav(["up", "--uavs", "2", "--record", str(tmp_path / "u1.mcap"), *BRIEF_UP,
                   "--endpoint", free_endpoint(), "--run-dir", str(tmp_path / "run")])
    assert code == 2 and "--record" in one_error_line(capsys)
    assert (tmp_path / "u1.mcap").read_bytes() == kept and not (tmp_path / "run").exists()
    # Nor one made between the check and the recording.
    with pytest.raises(RecordingError, match="cannot create it"):
        RecordingWriter(tmp_path / "u1.mcap", "jamnav")
    assert (tmp_path / "u1.mcap").read_bytes() == kept


def test_up_refuses_a_recording_that_its_restarted_recorder_would_write_over(tmp_path,
                                                                           capsys):
    kept = small_recording(tmp_path / "flight.3.mcap")
    code = jamnav(["up", "--uavs", "2", "--record", str(tmp_path / "flight.mcap"), *BRIEF_UP,
                   "--endpoint", free_endpoint(), "--run-dir", str(tmp_path / "run")])
    err = one_error_line(capsys)
    assert code == 2 and "flight.3.mcap exists" in err
    assert (tmp_path / "flight.3.mcap").read_bytes() == kept
    assert not (tmp_path / "flight.mcap").exists() and not (tmp_path / "run").exists()


def test_a_link_as_the_recording_is_refused_up_front(tmp_path, capsys):
    kept = small_recording(tmp_path / "earlier.mcap")
    dangling, to_earlier = tmp_path / "dangling.mcap", tmp_path / "to_earlier.mcap"
    dangling.symlink_to(tmp_path / "nowhere" / "x.mcap")
    to_earlier.symlink_to(tmp_path / "earlier.mcap")
    for link in (dangling, to_earlier):
        code = jamnav(["record", "--out", str(link), "--endpoint", free_endpoint()])
        err = one_error_line(capsys)
        assert code == 2 and err.startswith(f"jamnav: error: --out {link}: "), err
        assert link.is_symlink()
    assert not (tmp_path / "nowhere").exists()
    assert (tmp_path / "earlier.mcap").read_bytes() == kept


@pytest.mark.parametrize("speed", ["1e-300", "0.001", "0", "-1", "nan", "inf", "1001"])
def test_a_replay_speed_out_of_range_is_one_line(speed, tmp_path, capsys):
    small_recording(tmp_path / "r.mcap")
    code = jamnav(["replay", str(tmp_path / "r.mcap"), "--speed", speed,
                   "--endpoint", free_endpoint()])
    assert code == 2 and "--speed must be between 0.01 and 1000" in one_error_line(capsys)


@pytest.mark.parametrize("speed", ["0.01", "1000"])
def test_the_replay_speeds_at_the_ends_of_the_range_are_taken(speed, tmp_path, capsys):
    # Taken: what stops the replay is the next check, of the file.
    code = jamnav(["replay", str(tmp_path / "absent.mcap"), "--speed", speed])
    assert code == 2 and "No such file" in one_error_line(capsys)


def test_the_replay_help_says_the_speeds_it_takes(capsys):
    with pytest.raises(SystemExit):
        jamnav(["replay", "--help"])
    assert "0.01 to 1000" in " ".join(capsys.readouterr().out.split())


def record_ends(data: bytes, tmp_path: Path) -> list[int]:
    """Where each record of a complete MCAP file ends, as mcap's own reader walks it; the
    magic that closes the file ends it."""
    path = tmp_path / "walked.mcap"
    path.write_bytes(data)
    ends = []
    with path.open("rb") as stream:
        for _ in StreamReader(stream, emit_chunks=True).records:
            ends.append(stream.tell())
    return [*ends, len(data)]


def test_a_truncated_recording_says_so_and_where_its_whole_records_end(tmp_path, capsys):
    good = small_recording(tmp_path / "good.mcap")
    ends = record_ends(good, tmp_path)
    cut_path = tmp_path / "cut.mcap"
    # At and just after every record's end (a writer killed there), and inside the closing
    # magic, the file's last record.
    for cut in sorted({*ends[:-1], *(end + 1 for end in ends[:-1]), len(good) - 3}):
        cut_path.write_bytes(good[:cut])
        code = jamnav(["replay", str(cut_path), "--endpoint", free_endpoint()])
        whole = max(end for end in ends if end <= cut)
        assert code == 2 and one_error_line(capsys) == (
            f"jamnav: error: recording {cut_path}: truncated or damaged MCAP file: its "
            f"records are whole up to byte {whole:,} of {cut:,}\n"), cut


def test_a_recording_damaged_inside_is_one_line(tmp_path):
    good = bytearray(small_recording(tmp_path / "good.mcap"))
    with (tmp_path / "good.mcap").open("rb") as stream:
        reader = StreamReader(stream, emit_chunks=True)
        chunk_end = next(stream.tell() for record in reader.records
                         if isinstance(record, Chunk))
    good[chunk_end - 5] ^= 0xFF  # in the chunk's compressed messages
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(good)
    # Its summary is whole: the damage shows when the replay reaches the chunk.
    with Recording(damaged) as recording, pytest.raises(RecordingError) as refused:
        list(recording.messages())
    assert str(refused.value).startswith(f"recording {damaged}: damaged MCAP file (")
    assert "\n" not in str(refused.value)


def test_an_empty_recording_is_one_line(tmp_path, capsys):
    (tmp_path / "empty.mcap").touch()
    code = jamnav(["replay", str(tmp_path / "empty.mcap"), "--endpoint", free_endpoint()])
    assert code == 2 and one_error_line(capsys).endswith("empty.mcap: an empty file\n")
