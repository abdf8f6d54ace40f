"""The events every process publishes for anyone watching (``<prefix>/event/<type>``), one
model per type under one discriminated union, and their decoding."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, TypeAdapter, model_validator

from shared.jammer_messages import JammerEstimate, JammerInfo, recorded_one_jammer
from shared.outcomes import Outcome
from shared.scenario import MAX_JAMMERS, MAX_UAVS
from shared.wire import (
    Accuracy,
    Count,
    Digest,
    Finite,
    Message,
    NonNegative,
    Text,
    UavId,
    unpack,
    validated,
)

OutcomeLabel = Literal["success", "disconnection", "collision", "timeout"]


class _Event(Message):
    """What every event carries: when (unix seconds) and which process put it."""

    t: Finite  # unix seconds
    source: Text


class JammerChanged(_Event):
    """The world's jammers changed (a command, a swap): those in force from ``step`` on."""

    type: Literal["jammer_changed"] = "jammer_changed"
    jammers: list[JammerInfo] = Field(max_length=MAX_JAMMERS)
    episode: Count
    step: Count

    @model_validator(mode="before")
    @classmethod
    def _one_jammer_recorded(cls, data: Any) -> Any:
        return recorded_one_jammer(data, "jammer", "jammers")


class ChangeDetected(_Event):
    type: Literal["change_detected"] = "change_detected"
    version: Count  # the map version found outdated
    accuracy: Accuracy  # of that map on the window that fired
    change_time: Finite | None = None  # the detector's estimate of when the change happened


class SinrWeightsPublished(_Event):
    type: Literal["sinr_weights_published"] = "sinr_weights_published"
    version: Count
    accuracy: Accuracy | None
    sha256: Digest
    path: str = Field(max_length=4096)  # the safetensors file of this version (cloud's disk)
    # Corrected by where the jammer may be while its estimate has not converged yet.
    provisional: bool = False
    # How many jammers the uploads showed when the map was fitted, placed or not (None: they
    # could not tell yet): a provisional map's are counted before they are placed.
    jammers_counted: Count | None = Field(default=None, le=MAX_JAMMERS)


class JammerEstimated(_Event):
    type: Literal["jammer_estimated"] = "jammer_estimated"
    estimate: JammerEstimate


class RetrainFailed(_Event):
    type: Literal["retrain_failed"] = "retrain_failed"
    version: Count
    error: str = Field(max_length=2000)


class WeightsRefused(_Event):
    """An agent refused a weights payload and flies on with its previous version."""

    type: Literal["weights_refused"] = "weights_refused"
    uav: UavId
    weights: Literal["value", "sinr_map"]
    version: Count | None  # None: the payload was not even a readable message
    reason: str = Field(max_length=500)
    flying_on: Count | None  # the version still in use


class UavOutcomes(_Event):
    type: Literal["uav_outcomes"] = "uav_outcomes"
    episode: Count
    seed: Count
    steps: Count
    outcomes: list[OutcomeLabel] = Field(min_length=1, max_length=MAX_UAVS)


class RunFinished(_Event):
    type: Literal["run_finished"] = "run_finished"
    episodes: Count
    steps: Count
    seconds: NonNegative
    steps_per_second: NonNegative
    missed_deadlines: Count


Event = Annotated[
    JammerChanged | ChangeDetected | JammerEstimated | SinrWeightsPublished | RetrainFailed
    | WeightsRefused
    | UavOutcomes | RunFinished,
    Field(discriminator="type"),
]
_EVENTS: TypeAdapter[Event] = TypeAdapter(Event)


def decode_event(payload: bytes) -> Event:
    """The event in ``payload``, validated; MessageError otherwise."""
    return validated(_EVENTS.validate_python, unpack(bytes(payload), Message.max_bytes), "event")


def outcome_labels(codes) -> list[str]:
    return [Outcome(int(code)).label for code in codes]
