"""What the online SINR mapper gives out: each map it publishes, with the estimate it was
corrected with (``PublishedWeights``), and what it made of a batch of uploads
(``IngestReport``)."""

from __future__ import annotations

from typing import NamedTuple

from cloud_service.change_detection import DetectorCheck
from cloud_service.estimated_jammer import JammerEstimate


class PublishedWeights(NamedTuple):
    data: bytes  # safetensors
    sha256: str
    version: int
    accuracy: float  # held-out accuracy on what it was trained on
    estimate: JammerEstimate | None  # the jammer estimate the map was corrected with
    # When the change it answers began, while the estimate is still being refined (None once
    # a map settles it): a restarted cloud goes on refining from there.
    refining_since: float | None = None
    # Corrected by the jammer's hypotheses while no estimate converges (see OnlineSinrMapper).
    provisional: bool = False
    # How many jammers the uploads showed when it was fitted, placed or not (None: they could
    # not tell): a provisional map's jammers are counted before they are placed.
    jammers_counted: int | None = None


class IngestReport(NamedTuple):
    accepted: int
    duplicates: int
    check: DetectorCheck | None
