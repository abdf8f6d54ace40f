"""Per-UAV mission outcomes: exclusive and final once set."""

from __future__ import annotations

from enum import IntEnum


class Outcome(IntEnum):
    ACTIVE = 0
    SUCCESS = 1
    DISCONNECTION = 2
    COLLISION = 3
    TIMEOUT = 4

    @property
    def label(self) -> str:
        return self.name.lower()


FINAL_OUTCOMES = (Outcome.SUCCESS, Outcome.DISCONNECTION, Outcome.COLLISION, Outcome.TIMEOUT)
OUTCOME_LABELS = [outcome.label for outcome in Outcome]
