"""The uploads' evidence for a jammer hypothesis against none: the weighted log-likelihood
ratio of a jammer at a place and power (``JammerEvidence``).

Model. A measurement's SINR in dB is its no-jammer SINR (``no_jammer_belief``) less the
jammer's loss, 10 log10(1 + I_J / (N + I)), plus the receiver's error; its report's
probability is then ``report_likelihood``'s.

Cost. The GBS signal and interference of each measurement do not depend on the jammer, and a
report's likelihood depends on the jammer only through r, its power over the interference
plus noise (dB). So each measurement gets a table of its log-likelihood over r once; a
hypothesis then costs one distance per measurement and a table look-up per power.

Shadowing is correlated over metres, so successive measurements along a path repeat one error
rather than bring new evidence. Each measurement is weighted by one over the number of
measurements in its square of side ``INDEPENDENT_SPACING_M`` (``independence_weights``): a
square counts about once, so that the likelihood ratio and the standard deviations do not
claim the certainty of thousands of independent reports.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from cloud_service.no_jammer_belief import SinrBelief
from cloud_service.report_likelihood import ReportTables
from planning.compiled import chosen_planner, compiled_module
from shared.radio import RadioModel
from shared.scenario import Scenario

INDEPENDENT_SPACING_M = 3.0
_RATIO_STEP_DB = 0.1  # resolution of the per-measurement likelihood tables over r
# Below -30 dB the jammer moves the SINR by under 0.005 dB; at +30 dB it has cut it by 30 dB,
# which leaves nothing but level 0. Beyond these the likelihood no longer changes with r.
_RATIO_RANGE_DB = (-30.0, 30.0)
# Hypotheses x measurements per vectorized block: its temporaries stay near the CPU cache.
_BLOCK_ELEMENTS = 2**20


class Reports(NamedTuple):
    """The uploads a fit reads: where each was taken (n, 2), its level (n,) and its SINR (n,),
    NaN where only the level was reported; reported SINRs come in steps of ``step_db``."""

    xy: np.ndarray
    levels: np.ndarray
    sinr_db: np.ndarray
    step_db: float | None

    @classmethod
    def of(cls, scenario: Scenario, xy: np.ndarray, levels: np.ndarray,
           reported_db: np.ndarray | None = None) -> Reports:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        levels = np.asarray(levels, dtype=np.int64).reshape(-1)
        sinr_db = (np.full(len(levels), np.nan) if reported_db is None
                   else np.asarray(reported_db, dtype=np.float64).reshape(-1))
        return cls(xy, levels, sinr_db,
                   scenario.uav.report_step_db if np.isfinite(sinr_db).any() else None)

    def take(self, rows: np.ndarray) -> Reports:
        return Reports(self.xy[rows], self.levels[rows], self.sinr_db[rows], self.step_db)


def independence_weights(xy: np.ndarray, spacing_m: float) -> np.ndarray:
    """One over the number of measurements in each one's square of side ``spacing_m``."""
    cells = np.floor(xy / spacing_m).astype(np.int64)
    _, cell_of, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    return 1.0 / counts[cell_of.reshape(-1)]


