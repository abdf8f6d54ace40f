"""What agents and the cloud exchange: the measurement uploads (and the cloud's receipts),
and the networks the cloud serves (the value network, the SINR map)."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import ClassVar, Literal

import msgpack
import numpy as np
from pydantic import Field, model_validator

from shared.measurements import (
    FEATURES_DTYPE,
    MEASUREMENT_FIELDS,
    Label,
    MeasuredLevel,
    MeasuredStep,
    MeasuredTime,
    MeasurementBatch,
    ReportedSinr,
)
from shared.wire import Accuracy, Count, Digest, Finite, Message, Positive, UavId

MAX_UPLOAD = 256  # measurements per upload
FEATURE_BYTES = np.dtype(FEATURES_DTYPE).itemsize
MAX_WEIGHTS_BYTES = 8 * 2**20
MapMode = Literal["online", "perfect", "outdated"]


class MeasurementUpload(Message):
    """A batch of one UAV's measurements, sent as a query: the cloud answers once it has
    stored them, and the agent keeps them until then (the cloud screens each row).

    Column by column, the features as one block of little-endian float32 (what the agent
    computed and the cloud stores): as a map of floats per record, decoding an upload cost the
    cloud more than storing it (BENCHMARKS.md, "Fleets of agent processes")."""

    max_bytes: ClassVar[int] = 512 * 1024
    uav: UavId
    source: Label  # the UAV's name on its measurements, e.g. "uav-3"
    ids: list[Label] = Field(max_length=MAX_UPLOAD)
    steps: list[MeasuredStep]
    times: list[MeasuredTime]
    features: bytes  # len(ids) rows of FEATURES_DTYPE values, row after row
    levels: list[MeasuredLevel]
    sinr_db: list[ReportedSinr]
    # A round's upload (the cloud on the lockstep clock), which may hold nothing: the cloud
    # waits for one from every agent the round names.
    round: Count | None = None

    @model_validator(mode="after")
    def _rows(self) -> MeasurementUpload:
        rows = len(self.ids)
        if not rows and self.round is None:
            raise ValueError("ids: an upload outside a round holds at least one measurement")
        if any(len(column) != rows for column in (self.steps, self.times, self.levels,
                                                  self.sinr_db)):
            raise ValueError(f"steps, times, levels and sinr_db: one value per id ({rows})")
        if len(self.features) % FEATURE_BYTES or (len(self.features) // FEATURE_BYTES) % max(
                rows, 1) or bool(rows) != bool(self.features):
            raise ValueError(f"features: {rows} rows of {FEATURES_DTYPE} values")
        return self

    def newest(self) -> float:
        """When its newest measurement was taken (0 for none)."""
        return max(self.times, default=0.0)

    def batch(self) -> MeasurementBatch:
        """Its rows as arrays, not yet screened (``MeasurementSpec.screen``)."""
        rows = len(self.ids)
        features = np.frombuffer(self.features, dtype=FEATURES_DTYPE)
        features = features.reshape(rows, features.size // max(rows, 1))
        return MeasurementBatch.of_arrays(
            self.ids, self.source, self.steps, self.times, features, self.levels,
            [np.nan if db is None else db for db in self.sinr_db])


class UploadReceipt(Message):
    """The cloud's answer to an upload, once it is in the replay memory: records stored now,
    records it already held (a repeat after a lost receipt) and records it refused."""

    stored: Count
    duplicates: Count
    refused: Count


class RasterGrid(Message):
    """Where an int8 level raster lies: node (0, 0) at (x0, y0), rows along y."""

    x0: Finite
    y0: Finite
    spacing: Positive
    rows: int = Field(ge=2, le=4096)
    cols: int = Field(ge=2, le=4096)


class _Weights(Message):
    """Network weights as a message: a version and safetensors (or raster) bytes, refused
    unless their sha256 matches."""

    max_bytes: ClassVar[int] = MAX_WEIGHTS_BYTES + 4096
    version: Count
    sha256: Digest
    data: bytes = Field(min_length=1, max_length=MAX_WEIGHTS_BYTES)

    @model_validator(mode="after")
    def _digest(self):
        if hashlib.sha256(self.data).hexdigest() != self.sha256:
            raise ValueError("sha256 digest does not match the data")
        return self


class ValueWeights(_Weights):
    """The value network as safetensors bytes (architecture in the header metadata)."""


class SinrMap(_Weights):
    """A version of the SINR map: with ``grid`` unset, ``data`` is the SINR-mapping network as
    safetensors (``online``); with ``grid`` set, it is an int8 level raster, row-major
    (the true map for ``perfect``, the no-jammer map for ``outdated``)."""

    mode: MapMode
    accuracy: Accuracy | None = None
    grid: RasterGrid | None = None

    @model_validator(mode="after")
    def _raster_size(self) -> SinrMap:
        if self.grid is not None and len(self.data) != self.grid.rows * self.grid.cols:
            raise ValueError("raster data length differs from rows x cols")
        return self

    def levels(self) -> np.ndarray:
        grid = self.grid
        return np.frombuffer(self.data, dtype=np.int8).reshape(grid.rows, grid.cols)


def encode_upload(uav: int, source: str, records: Sequence[tuple],
                  round: int | None = None) -> bytes:
    """``encode`` of the ``MeasurementUpload`` of ``records`` without a model: each record a
    tuple of a ``Measurement``'s field values in ``MEASUREMENT_FIELDS`` order, its features
    already ``FEATURES_DTYPE`` bytes (as an agent's outbox holds them). The cloud validates
    every row on receipt."""
    if any(record[1] != source for record in records):
        raise ValueError(f"an upload's measurements are all {source!r}'s")
    ids, _, steps, times, features, levels, sinr_db = (
        zip(*records, strict=True) if records else ((),) * len(MEASUREMENT_FIELDS))
    return msgpack.packb({"uav": uav, "source": source, "ids": list(ids), "steps": list(steps),
                          "times": list(times), "features": b"".join(features),
                          "levels": list(levels), "sinr_db": list(sinr_db), "round": round},
                         use_bin_type=True)
