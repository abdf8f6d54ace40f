"""The agent's measurement uploads: an outbox that keeps every measurement until the cloud has
acknowledged it, and a sender thread that empties it.

Each upload is a query; the cloud answers with an ``UploadReceipt`` once the records are in its
replay memory. No answer (cloud down, restarting, overloaded) leaves the records in the outbox
and the sender tries again later, so a cloud outage shorter than the outbox loses nothing. A
receipt lost on the way makes the sender repeat an upload the cloud already stored: the memory
recognises the ids, so every measurement is stored exactly once. Only an outbox overflowing
during a long outage drops records, the oldest first, and counts them.

The flight loop never waits for the cloud: it only appends to the outbox.

Given a directory (``open_outbox``), the outbox is also a file there, one per UAV
(``OutboxFile``): each measurement is appended as it is taken and each receipt as a mark, so
an agent killed mid-flight loses nothing. The next agent of that UAV starts with what has no
receipt, and its counts, and sends those measurements first under their original ids (the
cloud stores a repeat once).
"""

from __future__ import annotations

import itertools
import logging
import os
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import msgpack

from shared import bus
from shared.cloud_messages import MAX_UPLOAD, UploadReceipt, encode_upload
from shared.measurements import MEASUREMENT_FIELDS, Measurement

DEFAULT_CAPACITY = 20_000  # measurements: over 3 minutes of a UAV at 100 steps/s
# Measurements per upload: each upload costs the cloud a transaction and the agent a round trip
# on a thread that shares the interpreter with its decisions; the age limit keeps slow clocks
# fresh.
DEFAULT_BATCH = 64
# Wall seconds a measurement waits for company before it goes alone. What the cloud has not
# received it cannot use to detect a change: in real time at 10 steps/s an agent keeps about 2
# measurements a step (de-duplicated), so 64 take 3 s and the age decides: the time to detect
# a jammer set follows it. A quarter of a second costs an agent at most 4 uploads a second.
DEFAULT_MAX_AGE_S = 0.25
RECEIPT_TIMEOUT_S = 5.0  # a cloud busy retraining still answers well within this
RETRY_FIRST_S, RETRY_MAX_S = 0.2, 2.0
FLUSH_S = 3.0  # how long a stopping agent keeps trying to hand over what it holds
ROUND_SENDERS = 4  # round uploads awaiting their receipts at once
# An outbox file is rewritten once this many measurements (and at least as many as it holds)
# were released since the last rewrite: it stays within about twice that size, and a rewrite
# costs in proportion to what it holds, so each measurement pays for it at most once.
REWRITE_AFTER = 4096
_FRAME = struct.Struct("<II")  # a record's header: payload length, CRC-32 of the payload
_MEASUREMENT, _MARK = 0, 1  # record kinds
# An outbox holds a measurement as its file stores it and the upload carries it: Measurement's
# fields in order (MEASUREMENT_FIELDS), the features as FEATURES_DTYPE bytes.
_TIME = MEASUREMENT_FIELDS.index("time")


@dataclass
class Ledger:
    """What became of the measurements an outbox was given: each one is acknowledged (stored,
    a duplicate or refused by the cloud), dropped from a full outbox, or still held."""

    taken: int = 0
    acknowledged: int = 0
    overflowed: int = 0  # dropped, oldest first, because the outbox was full
    refused: int = 0  # of the acknowledged
    duplicates: int = 0  # of the acknowledged

    @property
    def released(self) -> int:
        """Measurements no longer held. They are numbered 0, 1, ... as taken and released
        oldest first, so these are the numbers below ``released``: a watermark."""
        return self.acknowledged + self.overflowed


def _frame(record: list) -> bytes:
    payload = msgpack.packb(record, use_bin_type=True)
    return _FRAME.pack(len(payload), zlib.crc32(payload)) + payload


def _measurement_frame(number: int, record: tuple) -> bytes:
    return _frame([_MEASUREMENT, number, *record])


def _features(data: bytes) -> list[float]:
    return list(struct.unpack(f"<{len(data) // 4}f", data))


def _mark_frame(ledger: Ledger) -> bytes:
    return _frame([_MARK, ledger.acknowledged, ledger.overflowed, ledger.refused,
                   ledger.duplicates])


