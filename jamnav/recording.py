"""Runs kept as MCAP files: ``jamnav record`` (and ``jamnav up --record``) writes every message
put under a system's prefix, ``jamnav replay`` puts them on the bus again at the recorded pace.

The file opens in Foxglove as it is: one channel per key (``jamnav/uav/0/observation``, ...),
its schema the JSON schema of the key's pydantic model (schema encoding ``jsonschema``, one
schema per message type), each message the model's JSON form (message encoding ``json``),
binary fields (the weights' safetensors) as base64 strings marked ``contentEncoding: base64``.

A replay puts the very payloads that were recorded. Every process encodes with
``shared.wire.encode``; the JSON keeps what that encoding needs (ints stay ints, floats are
written as round-trip decimals), so the recorded payload is the model's encoding again. A
payload that is not (a sender with another msgpack encoder) is kept as it was, in an
attachment named ``<key>#<sequence>``, and replayed from there.
"""

from __future__ import annotations

import base64
import functools
import glob
import json
import logging
import os
import queue
import re
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, get_args

import zenoh
import zstandard
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.writer import MCAP0_MAGIC, Writer

from shared import access, bus
from shared.cloud_messages import SinrMap, ValueWeights
from shared.events import Event
from shared.jammer_messages import JammerEstimate
from shared.topics import Topics, uav_in_key
from shared.wire import Message, MessageError, decode, encode
from shared.world_messages import Action, AgentObservation, WorldState

METADATA = "jamnav"  # the metadata record that names the recorded prefix
VERBATIM_MEDIA_TYPE = "application/msgpack"
DRAIN_EVERY_S = 0.05
# The recorder's writing thread yields the CPU to the system it records: on arrival a message
# is only queued, and written when the others wait (a lockstep world waits every step).
RECORDER_NICENESS = 10
SUBSCRIBERS_WAIT_S = 1.0  # how long a replay gives a listener's subscription to reach it

EVENT_KINDS: dict[str, type[Message]] = {
    kind.model_fields["type"].default: kind for kind in get_args(get_args(Event)[0])}
KINDS: dict[str, type[Message]] = {kind.__name__: kind for kind in (
    WorldState, AgentObservation, Action, ValueWeights, SinrMap, JammerEstimate,
    *EVENT_KINDS.values())}


class RecordingError(ValueError):
    """A file that cannot be read as a recording; the text is one line."""


@functools.lru_cache(maxsize=4096)  # asked for every message; a run has a few dozen keys
def message_kind(topics: Topics, key: str) -> type[Message] | None:
    """The message put on ``key`` by the topic layout (docs/topics.md); None for a key that
    carries no put of the system."""
    uav = uav_in_key(key)
    per_uav = {} if uav is None else {topics.observation(uav): AgentObservation,
                                      topics.action(uav): Action}
    events = {topics.event(name): kind for name, kind in EVENT_KINDS.items()}
    return {topics.state: WorldState, topics.value_weights: ValueWeights,
            topics.sinr_map: SinrMap, topics.jammer_estimate: JammerEstimate,
            **per_uav, **events}.get(key)


@functools.cache
def _binary_fields(kind: type[Message]) -> tuple[str, ...]:
    return tuple(name for name, field in kind.model_fields.items() if field.annotation is bytes)


def json_schema(kind: type[Message]) -> bytes:
    schema = kind.model_json_schema()
    for name in _binary_fields(kind):
        field = schema["properties"][name]
        for rule in ("format", "minLength", "maxLength"):  # of bytes, not base64 characters
            field.pop(rule, None)
        field["contentEncoding"] = "base64"
    return json.dumps(schema).encode()


def to_json(message: Message) -> bytes:
    """``model_dump(mode="json")`` as JSON text, binary fields in base64."""
    binary = _binary_fields(type(message))
    if not binary:
        return message.model_dump_json().encode()
    fields = message.model_dump(mode="json", exclude=set(binary))
    fields.update({name: base64.b64encode(getattr(message, name)).decode() for name in binary})
    return json.dumps(fields).encode()


def from_json(kind: type[Message], text: bytes) -> Message:
    """The message ``to_json`` wrote, validated; MessageError otherwise."""
    try:
        fields = json.loads(text)
        for name in _binary_fields(kind):
            fields[name] = base64.b64decode(fields[name], validate=True)
        return kind.model_validate(fields)
    except (ValueError, TypeError, KeyError) as exc:  # pydantic's ValidationError included
        raise MessageError(f"{kind.__name__}: {' '.join(str(exc).split())[:200]}") from None


