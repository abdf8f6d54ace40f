"""A process's answer to a status query, and what the operator reads of the cloud's."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.jammer_messages import describe_count
from shared.wire import Count, Finite, Message, Text

Role = Literal["world", "cloud", "agent"]  # the processes that answer status queries
Scalar = int | float | str | bool | None


class ProcessStatus(Message):
    """A process's answer to a status query."""

    role: Role
    ident: Text
    pid: int = Field(ge=0)
    t: Finite
    episode: Count | None = None
    step: Count | None = None
    value_version: Count | None = None
    sinr_version: Count | None = None
    dropped: dict[str, Count] = Field(default_factory=dict, max_length=64)
    details: dict[str, Scalar] = Field(default_factory=dict, max_length=64)


def mapper_summary(cloud: ProcessStatus | None) -> str:
    """The online mapper's state from the cloud's status: map version, accuracy on recent
    uploads, and what it does about a change (with the measurements gathered since)."""
    if cloud is None or "map_phase" not in cloud.details:
        return "map ?"
    d = cloud.details
    recent = d.get("recent_accuracy")
    text = f"map v{cloud.sinr_version}" + (
        " (provisional)" if d.get("map_provisional") else "") + (
        f" {recent:.0%} on recent" if isinstance(recent, float) else "")
    if d["map_phase"] != "watching":
        text += (f", {d['map_phase']} ({d.get('since_change')} since change, "
                 f"{describe_count(d.get('jammers_counted'))})")
    return text
