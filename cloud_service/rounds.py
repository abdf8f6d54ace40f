"""The cloud on the lockstep clock: each world step's uploads taken as one round.

The world names the agents whose reports a round brings (``RoundOpened``); their uploads come
tagged with the round. Once all are in, the cloud stores them in UAV order, has the mapper
take them as one batch (what ``jamnav eval`` uploads after the same step), and answers the
world with the maps that published and the round each is in service from: a map published in
round t flies from round t + ceil(latency / dt), as in-process (``evaluation.OnlineMaps``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from shared.cloud_messages import MeasurementUpload
from shared.world_messages import RoundOpened

# How long a round waits for the uploads it names: an agent that died after the world named it
# must not stop the clock (the world itself waits for the round's close longer).
ROUND_WAIT_S = 30.0
# How long uploads wait for the world to open their round: it does so as it hands the agents
# their reports, so a round unopened by then is no round of this world's (a forgery, or a
# world gone), and its uploads are kept outside the rounds. The world opens a round just after
# handing the agents its reports, and an agent's upload can reach the cloud first: on a loaded
# 2-core machine by seconds, so 2 s took a real round's uploads out of it now and then. An
# upload held for a forged round is answered within this, well inside an agent's patience.
OPEN_WAIT_S = 5.0


def delay_rounds(latency_s: float, step_s: float) -> int:
    """Steps (rounds) between a map's publication and its first decisions: the one rule of
    the bus, ``jamnav eval`` and the benchmarks (a hair under a whole step is that step)."""
    return math.ceil(latency_s / step_s - 1e-9)


@dataclass
class Round:
    opened: RoundOpened | None = None
    uploads: dict[int, tuple[MeasurementUpload, Any]] = field(default_factory=dict)
    since: float = field(default_factory=time.monotonic)

    def complete(self) -> bool:
        return self.opened is not None and set(self.opened.uavs) <= self.uploads.keys()

    def overdue(self, now: float) -> bool:
        return self.opened is not None and now - self.since > ROUND_WAIT_S


class RoundDesk:
    """The rounds in the making, and the maps' service: which version flies after each round."""

    def __init__(self, delay: int, serving: int):
        self.delay = delay
        self.serving = serving  # the version the last closed round's next decisions fly
        self.pending: list[tuple[int, int]] = []  # (first round in service, version)
        self.closed_through = -1  # the last round closed
        self._rounds: dict[int, Round] = {}

    def open(self, opened: RoundOpened) -> None:
        """The world opens a round; one already closed is no round of this run's (a replayed
        or forged message), and is ignored: opened, it would be the oldest open round, and
        every round after it would wait ROUND_WAIT_S behind it."""
        if not self.stale(opened.round):
            self._rounds.setdefault(opened.round, Round()).opened = opened

    def add(self, upload: MeasurementUpload, reply: Any) -> None:
        """An upload of a round; a second one of the same UAV and round replaces the first."""
        self._rounds.setdefault(upload.round, Round()).uploads[upload.uav] = (upload, reply)

    def next_closing(
        self, now: float
    ) -> tuple[RoundOpened, list[tuple[MeasurementUpload, Any]]] | None:
        """The oldest opened round whose uploads are all in (or that waited long enough), its
        uploads in UAV order; None while it waits."""
        self._drop_unanswered(now)
        opened = [number for number, r in self._rounds.items() if r.opened is not None]
        if not opened:
            return None
        number = min(opened)
        current = self._rounds[number]
        if not (current.complete() or current.overdue(now)):
            return None
        del self._rounds[number]
        self.closed_through = number
        return current.opened, [current.uploads[uav] for uav in sorted(current.uploads)]

    def _drop_unanswered(self, now: float) -> None:
        """Forget the rounds opened that no upload came for in ROUND_WAIT_S. This run's world
        opens a round for the agents that measured in it, and they upload at once: such a
        round is a forged or replayed one, and closing it would put maps in service early and
        mark every later round of the world stale."""
        for number in [n for n, r in self._rounds.items() if r.overdue(now) and not r.uploads]:
            del self._rounds[number]

    def unopened(self, now: float) -> list[tuple[MeasurementUpload, Any]]:
        """The uploads of rounds the world has not opened within OPEN_WAIT_S, taken out."""
        gone = [number for number, r in self._rounds.items()
                if r.opened is None and now - r.since > OPEN_WAIT_S]
        return [upload for number in gone for upload in self._rounds.pop(number).uploads.values()]

    def published(self, round_number: int, versions: list[int]) -> None:
        """Versions published while round ``round_number`` was taken: they fly from
        ``round_number + delay`` on."""
        self.pending += [(round_number + self.delay, version) for version in versions]

    def close(self, round_number: int) -> None:
        """Put in service what is due by the decisions after ``round_number``."""
        due = [entry for entry in self.pending if entry[0] <= round_number]
        if due:
            self.serving = due[-1][1]
        self.pending = [entry for entry in self.pending if entry[0] > round_number]

    def stale(self, round_number: int) -> bool:
        """An upload for a round already closed (an agent's late or repeated one)."""
        return round_number <= self.closed_through
