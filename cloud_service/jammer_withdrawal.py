"""Whether the jammer behind a corrected map is still there: the test that withdraws a map
corrected for a jammer the reports show gone or moved (``WithdrawalTest``), the confirmation a
change's first corrected map waits for (``WithdrawalTest.confirms``), and what each report
weighs for both (``withdrawal_evidence``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from cloud_service.estimated_jammer import (
    NO_JAMMER,
    JammerEstimate,
    JammerHypotheses,
    posterior_hypotheses,
)
from cloud_service.map_correction import sinr_report_probabilities
from cloud_service.no_jammer_belief import sinr_beliefs
from cloud_service.report_models import ReportModels
from shared.measurements import MeasurementBatch
from shared.radio import RadioModel
from shared.scenario import Scenario


class WithdrawalCheck(NamedTuple):
    t: float  # time of the last report fed
    statistic: float  # nats against the jammer behind the map, after those reports
    since: float | None  # when the run of evidence that the statistic holds began
    reports: int  # reports weighed against that jammer so far
    fired: bool


@dataclass
class WithdrawalTest:
    """Whether the jammer behind the map in service is still there.

    Rule, a CUSUM over every UAV's reports in the order taken: S <- max(0, S + log(q / p)),
    with p and q the report model's probability of the reported level with that jammer and
    without any (``ReportModels.model_probability``, the model the detector weighs reports
    by), each at least ``floor``. A report where the jammer changes nothing weighs
    nothing; one where it should have lowered the level and did not pushes S up; one it
    explains pulls S down. The jammer is taken for gone (or moved) when S reaches
    ``threshold`` (``online_map.withdrawal_threshold``, measured there).

    Why pooled over the UAVs, unlike the detector: the evidence lies only in the zone the
    jammer is believed to cover, which the UAVs cross by turns; what one UAV's reports there
    show of a still jammer answers another's run along a zone edge the estimate misplaced.
    """

    threshold: float
    floor: float
    statistic: float = 0.0
    since: float | None = None
    reports: int = 0

    @classmethod
    def of(cls, scenario: Scenario) -> WithdrawalTest:
        online = scenario.online_map
        return cls(online.withdrawal_threshold, online.probability_floor)

    def update(self, with_jammer: np.ndarray, without: np.ndarray, times: np.ndarray,
               floors: np.ndarray | None = None) -> WithdrawalCheck | None:
        """Feed new reports (their probability with the jammer and without, when taken, and
        the floor of each, ``evidence``); the state after them, ``fired`` at the first report
        that takes S to the threshold; None when given nothing."""
        if len(times) == 0:
            return None
        for step, t in zip(self.evidence(with_jammer, without, floors).tolist(),
                           np.asarray(times).tolist(), strict=True):
            if self.statistic == 0.0:
                self.since = t
            self.statistic = max(0.0, self.statistic + step)
            self.reports += 1
            if self.statistic >= self.threshold:
                return WithdrawalCheck(t, self.statistic, self.since, self.reports, True)
        return WithdrawalCheck(float(times[-1]), self.statistic, self.since, self.reports,
                               False)

    def evidence(self, with_jammer: np.ndarray, without: np.ndarray,
                 floors: np.ndarray | None = None) -> np.ndarray:
        """Nats each report weighs against the jammer: log(q / p), both at least ``floor``
        (or each report's of ``floors``: a dB report's probability is of a half-dB interval,
        its outliers already counted, ``sinr_report_probabilities``)."""
        floor = self.floor if floors is None else floors
        return (np.log(np.maximum(without, floor)) - np.log(np.maximum(with_jammer, floor)))

    def confirms(self, evidence: WithdrawalEvidence, since: float, threshold: float) -> bool:
        """Whether the reports of ``evidence`` taken after ``since`` favour the jammer by
        ``threshold`` nats at least. A jammer seen only in the reports that raised a change (a
        blip, switched off since) is fitted by a still jammer placed where no later report
        could contradict it; such a phantom must never be served, so a change's first
        corrected map waits for this (``online_map.confirmation_threshold``)."""
        support = -self.evidence(evidence.with_jammer, evidence.without, evidence.floors)[
            evidence.times > since]
        return float(support.sum()) >= threshold


class WithdrawalEvidence(NamedTuple):
    """Reports as ``WithdrawalTest.update`` weighs them."""

    with_jammer: np.ndarray  # each one's probability with the jammer
    without: np.ndarray  # ... with none
    times: np.ndarray  # when each was taken
    floors: np.ndarray  # the least probability each may have (``WithdrawalTest.evidence``)


def withdrawal_evidence(models: ReportModels, data: MeasurementBatch, xy: np.ndarray,
                        jammer: JammerEstimate | JammerHypotheses,
                        shadowing_sigma_db: float) -> WithdrawalEvidence:
    """The reports of ``data``, taken at ``xy``, placed inside the area (beyond its edge the
    map is no evidence), weighed by ``models`` with ``jammer`` and without. An estimate is
    weighed with its uncertainty (``posterior_hypotheses``): taken as exact, a still jammer's
    rough first estimate was withdrawn by one UAV's run along the zone edge it misplaced
    (BENCHMARKS.md, "A jammer that comes and goes")."""
    scenario = models.scenario
    kept = np.flatnonzero(np.isfinite(xy).all(axis=1) & ~scenario.area.outside(xy))
    levels, xy, reported_db = data.levels[kept], xy[kept], data.sinr_db[kept]
    if isinstance(jammer, JammerEstimate):
        jammer = posterior_hypotheses(jammer)
    with_jammer = models.model_probability(levels, xy, jammer, shadowing_sigma_db)
    without = models.model_probability(levels, xy, None, shadowing_sigma_db)
    floors = np.full(len(kept), scenario.online_map.probability_floor)
    reported = np.isfinite(reported_db)
    if reported.any():  # a dB report weighs by its SINR
        here = xy[reported]
        belief = sinr_beliefs(RadioModel(scenario, shadowed=False), here,
                              models.no_jammer_probabilities(here), shadowing_sigma_db or None,
                              models.reference.at(here))
        with_jammer[reported], without[reported] = (
            sinr_report_probabilities(scenario, here, reported_db[reported], model, belief)
            for model in (jammer, NO_JAMMER))
        floors[reported] = 0.0
    return WithdrawalEvidence(with_jammer, without, data.times[kept], floors)
