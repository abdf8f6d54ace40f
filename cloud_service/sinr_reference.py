"""What UAVs measured with no jammer, cell by cell: the cloud's reference for dB reports.

Where receivers report the SINR itself (``uav.report = "db"``), the no-jammer map learned from
a survey says little of it: a level classifier, whose level bands are 0.8 dB to tens of dB
wide, and in icc2021-shadowed wrong on 16 % of the area. What UAVs measured at the same spot
before is sharper: the mean of k reports in a cell of ``online_map.reference_cell_m`` knows
the no-jammer SINR there to sqrt(s^2 / k + r^2), s^2 the spread of reports within a cell
(the receiver's noise and the field's roughness across the cell) and r^2 = s^2 less the
receiver's datasheet noise, the roughness alone.

A report enters only once it is ``online_map.reference_delay_s`` of flight old with no change
detected meanwhile and no jammer believed (the survey map in service): a jammer that appears
is then caught by the detector before its reports enter, and those are dropped. A jammer
present from the start and never detected is part of the reference, as it is of the map.

Against this reference the detector weighs a dB report by a one-sided test of a loss of
``online_map.detection_shift_db`` (``shift_evidence``), and the jammer estimate reads each
report's no-jammer SINR from it where it has one.

A restarted cloud rebuilds the reference from its replay memory by the same ``offer`` and
``commit`` (``OnlineSinrMapper._rebuild_reference``), with what the restart knows of when a
jammer was believed: the start of every change that a corrected map it published answered,
kept on that map's card (``refining_since``; the map resumed may be one). Every stored dB
report taken before the earliest of those starts is offered, every stored dB report if no card
tells of one, and committed as of the newest stored report: those ``reference_delay_s`` older
than it enter at once, the younger wait as live ones would. So on a map corrected for a jammer
only the reports from before its change enter; on an uncorrected one, those from before any
change its predecessors answered. What no card keeps, the rebuild cannot leave out: a change
answered by a provisional map or by the DNN alone, or not answered yet when the cloud stopped,
leaves no start behind, and the reports taken since it enter. Reports taken after a jammer's
withdrawal, which entered live, are left out with those taken while it was believed: the rule
reads no more of the cards than when changes began, and those cells refill as UAVs fly them.
Nor can the rule tell when a jammer began that the detector caught late: the reports its zone
gave the reference before, already jammed, would vouch against it, and the reports under it
would look like no loss at all, withdrawing every map corrected for it. So whenever a map
corrected for a jammer goes into service, and after a restart onto one, the reports that hold
its loss leave the reference (``discard_jammed``, judged by the mapper): where it takes
``detection_shift_db`` or more off the SINR, those nearer the survey map's no-jammer SINR less
that loss than the SINR itself. Those cells refill once no jammer is believed.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from cloud_service.no_jammer_belief import SinrBelief
from cloud_service.report_likelihood import OUTLIER_SHARE
from shared.scenario import Scenario

# Reports within a cell, at least, before its spread counts towards the pooled one.
_SPREAD_MIN_REPORTS = 2


class SinrReference:
    """Sums of the no-jammer dB reports in each cell of the area, and the reports that wait
    their turn to enter (``offer``, ``commit``, ``discard_since``)."""

    def __init__(self, scenario: Scenario):
        area, online = scenario.area, scenario.online_map
        self.cell_m = online.reference_cell_m
        self.delay_s = online.reference_delay_s
        self.noise_db = scenario.uav.measurement_noise_db
        self.detection_shift_db = online.detection_shift_db
        self.origin = np.array([area.x_min, area.y_min])
        self.shape = (math.ceil((area.y_max - area.y_min) / self.cell_m),
                      math.ceil((area.x_max - area.x_min) / self.cell_m))
        self.sums = np.zeros(self.shape)
        self.squares = np.zeros(self.shape)
        self.counts = np.zeros(self.shape, dtype=np.int64)
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def offer(self, xy: np.ndarray, sinr_db: np.ndarray, times: np.ndarray) -> None:
        """Reports taken with no jammer believed, to enter once ``commit`` finds them old
        enough; those without an SINR or outside the area are left out."""
        cells, inside = self._cells(xy)
        keep = inside & np.isfinite(sinr_db)
        if keep.any():
            self._pending.append((cells[keep], np.asarray(sinr_db)[keep],
                                  np.asarray(times, dtype=np.float64)[keep]))

    def commit(self, now: float) -> None:
        """Enter the pending reports taken at least ``delay_s`` before ``now``."""
        waiting = []
        for cells, sinr_db, times in self._pending:
            due = times <= now - self.delay_s
            rows, cols = cells[due].T
            np.add.at(self.sums, (rows, cols), sinr_db[due])
            np.add.at(self.squares, (rows, cols), sinr_db[due] ** 2)
            np.add.at(self.counts, (rows, cols), 1)
            if not due.all():
                waiting.append((cells[~due], sinr_db[~due], times[~due]))
        self._pending = waiting

    def remember(self, xy: np.ndarray, sinr_db: np.ndarray, times: np.ndarray) -> None:
        """``offer`` reports, then ``commit`` what is old enough by the latest of them."""
        self.offer(xy, sinr_db, times)
        self.commit(float(np.max(times)))

    def discard_since(self, start: float) -> None:
        """Drop the pending reports taken at or after ``start``: a change began then."""
        self._pending = [(cells[times < start], sinr_db[times < start], times[times < start])
                         for cells, sinr_db, times in self._pending]

    def discard_jammed(self, jammed: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
        """Drop what ``jammed(xy, sinr_db)`` (points (n, 2), the SINR measured there (n,))
        says a jammer had lowered: each cell's reports, judged by their mean at the cell's
        centre, and each report waiting to enter, by its own SINR at its cell's centre."""
        rows, cols = np.indices(self.shape)
        centres = self.origin + (np.stack([cols, rows], axis=-1) + 0.5) * self.cell_m
        held = self.counts > 0
        if held.any():
            cells = np.zeros(self.shape, dtype=bool)
            cells[held] = jammed(centres[held], self.sums[held] / self.counts[held])
            self.sums[cells] = self.squares[cells] = 0.0
            self.counts[cells] = 0
        if self._pending:  # judged at once, kept in the order they were offered
            pending_cells, sinr_db, times = (np.concatenate(part)
                                             for part in zip(*self._pending, strict=True))
            keep = ~jammed(centres[pending_cells[:, 0], pending_cells[:, 1]], sinr_db)
            self._pending = [(pending_cells[keep], sinr_db[keep], times[keep])]

    @property
    def reports(self) -> int:
        return int(self.counts.sum())

    def spread_db(self) -> float:
        """The pooled sd of reports about their cell's mean; the receiver's datasheet noise
        until cells hold enough reports to say."""
        counted = self.counts >= _SPREAD_MIN_REPORTS
        if not counted.any():
            return self.noise_db
        k = self.counts[counted]
        deviations = self.squares[counted] - self.sums[counted] ** 2 / k
        return math.sqrt(max(float(deviations.sum()) / float((k - 1).sum()), 0.0))

    def at(self, xy: np.ndarray) -> SinrBelief:
        """The no-jammer SINR at points ``xy`` (n, 2) by the reports of their cells: mean and
        sd, NaN where a cell holds none (or the point lies outside the area)."""
        cells, inside = self._cells(xy)
        rows, cols = cells.T
        count = np.where(inside, self.counts[rows, cols], 0)
        spread = self.spread_db()
        roughness_sq = max(spread**2 - self.noise_db**2, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            mean = np.where(count > 0, self.sums[rows, cols] / count, np.nan)
            sd = np.where(count > 0, np.sqrt(spread**2 / count + roughness_sq), np.nan)
        return SinrBelief(mean, sd)

    def shift_evidence_at(self, xy: np.ndarray, reported_db: np.ndarray) -> np.ndarray:
        """What each dB report ``reported_db`` taken at ``xy`` weighs for a loss of
        ``online_map.detection_shift_db`` against none, by this reference
        (``shift_evidence``)."""
        return shift_evidence(self.at(xy), reported_db, self.noise_db, self.detection_shift_db)

    def _cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's cell (row, col) and whether it lies inside the area."""
        cells = np.floor((np.asarray(xy, dtype=np.float64).reshape(-1, 2) - self.origin)
                         / self.cell_m)[:, ::-1]
        with np.errstate(invalid="ignore"):
            inside = np.isfinite(cells).all(axis=1) & (cells >= 0).all(axis=1) & (
                cells < self.shape).all(axis=1)
        return np.where(inside[:, None], cells, 0).astype(np.int64), inside


def shift_evidence(reference: SinrBelief, reported_db: np.ndarray, noise_db: float,
                   shift_db: float) -> np.ndarray:
    """Nats each dB report weighs for its no-jammer SINR having dropped by ``shift_db``
    against none: log N(v; m - shift, sd) / N(v; m, sd), sd^2 the reference's spread plus
    the receiver's ``noise_db``. At most log(1 / OUTLIER_SHARE), as one report in a hundred
    may contradict any model; NaN where the report or the reference has no SINR."""
    variance = reference.sd_db**2 + noise_db**2
    evidence = shift_db * (reference.mean_db - reported_db - shift_db / 2.0) / variance
    return np.minimum(evidence, -math.log(OUTLIER_SHARE))
