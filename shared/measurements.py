"""SINR measurements: the upload records, their features' size and the rules they must meet.

A UAV's measurement is <positions of its K_n nearest GBSs, SINR level> (paper Sec. III-C);
``planning.measuring`` computes those features and picks the reports a UAV uploads.

Uploads travel column by column (``shared.cloud_messages.MeasurementUpload``), an agent's
outbox holds ``Measurement`` records, and the cloud handles them in bulk as a
``MeasurementBatch`` of arrays. ``MeasurementSpec.screen`` is the one place where the rules a
measurement must satisfy (feature length, finite values, known level) are checked.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from shared.scenario import Scenario

PER_GBS_FEATURES = ("dx", "dy", "distance", "elevation", "azimuth")
# The widest SINR a report may carry, either way (dB): past any real receiver's range (NR's
# SS-SINR reports span -23 to 40 dB), so only a broken or forged report is refused.
MAX_REPORTED_DB = 100.0


def features_per_gbs(scenario: Scenario) -> int:
    """``PER_GBS_FEATURES``, and where GBSs reuse channels (``gbs.channels``) a co-channel
    flag: without it, a map cannot tell which GBSs interfere where."""
    return len(PER_GBS_FEATURES) + int(scenario.gbs.channels is not None)


def feature_size(scenario: Scenario) -> int:
    """Length of a measurement's features: per nearby GBS, then the nearest one's position
    where ``policy.nearest_gbs_position`` asks for it."""
    return (features_per_gbs(scenario) * scenario.policy.nearby_gbs
            + 2 * int(scenario.policy.nearest_gbs_position))


# Why a measurement was refused; the replay memory keeps one counter per reason.
REJECT_REASONS = ("malformed", "wrong_length", "not_finite", "unknown_level")


# A measurement's fields as they travel, record by record (``Measurement``) or column by column
# (``shared.cloud_messages.MeasurementUpload``).
Label = Annotated[str, Field(min_length=1, max_length=200)]  # an id, or whose it is
MeasuredStep = Annotated[int, Field(ge=0, lt=2**63)]
MeasuredTime = Annotated[float, Field(allow_inf_nan=False)]  # unix or simulated seconds
# A level's range depends on the scenario (checked by MeasurementSpec); the int32 bound only
# keeps absurd values from overflowing the arrays.
MeasuredLevel = Annotated[int, Field(ge=-(2**31), lt=2**31)]
# The SINR measured (dB, in the receiver's report steps) where the scenario's UAVs report it
# (uav.report = "db"); None from a receiver that reports levels only.
ReportedSinr = Annotated[float, Field(ge=-MAX_REPORTED_DB, le=MAX_REPORTED_DB,
                                      allow_inf_nan=False)] | None


class Measurement(BaseModel):
    """One measurement as a record: how an agent's outbox holds it (``MEASUREMENT_FIELDS``)
    and ``MeasurementBatch.records`` gives it. Its shape rules depend on the scenario: see
    MeasurementSpec."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: Label  # unique per upload: a resend is a duplicate
    source: Label  # e.g. "uav-3"
    step: MeasuredStep
    time: MeasuredTime
    features: list[float]  # gbs_features at the measuring position
    level: MeasuredLevel  # the quantized SINR level measured there
    sinr_db: ReportedSinr = None


# Measurement's fields in order. An agent holds the measurements it takes as plain tuples in
# this order (a model per record cost its flight loop more than everything else it does with
# one) and uploads them column by column: ``shared.cloud_messages.encode_upload``.
MEASUREMENT_FIELDS = tuple(Measurement.model_fields)
# The features as an agent holds and uploads them and the cloud stores them: little-endian
# float32, in half the size of float64 and never turned into Python floats on the way.
FEATURES_DTYPE = "<f4"


