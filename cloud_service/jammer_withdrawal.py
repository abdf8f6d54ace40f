"""Whether the jammer behind a corrected map is still there: the test that withdraws a map
corrected for a jammer the reports show gone or moved (``WithdrawalTest``), the confirmation a
change's first corrected map waits for (``WithdrawalTest.confirms``), what each report
weighs for both (``withdrawal_evidence``), and the test of each jammer of a set
(``MemberWithdrawals``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from cloud_service.estimated_jammer import (
    NO_JAMMER,
    JammerEstimate,
    JammerHypotheses,
    estimated_set,
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
                        jammer: JammerEstimate | JammerHypotheses, shadowing_sigma_db: float,
                        rest: JammerEstimate = NO_JAMMER) -> WithdrawalEvidence:
    """The reports of ``data``, taken at ``xy``, placed inside the area (beyond its edge the
    map is no evidence), weighed by ``models`` with ``jammer`` and with ``rest`` only (by
    default no jammer; a set's others, to weigh one of its jammers). An estimate is weighed
    with its uncertainty (``posterior_hypotheses``): taken as exact, a still jammer's rough
    first estimate was withdrawn by one UAV's run along the zone edge it misplaced
    (BENCHMARKS.md, "A jammer that comes and goes")."""
    scenario = models.scenario
    kept = np.flatnonzero(np.isfinite(xy).all(axis=1) & ~scenario.area.outside(xy))
    levels, xy, reported_db = data.levels[kept], xy[kept], data.sinr_db[kept]
    if isinstance(jammer, JammerEstimate):
        jammer = posterior_hypotheses(jammer)
    rest = posterior_hypotheses(rest) if rest.present else rest
    with_jammer = models.model_probability(levels, xy, jammer, shadowing_sigma_db)
    without = models.model_probability(levels, xy, rest, shadowing_sigma_db)
    floors = np.full(len(kept), scenario.online_map.probability_floor)
    reported = np.isfinite(reported_db)
    if reported.any():  # a dB report weighs by its SINR
        here = xy[reported]
        belief = sinr_beliefs(RadioModel(scenario, shadowed=False), here,
                              models.no_jammer_probabilities(here), shadowing_sigma_db or None,
                              models.reference.at(here))
        with_jammer[reported], without[reported] = (
            sinr_report_probabilities(scenario, here, reported_db[reported], model, belief)
            for model in (jammer, rest))
        floors[reported] = 0.0
    return WithdrawalEvidence(with_jammer, without, data.times[kept], floors)


class JammerGone(NamedTuple):
    """One jammer of a set the reports show gone (``MemberWithdrawals``)."""

    jammer: JammerEstimate
    rest: JammerEstimate  # the set without it
    check: WithdrawalCheck


class MemberWithdrawals:
    """Whether each jammer of an estimated set is still there: one ``WithdrawalTest`` a
    jammer, weighing the set against the set without it, so that one jammer switched off is
    withdrawn alone while the others' reports keep the set's test (against no jammer) down.
    None for one jammer, hypotheses or no correction: the set's own test is theirs."""

    def __init__(self, scenario: Scenario,
                 correction: JammerEstimate | JammerHypotheses | None = None):
        self.members = (correction.members if isinstance(correction, JammerEstimate)
                        else ())
        self.set = correction
        self.tests = ([WithdrawalTest.of(scenario) for _ in self.members]
                      if len(self.members) > 1 else [])

    def update(self, models: ReportModels, data: MeasurementBatch, xy: np.ndarray,
               shadowing_sigma_db: float) -> JammerGone | None:
        """Feed new reports to each jammer's test; the first jammer they show gone."""
        for index, test in enumerate(self.tests):
            rest = estimated_set([*self.members[:index], *self.members[index + 1:]])
            check = test.update(*withdrawal_evidence(models, data, xy, self.set,
                                                     shadowing_sigma_db, rest))
            if check is not None and check.fired:
                return JammerGone(self.members[index], rest, check)
        return None


@dataclass
class CorrectionWatch:
    """The jammer the map in service was corrected for (a converged estimate, a set of them,
    or a provisional map's hypotheses; None: an uncorrected map), the shadowing fitted beside
    it, and the tests that watch whether it is still there: the whole against no jammer, and
    each jammer of a set against the others (``MemberWithdrawals``)."""

    jammer: JammerEstimate | JammerHypotheses | None
    sigma_db: float
    whole: WithdrawalTest
    members: MemberWithdrawals

    @classmethod
    def of(cls, scenario: Scenario, jammer: JammerEstimate | JammerHypotheses | None = None,
           sigma_db: float = 0.0, whole: WithdrawalTest | None = None) -> CorrectionWatch:
        """Watch ``jammer`` afresh, or go on with the ``whole`` test a fit already fed."""
        return cls(jammer, sigma_db, whole or WithdrawalTest.of(scenario),
                   MemberWithdrawals(scenario, jammer))

    def weigh(self, models: ReportModels, data: MeasurementBatch, xy: np.ndarray,
              members_may_go: bool) -> JammerGone | WithdrawalCheck | None:
        """Feed new reports to the tests: the first jammer of a set they show gone, while
        ``members_may_go``; else the check that withdraws the whole, once it fired; else
        None."""
        gone = self.members.update(models, data, xy, self.sigma_db)
        if gone is not None and members_may_go:
            return gone
        check = self.whole.update(*withdrawal_evidence(models, data, xy, self.jammer,
                                                       self.sigma_db))
        return check if check is not None and check.fired else None
