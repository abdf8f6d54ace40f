"""The world's side of the cloud on the lockstep clock (``shared.world_messages``,
MeasurementRound): the cloud's answers to the rounds, and the map version each decision
flies."""

from __future__ import annotations

import threading
import time

from shared.world_messages import RoundClosed


class CloudRounds:
    """The cloud's answers to the rounds (zenoh's thread writes, the main loop reads), and the
    map the decisions fly: what the last closed round put in service, until a pending one is
    due."""

    def __init__(self):
        self._cond = threading.Condition()
        self._closed: dict[int, RoundClosed] = {}
        self.serving: int | None = None  # None: the agents fly what they started with
        self.pending: list[tuple[int, int]] = []

    def put(self, closed: RoundClosed) -> None:
        with self._cond:
            self._closed[closed.round] = closed
            self._cond.notify()

    def wait(self, number: int, until: float, stop: threading.Event) -> bool:
        """Whether the cloud closed round ``number`` by ``until``."""
        with self._cond:
            while number not in self._closed:
                remaining = until - time.monotonic()
                if remaining <= 0 or stop.is_set():
                    return False
                self._cond.wait(min(remaining, 0.2))
            closed = self._closed.pop(number)
            self._closed = {k: v for k, v in self._closed.items() if k > number}
        self.serving, self.pending = closed.serving, closed.pending
        return True

    def flown_at(self, number: int) -> int | None:
        """The map version the decisions after round ``number`` fly."""
        due = [version for first, version in self.pending if first <= number]
        return due[-1] if due else self.serving