@dataclass(frozen=True)
class MeasurementBatch:
    """Many measurements as arrays, the form memory, monitor and training work on."""

    ids: list[str]
    sources: list[str]
    steps: np.ndarray  # (n,) int64
    times: np.ndarray  # (n,) float64
    features: np.ndarray  # (n, F) float32
    levels: np.ndarray  # (n,) int64
    sinr_db: np.ndarray  # (n,) float64, NaN where a receiver reported the level only

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def of_arrays(
        cls,
        ids: Sequence[str],
        sources: Sequence[str] | str,
        steps: np.ndarray | int,
        times: np.ndarray | float,
        features: np.ndarray,
        levels: np.ndarray,
        sinr_db: np.ndarray | None = None,
    ) -> MeasurementBatch:
        """A batch from arrays; a scalar source, step or time applies to every row, and no
        ``sinr_db`` means levels only."""
        n = len(ids)
        with np.errstate(over="ignore"):  # beyond float32 becomes inf, refused as not finite
            features = np.asarray(features, dtype=np.float32)
        return cls(
            ids=list(ids),
            sources=[sources] * n if isinstance(sources, str) else list(sources),
            steps=np.broadcast_to(np.asarray(steps, dtype=np.int64), (n,)).copy(),
            times=np.broadcast_to(np.asarray(times, dtype=np.float64), (n,)).copy(),
            features=features.reshape(n, -1) if n else features.reshape(0, features.shape[-1]),
            levels=np.asarray(levels, dtype=np.int64).reshape(n),
            sinr_db=(np.full(n, np.nan) if sinr_db is None
                     else np.asarray(sinr_db, dtype=np.float64).reshape(n).copy()),
        )

    @classmethod
    def empty(cls, feature_size: int) -> MeasurementBatch:
        return cls.of_arrays([], [], 0, 0.0, np.zeros((0, feature_size)), np.zeros(0))

    def take(self, rows: np.ndarray) -> MeasurementBatch:
        """The rows selected by a boolean mask or an index array, in that order."""
        index = np.flatnonzero(rows) if np.asarray(rows).dtype == bool else np.asarray(rows)
        return MeasurementBatch(
            ids=[self.ids[i] for i in index],
            sources=[self.sources[i] for i in index],
            steps=self.steps[index],
            times=self.times[index],
            features=self.features[index],
            levels=self.levels[index],
            sinr_db=self.sinr_db[index],
        )

    def records(self) -> list[Measurement]:
        """Validated records, e.g. to send; a row the model refuses raises ValidationError."""
        return [
            Measurement(id=i, source=s, step=int(st), time=float(t), features=f, level=int(lv),
                        sinr_db=None if math.isnan(db) else db)
            for i, s, st, t, f, lv, db in zip(
                self.ids,
                self.sources,
                self.steps,
                self.times,
                self.features.tolist(),
                self.levels,
                self.sinr_db.tolist(),
                strict=True,
            )
        ]

    @staticmethod
    def concatenate(batches: Sequence[MeasurementBatch]) -> MeasurementBatch:
        return MeasurementBatch(
            ids=[i for b in batches for i in b.ids],
            sources=[s for b in batches for s in b.sources],
            steps=np.concatenate([b.steps for b in batches]),
            times=np.concatenate([b.times for b in batches]),
            features=np.concatenate([b.features for b in batches]),
            levels=np.concatenate([b.levels for b in batches]),
            sinr_db=np.concatenate([b.sinr_db for b in batches]),
        )


@dataclass(frozen=True)
class MeasurementSpec:
    """What a valid measurement looks like in one scenario: ``feature_size`` features, known
    levels."""

    feature_size: int
    level_count: int

    @classmethod
    def of(cls, scenario: Scenario) -> MeasurementSpec:
        return cls(
            feature_size=feature_size(scenario),
            level_count=scenario.channel.level_count,
        )

    def from_records(
        self, records: Iterable[Measurement | Mapping]
    ) -> tuple[MeasurementBatch, Counter]:
        """Records (models or plain dicts off the wire) to a screened batch and the count of
        refusals per reason."""
        rejected: Counter = Counter()
        kept: list[Measurement] = []
        for record in records:
            if not isinstance(record, Measurement):
                try:
                    record = Measurement.model_validate(record)
                except ValidationError:
                    rejected["malformed"] += 1
                    continue
            if len(record.features) != self.feature_size:
                rejected["wrong_length"] += 1
                continue
            kept.append(record)
        batch = MeasurementBatch.of_arrays(
            [r.id for r in kept],
            [r.source for r in kept],
            np.array([r.step for r in kept], dtype=np.int64),
            np.array([r.time for r in kept], dtype=np.float64),
            np.array([r.features for r in kept], dtype=np.float64).reshape(-1, self.feature_size),
            np.array([r.level for r in kept], dtype=np.int64),
            np.array([np.nan if r.sinr_db is None else r.sinr_db for r in kept],
                     dtype=np.float64),
        )
        batch, more = self.screen(batch)
        return batch, rejected + more

    def screen(self, batch: MeasurementBatch) -> tuple[MeasurementBatch, Counter]:
        """The rows that satisfy the rules, and the count of refusals per reason (first
        failing rule of each row)."""
        n = len(batch)
        if batch.features.ndim != 2 or batch.features.shape[1] != self.feature_size:
            return MeasurementBatch.empty(self.feature_size), +Counter(wrong_length=n)
        # A reported SINR is NaN where only the level was reported; anything else must be a
        # number a receiver can report.
        reported = np.isnan(batch.sinr_db) | (np.abs(batch.sinr_db) <= MAX_REPORTED_DB)
        finite = (np.isfinite(batch.features).all(axis=1) & np.isfinite(batch.times)
                  & reported)
        known = (batch.levels >= 0) & (batch.levels < self.level_count)
        rejected = Counter()
        if not finite.all():
            rejected["not_finite"] = int((~finite).sum())
        if not known.all():
            rejected["unknown_level"] = int((finite & ~known).sum())
        ok = finite & known
        return (batch if ok.all() else batch.take(ok)), +rejected

    def check(self, record: Measurement | Mapping) -> Measurement:
        """One record, validated for this scenario; raises ValueError naming the reason."""
        batch, rejected = self.from_records([record])
        if rejected:
            raise ValueError(f"measurement refused: {next(iter(rejected))}")
        return batch.records()[0]
