"""The agent's measurement uploads: an outbox that keeps every measurement until the cloud has
acknowledged it, and a sender thread that empties it.

Each upload is a query; the cloud answers with an ``UploadReceipt`` once the records are in its
replay memory. No answer (cloud down, restarting, overloaded) leaves the records in the outbox
and the sender tries again later, so a cloud outage shorter than the outbox loses nothing. A
receipt lost on the way makes the sender repeat an upload the cloud already stored: the memory
recognises the ids, so every measurement is stored exactly once. Only an outbox overflowing
during a long outage drops records, the oldest first, and counts them.

The flight loop never waits for the cloud: it only appends to the outbox.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque

from shared import bus
from shared.measurements import Measurement
from shared.messages import MAX_UPLOAD, MeasurementUpload, UploadReceipt

DEFAULT_CAPACITY = 20_000  # measurements: over 3 minutes of a UAV at 100 steps/s
# Measurements per upload: each upload costs the cloud a transaction and the agent a round trip
# on a thread that shares the interpreter with its decisions; the age limit keeps slow clocks
# fresh.
DEFAULT_BATCH = 64
RECEIPT_TIMEOUT_S = 5.0  # a cloud busy retraining still answers well within this
RETRY_FIRST_S, RETRY_MAX_S = 0.2, 2.0
FLUSH_S = 3.0  # how long a stopping agent keeps trying to hand over what it holds


class Outbox:
    """Measurements not yet acknowledged, oldest first, at most ``capacity`` of them."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY):
        if capacity < 1:
            raise ValueError("the outbox needs room for at least one measurement")
        self.capacity = capacity
        self._items: deque[tuple[int, Measurement]] = deque()
        self._numbers = itertools.count()
        self._cond = threading.Condition()
        self.taken = 0
        self.acknowledged = 0
        self.overflowed = 0  # dropped, oldest first, because the outbox was full

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def add(self, measurement: Measurement, batch: int) -> None:
        with self._cond:
            self._items.append((next(self._numbers), measurement))
            self.taken += 1
            if len(self._items) > self.capacity:
                self._items.popleft()
                self.overflowed += 1
            if len(self._items) in (1, batch):  # the age clock starts, or a batch is full
                self._cond.notify()

    def wait_batch(self, batch: int, max_age: float, timeout: float, flush: bool = False
                   ) -> list[tuple[int, Measurement]]:
        """The oldest records (at most one upload's worth) once there are ``batch`` of them or
        the oldest is ``max_age`` seconds old (any at all with ``flush``); [] after
        ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                now = time.monotonic()
                if self._items:
                    age = time.time() - self._items[0][1].time
                    if flush or len(self._items) >= batch or age >= max_age:
                        return list(itertools.islice(self._items, MAX_UPLOAD))
                    wake = min(deadline, now + max_age - age)
                else:
                    wake = deadline
                if now >= deadline:
                    return []
                self._cond.wait(max(wake - now, 0.001))

    def acknowledge(self, last: int) -> None:
        """Records up to number ``last`` reached the cloud (or were refused by it for good)."""
        with self._cond:
            while self._items and self._items[0][0] <= last:
                self._items.popleft()
                self.acknowledged += 1


class Uploader:
    """Sends the outbox to the cloud on its own thread, retrying with back-off."""

    def __init__(self, session, key: str, uav: int, outbox: Outbox, log: logging.Logger,
                 batch: int = DEFAULT_BATCH, max_age: float = 1.0):
        self.session, self.key, self.uav, self.outbox, self.log = session, key, uav, outbox, log
        self.batch, self.max_age = batch, max_age
        self.uploads = 0
        self.failures = 0  # uploads without a receipt (tried again)
        self.stored = 0
        self.duplicates = 0
        self.refused = 0

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
        deadline = time.monotonic() + FLUSH_S
        while (remaining := deadline - time.monotonic()) > 0:
            batch = self.outbox.wait_batch(self.batch, self.max_age, timeout=0, flush=True)
            if not batch:
                return
            if not self._send(batch, remaining):
                time.sleep(min(RETRY_FIRST_S, max(remaining, 0)))
        if left := len(self.outbox):
            self.log.warning("stopped with %d measurements not handed over", left)

    def _send(self, batch: list[tuple[int, Measurement]], timeout: float) -> bool:
        # Built from measurements this agent made and checked: no second validation.
        upload = MeasurementUpload.model_construct(uav=self.uav,
                                                   measurements=[m for _, m in batch])
        try:
            receipt = bus.query(self.session, self.key, UploadReceipt, upload, timeout=timeout)
        except bus.QueryRefused as exc:  # the cloud will never take these: do not resend
            self.refused += len(batch)
            self.log.warning("upload refused: %s", exc)
        except bus.BusError:
            self.failures += 1
            if self.failures in (1, 10) or self.failures % 100 == 0:
                self.log.info("no receipt for an upload (%d so far); %d measurements kept",
                              self.failures, len(self.outbox))
            return False
        else:
            self.stored += receipt.stored
            self.duplicates += receipt.duplicates
            self.refused += receipt.refused
        self.uploads += 1
        self.outbox.acknowledge(batch[-1][0])
        return True

    def counts(self) -> dict[str, int]:
        o = self.outbox
        return {"measurements_taken": o.taken, "measurements_acknowledged": o.acknowledged,
                "measurements_buffered": len(o), "measurements_overflowed": o.overflowed,
                "measurements_refused": self.refused,
                "measurements_duplicates": self.duplicates, "uploads": self.uploads,
                "upload_failures": self.failures}
