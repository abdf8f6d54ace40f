"""How probable a receiver's report is, given what the cloud believes of the SINR there.

A measurement's SINR in dB is reported with the receiver's error, N(0, sd^2); a level report
is that SINR quantized with the scenario's level edges (an ordinal probit), a dB report that
SINR in steps of ``uav.report_step_db``. A share ``OUTLIER_SHARE`` of reports contradicts any
model (a deep shadow, a map error) and falls anywhere. The jammer estimate reads thousands of
reports against many hypotheses, so their log-probabilities are tabulated over the SINR
(``ReportTables``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import log_ndtr, ndtr

from planning.compiled import chosen_planner, compiled_module
from shared.radio import RadioModel

# What a report adds once the world's no-jammer SINR is known: the receiver's noise and the
# spread of the jammer's loss about the ideal model's (the shadowing of the jammer's own
# link), together; measured in icc2021-shadowed (BENCHMARKS.md, "Online SINR mapping", the
# estimator's model).
REPORT_SIGMA_DB = 1.2
OUTLIER_SHARE = 0.01  # reports that may contradict the model (a deep shadow, a map error)
# An outlier dB report is taken as uniform over this span of SINRs, about what the area's
# SINRs span.
OUTLIER_SPAN_DB = 40.0

_SINR_STEP_DB = 0.05  # resolution of the level tables over the SINR
_SINR_RANGE_DB = (-60.0, 40.0)  # beyond, every level's probability is at its limit
_SD_STEP_DB = 0.05  # spreads are rounded to this to share level tables
# A dB report's table spans its offsets from the believed SINR this far either way: past it
# every spread in use leaves only the outlier floor.
_OFFSET_RANGE_DB = 40.0


def log_band_probability(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """log(Phi(upper) - Phi(lower)), taken in the tail where the difference does not
    cancel; -inf for an empty band. Infinite bounds are welcome: a band from -inf to +inf
    (where no flip is needed) has probability 1."""
    with np.errstate(invalid="ignore"):
        flip = lower + upper > 0
    lower, upper = np.where(flip, -upper, lower), np.where(flip, -lower, upper)
    log_upper = log_ndtr(upper)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        out = log_upper + np.log1p(-np.exp(log_ndtr(lower) - log_upper))
    return np.where(upper > lower, out, -np.inf)


def band_edges(radio: RadioModel, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The SINR band (dB) of each of ``levels``: its lower and upper edges, infinite at the
    ends of the scale."""
    bounds = np.concatenate([[-np.inf], radio.level_edges_db, [np.inf]])
    return bounds[levels], bounds[levels + 1]


def with_outliers(log_model: np.ndarray, outlier_share: float,
                  outlier_probability: float) -> np.ndarray:
    """A report's log-probability when a share ``outlier_share`` of reports contradicts the
    model and falls anywhere, with probability ``outlier_probability``."""
    return np.logaddexp(math.log1p(-outlier_share) + log_model,
                        math.log(outlier_share * outlier_probability))


def report_shares(radio: RadioModel, sinr_db: np.ndarray,
                  report_sigma_db: float = REPORT_SIGMA_DB) -> np.ndarray:
    """The share of reports at each level (..., levels) where the SINR is ``sinr_db`` and a
    report errs by N(0, report_sigma_db^2): what a map learned from many reports there gives
    at best, and what ``no_jammer_belief.map_reading`` reads back."""
    bounds = np.concatenate([[-np.inf], radio.level_edges_db, [np.inf]])
    below = ndtr((bounds - np.asarray(sinr_db)[..., None]) / report_sigma_db)
    return np.diff(below, axis=-1)