def _decode(payload: bytes) -> Ledger | tuple[int, tuple]:
    """A record's payload, a measurement as its number and record; ValueError or TypeError
    when it is not one this module wrote."""
    kind, *fields = msgpack.unpackb(payload)
    if kind == _MARK:
        acknowledged, overflowed, refused, duplicates = map(int, fields)
        return Ledger(acknowledged=acknowledged, overflowed=overflowed, refused=refused,
                      duplicates=duplicates)
    if kind != _MEASUREMENT:
        raise ValueError(f"unknown record kind {kind!r}")
    # An outbox written before reports carried the SINR holds level reports: None.
    number, ident, source, step, taken_at, features, level, sinr_db = (
        fields if len(fields) == 8 else (*fields, None))
    m = Measurement(id=ident, source=source, step=step, time=taken_at,
                    features=_features(features), level=level, sinr_db=sinr_db)
    return int(number), (m.id, m.source, m.step, m.time, features, m.level, m.sinr_db)


def outbox_path(directory: Path, uav: int) -> Path:
    return Path(directory) / f"uav-{uav}.outbox"


class OutboxFile:
    """An outbox on disk: framed msgpack records (length, CRC-32, payload), a measurement
    appended as it is taken and the ledger (a mark) after each receipt; rewritten now and
    then with only the last mark and the measurements still held.

    Appends are unbuffered ``os.write`` calls: a record is in the kernel once the call
    returns, so it survives the death of the agent, ``kill -9`` included. It does not survive
    a power loss of the host (nothing is fsync'd): an fsync per step would cost the flight
    loop milliseconds."""

    def __init__(self, path: Path, log: logging.Logger):
        self.path, self.log = Path(path), log
        self._fd: int | None = None

    def load(self) -> tuple[Ledger, list[tuple[int, tuple]]]:
        """The ledger an earlier agent left here, and its measurements not released."""
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return Ledger(), []
        ledger, held = Ledger(), []
        for record in self._records(data):
            if isinstance(record, Ledger):
                ledger = record
            else:
                held.append(record)
        held = [(number, m) for number, m in held if number >= ledger.released]
        ledger.taken = max(ledger.released, held[-1][0] + 1 if held else 0)
        return ledger, held

    def _records(self, data: bytes) -> Iterator[Ledger | tuple[int, tuple]]:
        """The records of ``data`` up to the first one cut short or damaged (an agent killed
        while writing it), which is dropped with what follows, and a warning."""
        offset = 0
        while offset < len(data):
            start = offset + _FRAME.size
            try:
                length, crc = _FRAME.unpack_from(data, offset)
                payload = data[start:start + length]
                if len(payload) < length or zlib.crc32(payload) != crc:
                    raise ValueError("record cut short or damaged")
                record = _decode(payload)
            except (struct.error, ValueError, TypeError) as exc:
                self.log.warning("%s: dropped its last %d bytes, a record its agent did not "
                                 "finish writing (%s)", self.path, len(data) - offset, exc)
                return
            yield record
            offset = start + length

    def append(self, numbered: Iterable[tuple[int, tuple]]) -> None:
        self._write(b"".join(_measurement_frame(number, record) for number, record in numbered))

    def mark(self, ledger: Ledger) -> None:
        self._write(_mark_frame(ledger))

    def rewrite(self, ledger: Ledger, held: Iterable[tuple[int, tuple]]) -> None:
        """Replace the file with ``ledger`` and ``held`` alone, atomically: an agent killed at
        any moment leaves the old file or the new one, whole."""
        staging = self.path.with_name(self.path.name + ".new")
        staging.write_bytes(_mark_frame(ledger) + b"".join(
            _measurement_frame(number, record) for number, record in held))
        os.replace(staging, self.path)
        self.close()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]