class JammerEvidence:
    """The measurements, reduced to what a jammer hypothesis needs: each one's weighted
    log-likelihood tabulated over r, the jammer's power over the ideal GBS interference plus
    noise (dB). The tables span ``_RATIO_RANGE_DB`` widened by ``power_span_db`` on both
    sides, so that one call's powers, up to that span apart, read them without clipping."""

    def __init__(
        self, radio: RadioModel, jammer_height_m: float, reports: Reports, weights: np.ndarray,
        belief: SinrBelief, report_sigma_db: float, outlier_share: float, power_span_db: float,
        placed: Sequence[tuple[np.ndarray, float]] = (),
    ):
        """``placed``: jammers taken as known, each (position (2,), effective power dBW):
        the evidence is then for one jammer more, against those alone (``no_jammer`` is
        their log-likelihood), as their interference adds to the new one's in Eq. (3)."""
        xy, levels, reported_db = reports.xy, reports.levels, reports.sinr_db
        self.xy = xy  # where the jammer's path loss reads them (``in_frame``)
        self.report_sigma_db = report_sigma_db
        _, _, co_channel = radio.serving(radio.gbs_received_power(xy))
        self.interference_db = 10.0 * np.log10(radio.noise_w + co_channel)
        self.gap_m = radio.altitude_m - jammer_height_m
        self.slope_db = 5.0 * (radio.alpha + 1.0)  # I_J ~ slant_sq ** -((alpha + 1) / 2)
        self.ratio_low_db = _RATIO_RANGE_DB[0] - power_span_db
        ratios_db = np.arange(self.ratio_low_db, _RATIO_RANGE_DB[1] + power_span_db,
                              _RATIO_STEP_DB)
        # 1 + the placed jammers' power over the interference plus noise, per measurement;
        # without any, one loss curve serves every measurement.
        base = 1.0 if not placed else 1.0 + np.sum(
            [10.0 ** (self.ratios_db(position[None], power_dbw)[0] / 10.0)
             for position, power_dbw in placed], axis=0)[:, None]
        loss_db = 10.0 * np.log10(base + 10.0 ** (ratios_db / 10.0))  # SINR lost to jamming
        tables = ReportTables(radio.level_edges_db, np.hypot(belief.sd_db, report_sigma_db),
                              outlier_share, reports.step_db)
        rows = np.arange(len(xy))
        self.table = tables.weighted_tables(belief.mean_db, loss_db, levels, reported_db,
                                            weights).ravel()
        self.effective_count = float(weights.sum())  # reports that count as independent
        self.ratio_count = len(ratios_db)
        self.row_start = (rows * self.ratio_count).astype(np.int32)
        placed_loss_db = 10.0 * np.log10(np.reshape(base, -1))
        self.no_jammer = float(weights @ tables.log_probability(belief.mean_db - placed_loss_db,
                                                                levels, rows, reported_db))

    def in_frame(self, frame_xy: np.ndarray) -> JammerEvidence:
        """The same reports with the jammer's path loss read at ``frame_xy`` (n, 2), one per
        measurement, while the ground stations' interference stays that of their places: a
        jammer driving at v, at p at time T, weighs on a report taken at time t as a still
        one at p would on a report taken at its place less v (t - T) (``driving_jammer``).
        The tables do not depend on where the jammer stands, so every frame shares them."""
        moved = copy.copy(self)
        moved.xy = np.asarray(frame_xy, dtype=np.float64).reshape(self.xy.shape)
        return moved

    def ratios_db(self, positions: np.ndarray, power_dbw: float | np.ndarray) -> np.ndarray:
        """r of a jammer at each of ``positions`` (H, 2) with effective power ``power_dbw``
        at every measurement: (H, n) dB."""
        dx = positions[:, 0, None] - self.xy[:, 0]
        dy = positions[:, 1, None] - self.xy[:, 1]
        slant_sq = dx * dx + dy * dy + self.gap_m**2
        return (np.asarray(power_dbw)[..., None] + 10.0 * math.log10(self.gap_m)
                - self.slope_db * np.log10(slant_sq) - self.interference_db)

    def log_likelihood_ratios(self, positions: np.ndarray, powers_dbw: np.ndarray) -> np.ndarray:
        """Log-likelihood of a jammer at each of ``positions`` (H, 2) with each effective
        power ``powers_dbw`` (P,), less that of no jammer: shape (H, P). Powers are read to
        the table's step and may span at most the ``power_span_db`` the tables were made for.
        Beyond the tables the likelihood no longer changes with r, so clipping the entries
        is exact. Summed by the compiled core unless ``JAMNAV_PLANNER=reference``, whose
        numpy gather is the reference."""
        power_steps = np.rint((powers_dbw - powers_dbw.min()) / _RATIO_STEP_DB).astype(np.int32)
        lowest_at = self.ratio_low_db - powers_dbw.min()  # path gain read at column 0
        last_first = self.ratio_count - 1 - int(power_steps.max())
        out = np.zeros((len(positions), len(powers_dbw)))
        if chosen_planner() == "compiled":
            compiled_module("_evidence").add_hypothesis_entries(
                np.ascontiguousarray(positions, dtype=np.float64), np.ascontiguousarray(self.xy),
                10.0 * math.log10(self.gap_m) - self.interference_db - lowest_at,
                self.slope_db, self.gap_m**2, _RATIO_STEP_DB, self.ratio_count, last_first,
                power_steps, self.table, out)
            return out - self.no_jammer
        # The gather's temporaries hold every power: blocks of hypotheses keep them small.
        per_block = max(1, _BLOCK_ELEMENTS // (len(powers_dbw) * len(self.xy)))
        for start in range(0, len(positions), per_block):
            block = positions[start : start + per_block]
            first_entry = np.clip(
                np.rint((self.ratios_db(block, 0.0) - lowest_at) / _RATIO_STEP_DB), 0,
                last_first).astype(np.int32) + self.row_start
            out[start : start + len(block)] = self.table[
                first_entry[:, None, :] + power_steps[:, None]].sum(axis=-1)
        return out - self.no_jammer