# -- writing --------------------------------------------------------------------------------------
class RecordingWriter:
    """An MCAP file being written; ``close`` it (in a ``finally``): only a closed file has the
    summary a reader seeks by."""

    def __init__(self, path: Path, prefix: str):
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            # Never over an earlier recording: the command line refuses one, and "x" also
            # refuses one made since (and a link, which O_EXCL does not follow).
            self._file = path.open("xb")
        except OSError as exc:
            raise RecordingError(f"recording {path}: cannot create it: {exc.strerror}") from None
        self._writer = Writer(self._file)
        self._writer.start(profile="", library="jamnav")
        self._writer.add_metadata(METADATA, {"prefix": prefix})
        self._schemas: dict[type[Message], int] = {}
        self._channels: dict[str, int] = {}
        self._sequences: dict[str, int] = {}
        self.messages = 0

    def write(self, key: str, kind: type[Message], payload: bytes, log_time_ns: int) -> None:
        """Add the ``kind`` message ``payload`` that arrived on ``key``; MessageError if it is
        not one (nothing is written then)."""
        message = decode(kind, payload)
        channel = self._channel(key, kind)
        sequence = self._sequences[key] = self._sequences[key] + 1
        self._writer.add_message(channel, log_time_ns, to_json(message), log_time_ns, sequence)
        if encode(message) != payload:
            self._writer.add_attachment(log_time_ns, log_time_ns, f"{key}#{sequence}",
                                        VERBATIM_MEDIA_TYPE, payload)
        self.messages += 1

    def _channel(self, key: str, kind: type[Message]) -> int:
        if key not in self._channels:
            if kind not in self._schemas:
                self._schemas[kind] = self._writer.register_schema(
                    kind.__name__, "jsonschema", json_schema(kind))
            self._channels[key] = self._writer.register_channel(key, "json",
                                                                self._schemas[kind])
            self._sequences[key] = 0
        return self._channels[key]

    @property
    def keys(self) -> int:
        return len(self._channels)

    def close(self) -> None:
        try:
            self._writer.finish()
        finally:
            self._file.close()


@dataclass(frozen=True)
class RecordSummary:
    path: Path
    messages: int
    keys: int
    refused: dict[str, int]
    cpu_s: float  # the recording process's, zenoh's threads included, while it recorded


def record(session: zenoh.Session, topics: Topics, path: Path, stop: threading.Event,
           duration: float | None, log: logging.Logger) -> RecordSummary:
    """Write what is put under the prefix to ``path`` until ``stop`` is set or ``duration`` seconds
    have passed. Zenoh's delivery thread only queues a sample; this thread writes it. The
    liveliness token ``<prefix>/alive/recorder/<pid>`` says that the subscription is in."""
    inbox: queue.SimpleQueue = queue.SimpleQueue()

    def arrived(sample: zenoh.Sample) -> None:
        inbox.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    refused = bus.Dropped(log)
    cpu_start = time.process_time()
    writer = RecordingWriter(path, topics.prefix)
    declared: list[Any] = []
    try:
        declared.append(session.declare_subscriber(topics.everything, arrived))
        declared.append(bus.declare_alive(session, topics, access.RECORDER, os.getpid()))
        log.info("recording %s to %s", topics.everything, path)
        deadline = None if duration is None else time.monotonic() + duration
        while not stop.wait(DRAIN_EVERY_S):
            _drain(inbox, writer, topics, refused)
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        for entity in declared:
            entity.undeclare()
        try:
            _drain(inbox, writer, topics, refused)
        finally:
            writer.close()
    return RecordSummary(path, writer.messages, writer.keys, refused.as_dict(),
                         time.process_time() - cpu_start)


def _drain(inbox: queue.SimpleQueue, writer: RecordingWriter, topics: Topics,
           refused: bus.Dropped) -> None:
    while not inbox.empty():
        key, payload, log_time_ns = inbox.get_nowait()
        kind = message_kind(topics, key)
        if kind is None:
            refused.add(key, "no message of the system is put on this key")
            continue
        try:
            writer.write(key, kind, payload, log_time_ns)
        except MessageError as exc:
            refused.add(key, str(exc))


# -- the files of a restarted recorder (`jamnav up --record`) -----------------------------------
def recording_path(path: Path, restarts: int) -> Path:
    """Where the recorder writes: ``path``, and after its n-th restart ``<stem>.<n><suffix>``
    (the earlier file stays as it was closed)."""
    return path if restarts == 0 else path.with_name(f"{path.stem}.{restarts}{path.suffix}")


def restarted_recordings(path: Path) -> list[Path]:
    """The files ``recording_path`` names after restarts that exist now (an earlier run's)."""
    restarted = re.compile(rf"{re.escape(path.stem)}\.[1-9][0-9]*{re.escape(path.suffix)}")
    return sorted(earlier for earlier in path.parent.glob(f"{glob.escape(path.stem)}.*")
                  if restarted.fullmatch(earlier.name))


# -- reading and replaying ----------------------------------------------------------------------
@dataclass(frozen=True)
class Recorded:
    key: str
    log_time_ns: int
    message: Message
    payload: bytes  # the msgpack bytes as they were put


# What the mcap reader raises on a file that is not MCAP, is cut short or damaged (OSError:
# it seeks to the footer's place before the end, which is before the start of a tiny file).
_UNREADABLE = (McapError, struct.error, EOFError, ValueError, KeyError, IndexError,
               zstandard.ZstdError, OSError)

_RECORD_HEAD = struct.Struct("<BQ")  # an MCAP record's opcode and the length of its content