class ReportTables:
    """log P(report | believed SINR, spread), with the outlier floor, tabulated over the SINR
    for every spread in use (rounded to ``_SD_STEP_DB``, so that a few tables serve thousands
    of measurements). A level report's is the ordinal probit's: the probability of the
    level's band. A dB report's (the SINR in steps of ``step_db``) is the probability of its
    step's interval, a function of the report less the SINR, tabulated over that."""

    def __init__(self, edges_db: np.ndarray, sds_db: np.ndarray, outlier_share: float,
                 step_db: float | None):
        rounded, self.table_of = np.unique(np.rint(sds_db / _SD_STEP_DB), return_inverse=True)
        self.table_of = self.table_of.reshape(-1)
        sinr_db = np.arange(*_SINR_RANGE_DB, _SINR_STEP_DB)
        self.sinr_count = len(sinr_db)
        bounds = np.concatenate([[-np.inf], edges_db, [np.inf]])
        self.level_count = len(bounds) - 1
        spread = (rounded * _SD_STEP_DB)[:, None, None]
        # A spread under half a step rounds to 0 (icc2021's exact receivers read at the
        # survey map's 0.02 dB): its bounds over it are infinite, and its band a step, 1
        # inside and 0 outside, which log_band_probability takes as it is.
        self.step_db = step_db
        with np.errstate(divide="ignore"):
            self.values = with_outliers(
                log_band_probability((bounds[:-1, None] - sinr_db) / spread,
                                     (bounds[1:, None] - sinr_db) / spread),
                outlier_share, 1.0 / self.level_count).ravel()
            if step_db is not None:  # offsets of a report from the SINR, as for the SINR
                offsets_db = np.arange(-_OFFSET_RANGE_DB, _OFFSET_RANGE_DB, _SINR_STEP_DB)
                spread = spread[:, 0]
                self.db_values = with_outliers(
                    log_band_probability((offsets_db - step_db / 2.0) / spread,
                                         (offsets_db + step_db / 2.0) / spread),
                    outlier_share, step_db / OUTLIER_SPAN_DB).ravel()
                self.offset_count = len(offsets_db)

    def weighted_tables(self, believed_db: np.ndarray, loss_db: np.ndarray, levels: np.ndarray,
                        reported_db: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Each measurement's (the rows of these tables, in order) log-probability of its
        report where its SINR is ``believed_db`` (n,) less each of ``loss_db`` ((R,), or
        (n, R) for each its own), times its weight: (n, R) float32. The compiled core reads
        the tables unless ``JAMNAV_PLANNER=reference``: the same arithmetic, the same bits."""
        rows = np.arange(len(believed_db))
        if chosen_planner() != "compiled":
            return (weights[:, None] * self.log_probability(
                believed_db[:, None] - loss_db, levels[:, None], rows[:, None],
                reported_db[:, None])).astype(np.float32)
        out = np.empty((len(believed_db), np.shape(loss_db)[-1]), dtype=np.float32)
        with_db = self.step_db is not None
        compiled_module("_evidence").weighted_report_tables(
            np.ascontiguousarray(believed_db, dtype=np.float64),
            np.ascontiguousarray(np.atleast_2d(loss_db), dtype=np.float64),
            np.ascontiguousarray(self.table_of[rows] * self.level_count + levels,
                                 dtype=np.int64),
            self.values, self.sinr_count, _SINR_RANGE_DB[0], _SINR_STEP_DB,
            np.ascontiguousarray(reported_db if with_db else np.full(len(rows), np.nan),
                                 dtype=np.float64),
            np.ascontiguousarray(self.table_of[rows] if with_db else np.zeros(len(rows)),
                                 dtype=np.int64),
            self.db_values if with_db else np.zeros(1), self.offset_count if with_db else 1,
            _OFFSET_RANGE_DB, np.ascontiguousarray(weights, dtype=np.float64), out)
        return out

    def log_probability(self, sinr_db: np.ndarray, levels: np.ndarray, rows: np.ndarray,
                        reported_db: np.ndarray | None = None):
        """For measurement ``rows`` (their spreads), reported ``levels`` and, where finite,
        SINRs ``reported_db``, at believed SINRs ``sinr_db`` (any broadcastable shapes)."""
        step = np.rint((sinr_db - _SINR_RANGE_DB[0]) / _SINR_STEP_DB).astype(np.int64)
        np.clip(step, 0, self.sinr_count - 1, out=step)
        table = self.table_of[rows] * self.level_count + levels
        by_level = self.values[table * self.sinr_count + step]
        if reported_db is None or self.step_db is None:
            return by_level
        reported = np.isfinite(reported_db)
        if not reported.any():
            return by_level
        offset = np.rint((np.where(reported, reported_db, 0.0) - sinr_db + _OFFSET_RANGE_DB)
                         / _SINR_STEP_DB).astype(np.int64)
        np.clip(offset, 0, self.offset_count - 1, out=offset)
        by_db = self.db_values[self.table_of[rows] * self.offset_count + offset]
        return np.where(reported, by_db, by_level)