class Outbox:
    """Measurements not yet acknowledged, oldest first, at most ``capacity`` of them; also in
    ``file`` if given, starting with what an earlier agent left there. Each is held as its
    number and its record (see ``FEATURES_DTYPE``)."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY, file: OutboxFile | None = None):
        if capacity < 1:
            raise ValueError("the outbox needs room for at least one measurement")
        self.capacity = capacity
        self._items: deque[tuple[int, tuple]] = deque()
        self._cond = threading.Condition()
        self.ledger = Ledger()
        self._file = file
        self._released_at_rewrite = 0
        if file is not None:
            self.ledger, held = file.load()
            self._items.extend(held)
            self._drop_overflow()
            self._rewrite()  # compact from the start, and nothing appended after a torn tail

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def add(self, measurements: Sequence[tuple], batch: int) -> None:
        """Take ``measurements`` (records); with a file, they are in the kernel on return."""
        with self._cond:
            before = len(self._items)
            numbered = list(enumerate(measurements, start=self.ledger.taken))
            if self._file is not None:
                self._file.append(numbered)
            self._items.extend(numbered)
            self.ledger.taken += len(numbered)
            self._drop_overflow()
            if before == 0 or before < batch <= len(self._items):
                self._cond.notify()  # the age clock starts, or a batch is full

    def _drop_overflow(self) -> None:
        while len(self._items) > self.capacity:
            self._items.popleft()
            self.ledger.overflowed += 1

    def wait_batch(self, batch: int, max_age: float, timeout: float, flush: bool = False
                   ) -> list[tuple[int, tuple]]:
        """The oldest records (at most one upload's worth) once there are ``batch`` of them or
        the oldest is ``max_age`` seconds old (any at all with ``flush``); [] after
        ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                now = time.monotonic()
                if self._items:
                    age = time.time() - self._items[0][1][_TIME]
                    if flush or len(self._items) >= batch or age >= max_age:
                        return list(itertools.islice(self._items, MAX_UPLOAD))
                    wake = min(deadline, now + max_age - age)
                else:
                    wake = deadline
                if now >= deadline:
                    return []
                self._cond.wait(max(wake - now, 0.001))

    def acknowledge(self, last: int, refused: int = 0, duplicates: int = 0) -> None:
        """Records up to number ``last`` reached the cloud (or were refused by it for good);
        the receipt counted ``refused`` and ``duplicates`` among them."""
        with self._cond:
            while self._items and self._items[0][0] <= last:
                self._items.popleft()
                self.ledger.acknowledged += 1
            self.ledger.refused += refused
            self.ledger.duplicates += duplicates
            if self._file is not None:
                self._file.mark(self.ledger)

    def passed(self, taken: int, receipt: UploadReceipt | None) -> None:
        """Account for ``taken`` records that went to the cloud past the outbox (a round's, on
        the lockstep clock): acknowledged with ``receipt``, or dropped without one."""
        with self._cond:
            self.ledger.taken += taken
            if receipt is None:
                self.ledger.overflowed += taken
            else:
                self.ledger.acknowledged += taken
                self.ledger.refused += receipt.refused
                self.ledger.duplicates += receipt.duplicates
            if self._file is not None:
                self._file.mark(self.ledger)

    def tidy(self) -> None:
        """Rewrite the file once enough of it is released. The sender calls this between
        uploads: the flight loop never rewrites, at most it waits for one to end."""
        with self._cond:
            if self._file is not None and self.ledger.released - self._released_at_rewrite >= (
                    max(REWRITE_AFTER, len(self._items))):
                self._rewrite()

    def _rewrite(self) -> None:
        self._file.rewrite(self.ledger, self._items)
        self._released_at_rewrite = self.ledger.released

    def close(self) -> None:
        """Leave the file compact for the next agent of this UAV."""
        with self._cond:
            if self._file is not None:
                self._rewrite()
                self._file.close()


def open_outbox(capacity: int, directory: Path | None, uav: int, log: logging.Logger
                ) -> Outbox:
    """UAV ``uav``'s outbox: in memory only without a directory, else durable in it."""
    if directory is None:
        return Outbox(capacity)
    outbox = Outbox(capacity, OutboxFile(outbox_path(directory, uav), log))
    if held := len(outbox):
        log.info("%d measurements of an earlier agent of this UAV have no receipt: sending "
                 "them first", held)
    return outbox


class Uploader:
    """Sends the outbox to the cloud on its own thread, retrying with back-off."""

    def __init__(self, session, key: str, uav: int, source: str, outbox: Outbox,
                 log: logging.Logger, batch: int = DEFAULT_BATCH,
                 max_age: float = DEFAULT_MAX_AGE_S):
        self.session, self.key, self.outbox, self.log = session, key, outbox, log
        self.uav, self.source = uav, source
        self.batch, self.max_age = batch, max_age
        self.uploads = 0
        self.failures = 0  # uploads without a receipt (tried again)
        self.stored = 0
        self._counts = threading.Lock()  # round uploads are answered on senders' threads
        # Round uploads go out at once and their receipts are awaited off the flight loop: the
        # world waits for the cloud's close of the round, not for the agent's receipt, and a
        # round the world never opens (a forged one) is answered only after a while.
        self._round_senders = ThreadPoolExecutor(ROUND_SENDERS, thread_name_prefix="round")

    def run(self, stop: threading.Event) -> None:
        """Until ``stop``; then try for ``FLUSH_S`` more to hand over what is left."""
        retry = RETRY_FIRST_S
        while not stop.is_set():
            batch = self.outbox.wait_batch(self.batch, self.max_age, timeout=0.5)
            if not batch:
                continue
            if self._send(batch, RECEIPT_TIMEOUT_S):
                retry = RETRY_FIRST_S
            else:
                stop.wait(retry)
                retry = min(2 * retry, RETRY_MAX_S)
            self.outbox.tidy()
        self._round_senders.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + FLUSH_S
        while (remaining := deadline - time.monotonic()) > 0:
            batch = self.outbox.wait_batch(self.batch, self.max_age, timeout=0, flush=True)
            if not batch:
                return
            if not self._send(batch, remaining):
                time.sleep(min(RETRY_FIRST_S, max(remaining, 0)))
        if left := len(self.outbox):
            self.log.warning("stopped with %d measurements not handed over", left)

    def _send(self, batch: list[tuple[int, tuple]], timeout: float) -> bool:
        upload = encode_upload(self.uav, self.source, [record for _, record in batch])
        refused = duplicates = 0
        try:
            receipt = bus.query(self.session, self.key, UploadReceipt, upload, timeout=timeout)
        except bus.QueryRefused as exc:  # the cloud will never take these: do not resend
            refused = len(batch)
            self.log.warning("upload refused: %s", exc)
        except bus.BusError:
            self.failures += 1
            if self.failures in (1, 10) or self.failures % 100 == 0:
                self.log.info("no receipt for an upload (%d so far); %d measurements kept",
                              self.failures, len(self.outbox))
            return False
        else:
            self.stored += receipt.stored
            refused, duplicates = receipt.refused, receipt.duplicates
        self.uploads += 1
        self.outbox.acknowledge(batch[-1][0], refused, duplicates)
        return True

    def send_round(self, records: list[tuple], round_number: int, timeout: float) -> None:
        """The cloud on the lockstep clock: a round's records (as the outbox holds them; maybe
        none) in one upload tagged with the round, at once. They pass the outbox: a round
        closes without an upload that does not arrive in time, so one is never sent again."""
        upload = encode_upload(self.uav, self.source, records, round_number)
        self._round_senders.submit(self._send_round, upload, len(records), round_number,
                                   timeout)

    def _send_round(self, upload: bytes, taken: int, round_number: int, timeout: float) -> None:
        try:
            receipt = bus.query(self.session, self.key, UploadReceipt, upload, timeout=timeout)
        except bus.BusError as exc:
            self.log.warning("round %d: upload of %d measurements lost: %s", round_number,
                             taken, exc)
            receipt = None
        with self._counts:
            if receipt is None:
                self.failures += 1
            else:
                self.uploads += 1
                self.stored += receipt.stored
        self.outbox.passed(taken, receipt)

    def counts(self) -> dict[str, int]:
        ledger = self.outbox.ledger
        return {"measurements_taken": ledger.taken,
                "measurements_acknowledged": ledger.acknowledged,
                "measurements_buffered": len(self.outbox),
                "measurements_overflowed": ledger.overflowed,
                "measurements_refused": ledger.refused,
                "measurements_duplicates": ledger.duplicates, "uploads": self.uploads,
                "upload_failures": self.failures}