def _whole_records_end(stream: BinaryIO, size: int) -> tuple[int, bool] | None:
    """Where the last whole record of an MCAP file of ``size`` bytes ends, and whether the
    file ends as a complete one does (footer, then magic); None for a file that does not
    start as MCAP. Only the records' heads are read, seeking past their content, so a file of
    any size is scanned at once."""
    stream.seek(0)
    if stream.read(len(MCAP0_MAGIC)) != MCAP0_MAGIC:
        return None
    end = len(MCAP0_MAGIC)
    while end + _RECORD_HEAD.size <= size:
        stream.seek(end)
        opcode, length = _RECORD_HEAD.unpack(stream.read(_RECORD_HEAD.size))
        if length > size - end - _RECORD_HEAD.size:
            break
        end += _RECORD_HEAD.size + length
        if opcode == Opcode.FOOTER:
            stream.seek(end)
            return end, stream.read(len(MCAP0_MAGIC)) == MCAP0_MAGIC
    return end, False


class Recording:
    """A recording opened for reading (a context manager); RecordingError, one line, for a
    file that is missing or not a complete recording."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            self._file = self.path.open("rb")
        except OSError as exc:
            raise RecordingError(f"recording {path}: {exc.strerror}") from None
        try:
            self.prefix, self._verbatim = self._contents()
        except BaseException:
            self._file.close()
            raise

    def _contents(self) -> tuple[str, dict[str, bytes]]:
        """The recorded prefix and the payloads kept verbatim, read from the summary."""
        try:
            self._reader = make_reader(self._file, validate_crcs=True)
            if self._reader.get_summary() is None:
                raise McapError("no summary")
            found = {m.name: m.metadata for m in self._reader.iter_metadata()}
            verbatim = {a.name: a.data for a in self._reader.iter_attachments()}
        except _UNREADABLE as exc:
            raise self._error(exc) from None
        if "prefix" not in found.get(METADATA, {}):
            raise RecordingError(f"recording {self.path}: an MCAP file, but not a jamnav "
                                 "recording")
        return found[METADATA]["prefix"], verbatim

    def _error(self, exc: Exception) -> RecordingError:
        """What the reader's ``exc`` means for the user: the reader only sees that the
        summary at the end, or a record it points to, does not parse."""
        size = os.fstat(self._file.fileno()).st_size
        scanned = _whole_records_end(self._file, size)
        if scanned is None:
            return RecordingError(f"recording {self.path}: "
                                  + ("not an MCAP file" if size else "an empty file"))
        end, complete = scanned
        if complete:
            reason = " ".join(str(exc).split())[:160] or type(exc).__name__
            return RecordingError(f"recording {self.path}: damaged MCAP file ({reason})")
        return RecordingError(f"recording {self.path}: truncated or damaged MCAP file: its "
                              f"records are whole up to byte {end:,} of {size:,}")

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *_) -> None:
        self._file.close()

    def messages(self) -> Iterator[Recorded]:
        """Every message in the order it arrived, validated against its schema's model."""
        try:
            for schema, channel, record in self._reader.iter_messages(log_time_order=False):
                kind = KINDS.get(schema.name if schema is not None else "")
                if kind is None:
                    raise MessageError(f"channel {channel.topic} has no jamnav message type")
                message = from_json(kind, record.data)
                payload = self._verbatim.get(f"{channel.topic}#{record.sequence}")
                yield Recorded(channel.topic, record.log_time, message,
                               encode(message) if payload is None else payload)
        except MessageError as exc:
            raise RecordingError(f"recording {self.path}: {exc}") from None
        except _UNREADABLE as exc:
            raise self._error(exc) from None


def replay(session: zenoh.Session, recording: Recording, prefix: str | None, speed: float,
           stop: threading.Event) -> int:
    """Put the recording's messages again, ``speed`` times the recorded pace, on their keys
    re-rooted under ``prefix`` (default: the recorded one); how many were put."""
    root = recording.prefix if prefix is None else prefix
    publishers: dict[str, zenoh.Publisher] = {}
    _wait_for_listeners(session, root, publishers)
    start: tuple[float, int] | None = None
    count = 0
    for item in recording.messages():
        if start is None:
            start = (time.monotonic(), item.log_time_ns)
        due = start[0] + (item.log_time_ns - start[1]) / 1e9 / speed
        if stop.wait(max(0.0, due - time.monotonic())):
            break
        key = root + item.key[len(recording.prefix):]
        if key not in publishers:
            publishers[key] = bus.reliable_publisher(session, key)
        publishers[key].put(item.payload)
        count += 1
    return count


def _wait_for_listeners(session: zenoh.Session, root: str,
                        publishers: dict[str, zenoh.Publisher]) -> None:
    """A put sent before a subscription has reached this session is lost: give a listener
    that is already there (a console, a recorder) a moment to be known."""
    probe = publishers.setdefault(Topics(root).state,
                                  bus.reliable_publisher(session, Topics(root).state))
    deadline = time.monotonic() + SUBSCRIBERS_WAIT_S
    while not probe.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(bus.MATCH_SETTLE_S)
