"""What agents and the cloud exchange: the measurement uploads (and the cloud's receipts),
and the networks the cloud serves (the value network, the SINR map)."""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from typing import ClassVar, Literal

import msgpack
import numpy as np
from pydantic import Field, model_validator

from shared.measurements import MEASUREMENT_FIELDS, Measurement
from shared.wire import Accuracy, Count, Digest, Finite, Message, Positive, UavId

MAX_UPLOAD = 256  # measurements per upload
MAX_WEIGHTS_BYTES = 8 * 2**20
MapMode = Literal["online", "perfect", "outdated"]


class MeasurementUpload(Message):
    """A batch of one UAV's measurements, sent as a query: the cloud answers once it has
    stored them, and the agent keeps them until then (the cloud screens each record)."""

    max_bytes: ClassVar[int] = 512 * 1024
    uav: UavId
    measurements: list[Measurement] = Field(max_length=MAX_UPLOAD)
    # A round's upload (the cloud on the lockstep clock), which may hold nothing: the cloud
    # waits for one from every agent the round names.
    round: Count | None = None

    @model_validator(mode="after")
    def _something_or_a_round(self) -> MeasurementUpload:
        if not self.measurements and self.round is None:
            raise ValueError("measurements: an upload outside a round holds at least one")
        return self


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


def encode_upload(uav: int, records: Iterable[tuple], round: int | None = None) -> bytes:
    """``encode`` of a ``MeasurementUpload`` of ``records``, each a tuple of a ``Measurement``'s
    field values in ``MEASUREMENT_FIELDS`` order, without a model per record: an agent uploads
    the records it made itself, and the cloud validates each one on receipt."""
    measurements = [dict(zip(MEASUREMENT_FIELDS, record, strict=True)) for record in records]
    return msgpack.packb({"uav": uav, "measurements": measurements, "round": round},
                         use_bin_type=True)
