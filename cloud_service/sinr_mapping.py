"""Online SINR mapping in the cloud (paper Sec. III-C): train, watch, detect, adapt, publish.

- ``train_sinr_map`` (in ``cloud_service.sinr_training``, apart as it needs torch): supervised
  training of the SINR-mapping network on measurements (mini-batches of 200, Adam lr 5e-3,
  L2 1e-4: the paper's values).
- ``ChangeDetector``: the rule that declares a jammer change when one UAV's uploads keep
  contradicting the map.
- ``OnlineSinrMapper``: memory + detector + jammer estimate + DNN refits + publication, with
  no transport of its own, so the bus shell around it stays thin.

K_n matters. The figures quoted here are for K_n = 12 (every GBS of icc2021). With K_n = 4
the network of the paper's size tops out near 96 % without a jammer and near 90 % with one
(more data and epochs did not help): the interference, and the jammer's hole, depend on
where the UAV is in the whole layout, which it must then infer from four relative positions
whose order reshuffles at every cell edge. With every GBS in view the position is explicit.
Measured without a jammer (30,000 uniform measurements, 60 epochs): K_n = 4: 96.0 %,
5: 97.6 %, 6: 98.5 %, 8: 99.4 %, 12: 99.4 %. After a Table I change, warm-started on 3,000
uniform measurements: ~89-92 % with K_n = 4, ~96-97 % with 8, ~98 % with 12.
"""

from __future__ import annotations

import threading
import time as wall
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from cloud_service.estimated_jammer import (
    NO_JAMMER,
    JammerEstimate,
    JammerHypotheses,
    posterior_hypotheses,
)
from cloud_service.jammer_estimation import locate_jammer
from cloud_service.map_correction import (
    corrected_level_probabilities,
    corrected_levels,
    ideal_level_probabilities,
    ideal_model_spread_db,
    sinr_report_probabilities,
)
from cloud_service.no_jammer_belief import fit_shadowing_sigma, sigma_fit_sample, sinr_beliefs
from cloud_service.report_likelihood import REPORT_SIGMA_DB
from cloud_service.simulated_measurements import uniform_positions
from cloud_service.sinr_memory import SinrMemory, Uploads
from cloud_service.sinr_reference import SinrReference, shift_evidence
from cloud_service.upload_positions import positions_from_features
from planning.maps import MAP_SPACING_M, LevelRaster, sinr_network_raster
from planning.networks import SinrMapNetwork, predict_probabilities, sha256, to_bytes
from shared.measurements import MeasurementBatch, scenario_features
from shared.radio import RadioModel
from shared.scenario import Scenario

TARGET_ACCURACY = 0.97  # the accuracy bar the online map is held to on fresh measurements


# -- change detection ---------------------------------------------------------------------------
class DetectorCheck(NamedTuple):
    t: float  # time of the last measurement fed
    source: str  # the UAV whose statistic is the highest
    statistic: float  # that UAV's CUSUM after this batch
    fired: bool


@dataclass
class ChangeDetector:
    """Declares a jammer change when one UAV's reports keep contradicting the map.

    Rule, a CUSUM per UAV over its reports in the order taken: S <- max(0, S + log(u / p)),
    with p the map's own probability of the reported level (its softmax; at least ``floor``)
    and u = 1 / levels, the probability a map that knows nothing would give. A report the
    map expected (p > u) pulls S down; one it ruled out pushes it up. A change is declared
    when one UAV's S reaches ``threshold``; the time its excursion began (S last at 0) is
    the estimate of when the change happened.

    Why per UAV: a jammed zone is local. With four UAVs only one may cross it, and pooled
    its reports would be diluted by the others'. Why the map's probabilities: where the map
    is unsure (a cell edge, a patch of shadowing it could not learn) a contradiction is weak
    evidence, and where it is sure it is strong. The map's errors are not independent from
    one report to the next (reports lie 0.25 m apart, shadowing decorrelates over 10 m), so
    the threshold must outlast the runs of contradictions a still jammer produces: it is a
    scenario value (``online_map.change_threshold``, measured there). After firing, the
    detector is disarmed until ``reset``.
    """

    levels: int
    threshold: float
    floor: float
    armed: bool = True
    change_start: float | None = None
    _statistic: dict[str, float] = field(default_factory=dict, repr=False)
    _excursion_start: dict[str, float] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, scenario: Scenario) -> ChangeDetector:
        online = scenario.online_map
        return cls(scenario.channel.level_count, online.change_threshold,
                   online.probability_floor)

    def reset(self) -> None:
        """A new map is in service: statistics cleared, detector armed."""
        self.armed = True
        self.change_start = None
        self._statistic.clear()
        self._excursion_start.clear()

    def update(self, probability: np.ndarray, sources: list[str], times: np.ndarray,
               evidence_db: np.ndarray | None = None) -> DetectorCheck | None:
        """Feed the new uploads (the map's probability of each reported level, who took it,
        when, and where finite the nats a dB report weighs instead, ``shift_evidence``);
        returns the state after them (``fired`` set when a change is declared), None when
        disarmed or given nothing."""
        if not self.armed or len(probability) == 0:
            return None
        evidence = np.log(1.0 / self.levels) - np.log(np.maximum(probability, self.floor))
        if evidence_db is not None:
            evidence = np.where(np.isfinite(evidence_db), evidence_db, evidence)
        for step, source, t in zip(evidence.tolist(), sources, np.asarray(times).tolist(),
                                   strict=True):
            statistic = self._statistic.get(source, 0.0)
            if statistic == 0.0:
                self._excursion_start[source] = t
            statistic = max(0.0, statistic + step)
            self._statistic[source] = statistic
            if statistic >= self.threshold:
                self.armed = False
                self.change_start = self._excursion_start[source]
                return DetectorCheck(t, source, statistic, True)
        source = max(self._statistic, key=self._statistic.get)
        return DetectorCheck(float(times[-1]), source, self._statistic[source], False)


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
    without any (``OnlineSinrMapper.model_probability``, the model the detector weighs
    reports by), each at least ``floor``. A report where the jammer changes nothing weighs
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


# -- the online mapper --------------------------------------------------------------------------
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


@dataclass(frozen=True)
class RetrainConfig:
    """How the mapper answers a detected change (values measured: bench_adaptation.py)."""

    # Post-change measurements before the first estimate of the jammer is tried, and between
    # tries while none converges (four UAVs upload about 40 a second): at least
    # ``estimate_every`` more, and ``estimate_growth`` times as many as at the last try, so
    # that a jammer the data cannot place (a fit costs 0.1-0.9 s) is tried ~20 times up to
    # ``min_samples``, not at every upload.
    estimate_from: int = 40
    estimate_every: int = 40
    estimate_growth: float = 1.25
    # The corrected map is refined (estimate and DNN again, on all post-change data) every
    # ``refine_every`` post-change measurements until ``settle_after``; then the map stands
    # and the detector watches it. Measured with 20 UAVs after a Table I change: settling at
    # 2,000 left maps at 96.7-98 % (the estimate still 3-5 m off), at 4,000 at 98.4-98.6 %.
    refine_every: int = 600
    settle_after: int = 4000
    # Without a converged estimate, the DNN alone retrains once this many post-change
    # measurements are in, and the estimate has been tried ``min_tries`` times: four UAVs
    # bring 4,000 in after ~20 tries, 256 in a second, after two (the city: that map went out
    # unsettled by any estimate, and its errors raised a false change a second later).
    min_samples: int = 4000
    min_tries: int = 8
    # Mini-batches of 200 (~0.8 s on one core) per fit.
    steps: int = 1000
    # ... per provisional map: a stopgap, out in a fraction of the time, that the next try
    # replaces.
    provisional_steps: int = 250
    max_seconds: float | None = 2.5  # a slow machine still publishes within ~3 s of the data
    # No early stop: the run is short, and stopping at a high learning rate (the decay is
    # scheduled over ``steps``) would leave the class boundaries unsettled.
    target_accuracy: float | None = None
    holdout: float = 0.2


class IngestReport(NamedTuple):
    accepted: int
    duplicates: int
    check: DetectorCheck | None


RECENT_KEPT = 500  # uploads over which the map in service is scored for status
CLOSE_WAIT_S = 5.0  # how long a closing mapper waits for the work under way


class OnlineSinrMapper:
    """The cloud's online SINR map: ingest uploads, watch the map, adapt it on a change.

    ``ingest`` stores a batch in the memory D_w and feeds the detector how probable the map
    found each report. Once a change is declared (its start estimated by the detector):
    1. from ``retrain.estimate_from`` post-change measurements on, the jammer is estimated
       from them (position, power, uncertainty; ``jammer_estimation``); an estimate that
       does not converge is never published and is tried again with more data. Meanwhile,
       if the uploads show a jammer that they cannot place yet, a provisional map is fitted
       and published (no estimate with it): the no-jammer map corrected by every place and
       power the jammer may have, each in proportion to its probability
       (``jammer_hypotheses``), changed only where the survey map's level became improbable;
    2. the first converged estimate corrects the no-jammer map (``base_network``, learned
       from a survey, or the ideal model where the survey keeps to it:
       ``_no_jammer_probabilities``) into a prior over the whole area; the DNN is fitted to
       the prior plus every post-change upload and published at once, with the estimate;
    3. every ``retrain.refine_every`` further measurements, estimate and fit again, until
       ``retrain.settle_after``; then the detector re-arms on the final map.
    4. from the first corrected map on (an estimate's or a provisional one), every report is
       weighed against the jammer it was corrected for (``WithdrawalTest``; at a fit, the
       post-change reports it was fitted on first). Once they show that jammer gone or
       moved, it is withdrawn (``estimate_withdrawn``): the survey map is published again,
       the handling of the change ends and the detector re-arms on the survey map, so a
       jammer that stands elsewhere is detected and estimated afresh from reports taken
       after the withdrawal. A corrected map already contradicted by the reports it was
       fitted on is not published.
    Without any converged estimate, the DNN alone retrains on ``retrain.min_samples``
    post-change measurements, once the estimate was tried ``retrain.min_tries`` times (the
    paper's path), with the survey map as its prior where the uploads have not been. Work
    runs in a worker thread when ``background`` (``ingest`` never waits), inline otherwise
    (deterministic simulations); each new map calls ``publish(PublishedWeights)``.

    ``clock`` stamps the events: time.time in service, the simulated time in simulations.
    ``estimate``: the jammer estimate behind ``network``, for a cloud that restarts on the map
    it last published (the detector weighs reports by it, see ``report_probability``), and
    ``refining_since`` the start of the change that map was still refining: the refinement
    goes on from the memory, which the restart kept. ``base_accuracy``: the survey map's, for
    its publication when an estimate is withdrawn (``accuracy`` without a ``base_network``).
    """

    def __init__(
        self,
        scenario: Scenario,
        memory: SinrMemory,
        network: SinrMapNetwork,
        accuracy: float,
        *,
        base_network: SinrMapNetwork | None = None,
        publish: Callable[[PublishedWeights], None] | None = None,
        detector: ChangeDetector | None = None,
        retrain: RetrainConfig | None = None,
        clock: Callable[[], float] = wall.time,
        background: bool = True,
        version: int = 0,
        seed: int = 0,
        estimate: JammerEstimate | None = None,
        refining_since: float | None = None,
        base_accuracy: float | None = None,
    ):
        self.scenario = scenario
        self.memory = memory
        self.publish = publish
        self.level_count = scenario.channel.level_count
        self.detector = detector or ChangeDetector.of(scenario)
        self.detector.reset()
        self.retrain = retrain or RetrainConfig()
        self.clock = clock
        self.background = background
        self.events: list[dict[str, Any]] = []
        self.estimate = estimate
        # The jammer the map in service was corrected for: a converged estimate, or the
        # hypotheses of a provisional map; None on an uncorrected map.
        self._correction: JammerEstimate | JammerHypotheses | None = (
            estimate if estimate is not None and estimate.present else None)
        self._estimate_sigma_db = 0.0  # the shadowing fitted beside ``_correction``
        self._withdrawal = WithdrawalTest.of(scenario)
        self.reference = SinrReference(scenario)
        self._network = network
        self._base = base_network or network
        self._base_accuracy = accuracy if base_network is None else base_accuracy
        self._accuracy = accuracy
        self._provisional = False  # whether the map in service is a provisional one
        self._version = version
        self._seed = seed
        self._lock = threading.Lock()
        self._recent = deque(maxlen=RECENT_KEPT)
        self._change: _Change | None = None  # set while a change is being handled
        self._busy = False
        self._worker: threading.Thread | None = None
        # Set by ``close``: work under way stops at its next check and publishes nothing.
        self._closing = threading.Event()
        survey_sigma_db = self._shadowing_sigma(self._prior_positions())
        # How far reports may lie from the ideal model where the survey map keeps to it so
        # closely that the model is the better no-jammer map (None elsewhere): a property of
        # the survey map, fitted once (``_no_jammer_probabilities``).
        self._model_spread_db = ideal_model_spread_db(scenario, survey_sigma_db)
        if estimate is not None:
            self._estimate_sigma_db = survey_sigma_db
            if refining_since is not None:  # as if that map had just been fitted
                done = len(memory.since(refining_since))
                self._change = _Change(refining_since, self.clock(), done, estimate, done,
                                       done, confirmed=True)
        # The change whose handling made the correction in service.
        self._correction_change = self._change

    @property
    def version(self) -> int:
        return self._version

    @property
    def accuracy(self) -> float:
        """Held-out accuracy of the network in service."""
        return self._accuracy

    def current_network(self) -> SinrMapNetwork:
        """The network in service. Never trained further in place: a retraining builds a new
        one and swaps it in, so a caller may keep using what it got."""
        return self._network

    def map_raster(
        self, scenario: Scenario | None = None, spacing: float = MAP_SPACING_M
    ) -> LevelRaster:
        return sinr_network_raster(self._network, scenario or self.scenario, spacing)

    def state(self) -> dict[str, Any]:
        """What an operator asks of the mapper: the map in service, how it fares on recent
        uploads, and where the handling of a change stands."""
        with self._lock:
            change = self._change
            recent = float(np.mean(self._recent)) if self._recent else None
            return {"map_version": self._version, "recent_accuracy": recent,
                    "recent_uploads": len(self._recent),
                    "phase": "watching" if change is None else change.phase,
                    "since_change": None if change is None else change.measurements,
                    "provisional": self._provisional, "estimate": self.estimate,
                    # Nats the reports hold against the jammer the map was corrected for.
                    "withdrawal_evidence": None if self._correction is None
                    else self._withdrawal.statistic}

    def ingest(self, uploads: Uploads) -> IngestReport:
        stored, duplicates = self.memory.store(uploads)
        return self.take(stored, duplicates)

    def take(self, stored: MeasurementBatch, duplicates: int = 0) -> IngestReport:
        """Watch and adapt on measurements the memory has just ``stored`` (``ingest`` stores
        them first; the cloud on the lockstep clock stores a round's uploads one by one, then
        has the round taken as one batch)."""
        check = None
        with self._lock:
            withdrawn = None
            if len(stored):
                probabilities = predict_probabilities(self._network, stored.features)
                self._recent.extend((probabilities.argmax(-1) == stored.levels).tolist())
                xy = positions_from_features(self.scenario, stored.features)
                if self._correction is not None:
                    withdrawn = self._weigh_correction(stored, xy)
                # The reports that withdrew a map are not weighed again against the survey map.
                if withdrawn is None and self._change is None:
                    probability = self.report_probability(stored, probabilities, xy)
                    # The map is learned over the area only and extrapolates past its edge,
                    # where a UAV flown out (avoidance pushes some out in a crowd) contradicts
                    # it with nothing changed: 16 UAVs on Table I's 1 W settings raised a false
                    # change in 2 of 4 runs of 100 episodes so. Reports from out there are no
                    # evidence either way.
                    inside = np.flatnonzero(~self.scenario.area.outside(xy))
                    check = self.detector.update(probability[inside],
                                                 [stored.sources[k] for k in inside],
                                                 stored.times[inside],
                                                 self._shift_evidence(stored, xy)[inside])
                    if check is not None and check.fired:
                        self._on_change(check)
                    else:
                        self._remember(stored, xy)
                elif self._change is not None:
                    self._change.measurements += int((stored.times >= self._change.start).sum())
            job = None
            if not self._busy and self._change is not None:  # one worker at a time
                job = self._change.next_job(self.retrain)
                self._busy = job is not None
        if job is not None:
            if self.background:
                self._worker = threading.Thread(target=self._run, args=(job,),
                                                name="sinr-adapt", daemon=True)
                self._worker.start()
            else:
                self._run(job)
        if withdrawn is not None and self.publish is not None:
            self.publish(withdrawn)
        return IngestReport(len(stored), duplicates, check)

    def _remember(self, stored: MeasurementBatch, xy: np.ndarray) -> None:
        """Reports taken while no change is handled enter the no-jammer reference in turn,
        if no jammer is believed either."""
        if self._correction is None:
            self.reference.offer(xy, stored.sinr_db, stored.times)
            self.reference.commit(float(stored.times.max()))

    def _shift_evidence(self, stored: MeasurementBatch, xy: np.ndarray) -> np.ndarray:
        """What each dB report weighs for a jammer against the no-jammer reference
        (``shift_evidence``), while no jammer is believed; NaN elsewhere, and for level
        reports."""
        if self._correction is not None or not np.isfinite(stored.sinr_db).any():
            return np.full(len(stored), np.nan)
        return shift_evidence(self.reference.at(xy), stored.sinr_db,
                              self.scenario.uav.measurement_noise_db,
                              self.scenario.online_map.detection_shift_db)

    @property
    def model_spread_db(self) -> float | None:
        """How far reports may lie from the ideal model where it is the no-jammer map; None
        where the survey map departs from it too far (``_no_jammer_probabilities``)."""
        return self._model_spread_db

    def report_probability(self, stored: MeasurementBatch, probabilities: np.ndarray,
                           xy: np.ndarray | None = None) -> np.ndarray:
        """How probable each stored report was: by the map in service, or by a model that
        expected it more: the ideal model (with the jammer estimate, if any) where the survey
        map says the world keeps to it closely (``ideal_model_spread_db``), and the survey map
        corrected by a jammer estimate, where one stands behind the map.
        A DNN errs along its levels' edges: the survey map of icc2021 is confidently wrong
        there often enough that the detector raised 2 false changes in 30 min of four UAVs'
        flight at a probability floor of 0.002, none when the ideal model vouches for such
        reports; and a DNN fitted to a jammed zone errs along the zone's edge, where the
        lookahead flies its UAVs, so one UAV's reports there contradict it again and again
        (in-process, a false change every 15-25 min of flight with a still jammer). A moved
        or retuned jammer contradicts the models too, so a change still shows.
        ``probabilities``: the map's of every level for each report; ``xy``: where the
        reports were taken (``positions_from_features`` of their features, if not given)."""
        if xy is None:
            xy = positions_from_features(self.scenario, stored.features)
        reported = _of_reported(probabilities, stored.levels)
        if self.estimate is not None and self.estimate.present:
            model = self.model_probability(stored.levels, xy, self.estimate,
                                           self._estimate_sigma_db)
        elif self._model_spread_db is not None:
            model = _of_reported(ideal_level_probabilities(
                self.scenario, xy, None, self._model_spread_db), stored.levels)
        else:
            return reported
        # fmax: a report whose position cannot be recovered has the map's probability only.
        return np.fmax(reported, model)

    def model_probability(self, levels: np.ndarray, xy: np.ndarray,
                          jammer: JammerEstimate | JammerHypotheses | None,
                          shadowing_sigma_db: float) -> np.ndarray:
        """How probable the cloud's models make each reported level (n,), taken at ``xy``
        (n, 2), with ``jammer`` (an estimate, a provisional map's hypotheses, or None: no
        jammer): the no-jammer map corrected by it as a receiver reports
        (``corrected_level_probabilities``, at ``shadowing_sigma_db``), or the ideal model
        with it where the survey map keeps to that model, whichever expected the report
        more. NaN where ``xy`` is."""
        model = _of_reported(corrected_level_probabilities(
            self.scenario, self._no_jammer_probabilities, jammer or NO_JAMMER, xy,
            shadowing_sigma_db=shadowing_sigma_db, report_sigma_db=REPORT_SIGMA_DB), levels)
        if self._model_spread_db is None:
            return model
        return np.fmax(model, _of_reported(ideal_level_probabilities(
            self.scenario, xy, jammer, self._model_spread_db), levels))

    def _withdrawal_evidence(self, data: MeasurementBatch, xy: np.ndarray,
                             jammer: JammerEstimate | JammerHypotheses, sigma_db: float):
        """The reports of ``data`` placed inside the area (beyond its edge the map is no
        evidence, see ``ingest``): their probability with ``jammer`` and without, and when
        each was taken, for ``WithdrawalTest.update``. An estimate is weighed with its
        uncertainty (``posterior_hypotheses``): a still jammer's first estimate, 7 m and
        1.8 dB off with an 8 m sd, was withdrawn by one UAV's run along the zone edge it
        misplaced when taken as exact (bench_adaptation, icc2021, change 116)."""
        kept = np.flatnonzero(np.isfinite(xy).all(axis=1) & ~self.scenario.area.outside(xy))
        levels, xy, reported_db = data.levels[kept], xy[kept], data.sinr_db[kept]
        if isinstance(jammer, JammerEstimate):
            jammer = posterior_hypotheses(jammer)
        with_jammer = self.model_probability(levels, xy, jammer, sigma_db)
        without = self.model_probability(levels, xy, None, sigma_db)
        floors = np.full(len(kept), self.scenario.online_map.probability_floor)
        reported = np.isfinite(reported_db)
        if reported.any():  # a dB report weighs by its SINR
            here = xy[reported]
            belief = sinr_beliefs(RadioModel(self.scenario, shadowed=False), here,
                                  self._no_jammer_probabilities(here), sigma_db or None,
                                  self.reference.at(here))
            with_jammer[reported], without[reported] = (
                sinr_report_probabilities(self.scenario, here, reported_db[reported], model,
                                          belief) for model in (jammer, NO_JAMMER))
            floors[reported] = 0.0
        return with_jammer, without, data.times[kept], floors

    def _weigh_correction(self, stored: MeasurementBatch,
                          xy: np.ndarray) -> PublishedWeights | None:
        """New reports weighed against the jammer the map in service was corrected for;
        the survey map to publish when they withdraw it."""
        check = self._withdrawal.update(*self._withdrawal_evidence(
            stored, xy, self._correction, self._estimate_sigma_db))
        if check is None or not check.fired:
            return None
        return self._withdraw_locked(self._correction, check)

    def _withdraw_locked(self, jammer: JammerEstimate | JammerHypotheses,
                         check: WithdrawalCheck) -> PublishedWeights | None:
        """The reports say ``jammer`` is gone: the survey map goes back in service (what to
        publish, None if it is in service already) and the detector watches it afresh. A
        change detected since that map went out (the jammer moved) is handled on: its
        reports are what the next estimate needs."""
        if self._change is None or self._change is self._correction_change:
            self._settle_locked()
        withdrawn_version = self._version
        published = None
        if self._network is not self._base:
            weights = to_bytes(self._base)
            self._version += 1
            self._network, self._accuracy = self._base, self._base_accuracy
            published = PublishedWeights(weights, sha256(weights), self._version,
                                         self._base_accuracy, None)
        self.estimate, self._correction, self._provisional = None, None, False
        estimate = jammer if isinstance(jammer, JammerEstimate) else None
        self.events.append({
            "type": "estimate_withdrawn", "t": self.clock(), "version": self._version,
            "withdrawn_version": None if published is None else withdrawn_version,
            "provisional": estimate is None,
            **{key: None if estimate is None else getattr(estimate, key)
               for key in ("x", "y", "power_w")},
            "evidence_nats": check.statistic, "evidence_since": check.since,
            "reports": check.reports})
        if published is not None:
            self.events.append({"type": "sinr_weights_published", "t": self.clock(),
                                "version": self._version, "sha256": published.sha256,
                                "accuracy": self._base_accuracy,
                                "samples": 0, "train_seconds": 0.0, "provisional": False})
        return published

    def _on_change(self, check: DetectorCheck) -> None:
        start = self.detector.change_start
        self.reference.discard_since(start)
        self._change = _Change(start, self.clock(), len(self.memory.since(start)))
        self.events.append({"type": "change_detected", "t": self.clock(),
                            "version": self._version, "source": check.source,
                            "accuracy": float(np.mean(self._recent)), "change_time": start})

    def _run(self, job: str) -> None:
        change = self._change
        try:
            data = self.memory.since(change.start)
            if job == "estimate":
                self._try_estimate(change, data)
            elif job == "fit":  # the DNN alone, the jammer neither placed nor confirmed
                self._fit(change, data, None)
            else:  # "settle": the map stands, the detector watches it
                self._settle(change)
        except Exception as exc:  # a failed adaptation must not leave the mapper stuck
            with self._lock:
                self.events.append({"type": "retrain_failed", "t": self.clock(),
                                    "version": self._version, "error": repr(exc)})
                self._settle_locked()
        finally:
            with self._lock:
                self._busy = False

    def _try_estimate(self, change: _Change, data: MeasurementBatch) -> None:
        # The survey map carries the world's shadowing, which the ideal model lacks: without
        # it a jammer cannot be told from a shadow; its probabilities, not only its levels,
        # say how near a level's edge each report lies (see jammer_estimation).
        xy = positions_from_features(self.scenario, data.features)
        located = locate_jammer(
            self.scenario, xy, data.levels, reported_db=data.sinr_db,
            no_jammer_levels=self._no_jammer_probabilities(xy),
            no_jammer_db=self.reference.at(xy),
            report_sigma_db=(REPORT_SIGMA_DB if self._model_spread_db is None
                             else self._model_spread_db))
        if self._closing.is_set():
            return
        estimate = located.estimate
        change.tried_at = len(data)
        change.tries += 1
        if estimate is None and change.estimate is not None:
            estimate = change.estimate  # refining: keep the last estimate that converged
        if estimate is not None:
            change.estimate = estimate
            self._fit(change, data, estimate)
            return
        if not change.failure_logged:
            change.failure_logged = True
            self.events.append({"type": "estimate_not_converged", "t": self.clock(),
                                "measurements": len(data)})
        # A jammer the uploads show but cannot place yet: a provisional map, corrected by every
        # place it may be in proportion to its probability, until an estimate converges.
        if located.hypotheses is not None:
            self._fit(change, data, located.hypotheses)

    def _fit(self, change: _Change, data: MeasurementBatch,
             jammer: JammerEstimate | JammerHypotheses | None) -> None:
        """Fit the DNN to the post-change uploads, plus the prior of the no-jammer map
        corrected by ``jammer`` (a converged estimate, or a provisional map's hypotheses),
        and publish. Without ``jammer`` the prior is the no-jammer map as surveyed: fitted to
        the uploads alone, which lie along a few paths, the network forgot the survey
        elsewhere (icc2021-shadowed, no jammer, 3 seeds x 200 episodes: 96.9 / 97.9 / 96.9 %
        success alone, 97.9 / 98.5 / 97.5 % with the prior; BENCHMARKS.md)."""
        config = self.retrain
        features, levels = data.features, data.levels
        prior_xy = self._prior_positions()
        prior_features = scenario_features(self.scenario, prior_xy)
        sigma_db = 0.0
        withdrawal = WithdrawalTest.of(self.scenario)
        if jammer is None:
            prior_levels = self._no_jammer_probabilities(prior_xy).argmax(axis=-1)
        else:
            sigma_db = self._shadowing_sigma(prior_xy)
            if not self._may_serve(change, data, jammer, sigma_db, withdrawal):
                return
            prior_levels = corrected_levels(self.scenario, self._no_jammer_probabilities,
                                            jammer, prior_xy, shadowing_sigma_db=sigma_db)
        features = np.concatenate([features, prior_features])
        levels = np.concatenate([levels, prior_levels])
        # The estimate behind the map, when one converged; a provisional map has none.
        provisional = isinstance(jammer, JammerHypotheses)
        estimate = None if provisional else jammer
        # Imported here, on the first retraining: torch takes seconds to load, and the cloud
        # serves weights from its start (the cloud process loads it meanwhile).
        from cloud_service.sinr_training import train_sinr_map

        result = train_sinr_map(
            features, levels, self.level_count, network=self._base,
            steps=config.provisional_steps if provisional else config.steps,
            max_seconds=config.max_seconds, target_accuracy=config.target_accuracy,
            holdout=config.holdout, seed=self._seed + self._version + 1,
            stop=self._closing.is_set)
        if self._closing.is_set():
            return
        change.fitted_at = len(data)
        weights = to_bytes(result.network)
        with self._lock:
            if self._change is not change:  # withdrawn while it was being fitted
                return
            self._network = result.network
            self._version += 1
            self._accuracy = result.accuracy
            self._provisional = provisional
            self.estimate, self._estimate_sigma_db = estimate, sigma_db
            self._correction, self._withdrawal = jammer, withdrawal
            self._correction_change = change
            published = PublishedWeights(weights, sha256(weights), self._version,
                                         result.accuracy, estimate,
                                         None if estimate is None else change.start,
                                         provisional)
            if estimate is not None:
                self.events.append({"type": "jammer_estimated", "t": self.clock(),
                                    "map_version": self._version, **estimate._asdict()})
            self.events.append({"type": "sinr_weights_published", "t": self.clock(),
                                "version": self._version, "sha256": published.sha256,
                                "accuracy": result.accuracy,
                                "samples": len(data), "train_seconds": result.seconds,
                                "provisional": provisional})
        if self.publish is not None:
            self.publish(published)
        if jammer is None:  # the paper's path: one retraining per change
            self._settle(change)

    def _may_serve(self, change: _Change, data: MeasurementBatch,
                   jammer: JammerEstimate | JammerHypotheses, sigma_db: float,
                   withdrawal: WithdrawalTest) -> bool:
        """Whether a map corrected for ``jammer`` may go out: the post-change reports it is
        to be fitted on do not already show that jammer gone (else it is withdrawn,
        ``_withdraw_unfitted``) and, for a change's first map, confirm it (``_confirmed``).
        ``withdrawal`` is left fed with those reports."""
        evidence = self._withdrawal_evidence(
            data, positions_from_features(self.scenario, data.features), jammer, sigma_db)
        check = withdrawal.update(*evidence)
        if check is not None and check.fired:
            self._withdraw_unfitted(change, jammer, check)
            return False
        return self._confirmed(change, withdrawal, *evidence)

    def _confirmed(self, change: _Change, withdrawal: WithdrawalTest, with_jammer: np.ndarray,
                   without: np.ndarray, times: np.ndarray, floors: np.ndarray) -> bool:
        """Whether the reports taken since the change was detected show its jammer still
        there, by ``online_map.confirmation_threshold`` nats at least. A jammer seen only in
        the reports that raised the change (a blip, switched off since) is fitted by a still
        jammer placed where no later report could contradict it; such a phantom is never
        served, and the change's first corrected map waits for this."""
        if not change.confirmed:
            support = -withdrawal.evidence(with_jammer, without, floors)[
                times > change.detected_at]
            change.confirmed = float(support.sum()) >= (
                self.scenario.online_map.confirmation_threshold)
        return change.confirmed

    def _withdraw_unfitted(self, change: _Change, jammer: JammerEstimate | JammerHypotheses,
                           check: WithdrawalCheck) -> None:
        """The reports a correction was to be fitted on already show its jammer gone: it is
        not fitted, the change's handling ends, and any corrected map in service is
        withdrawn."""
        with self._lock:
            if self._change is not change:
                return
            self._settle_locked()
            published = self._withdraw_locked(jammer, check)
        if published is not None and self.publish is not None:
            self.publish(published)

    def _settle(self, change: _Change) -> None:
        with self._lock:
            if self._change is change:
                self._settle_locked()

    def _settle_locked(self) -> None:
        self._change = None
        self.detector.reset()

    def _prior_positions(self) -> np.ndarray:
        """Where the estimate-corrected map labels the area for the DNN (a fresh draw for
        each map version)."""
        return uniform_positions(self.scenario, self.scenario.online_map.prior_points,
                                 np.random.default_rng(self._seed + self._version))

    def _shadowing_sigma(self, xy: np.ndarray) -> float:
        """How far the survey map says the world departs from the ideal model, at ``xy``."""
        xy = sigma_fit_sample(xy)
        return fit_shadowing_sigma(RadioModel(self.scenario, shadowed=False), xy,
                                   self._base_probabilities(xy).argmax(axis=-1))

    def _base_probabilities(self, xy: np.ndarray) -> np.ndarray:
        return predict_probabilities(self._base, scenario_features(self.scenario, xy))

    def _no_jammer_probabilities(self, xy: np.ndarray) -> np.ndarray:
        """What the cloud believes of each level at points ``xy`` (n, 2) with no jammer, for
        the estimate, the corrected maps and the detector: the ideal model's, give or take
        its spread, where the survey map keeps to it that closely (in icc2021 it agrees with
        the model on 99.2 % of the area and errs along its levels' edges); the survey map's
        elsewhere. The estimate then reads each report at that spread, not at the
        REPORT_SIGMA_DB a world unlike the model needs: a weak jammer's first few
        contradicting reports (7 of 65, a 0.36 W jammer 18 m off) explained no jammer near
        them at 1.2 dB, and the provisional map that followed was 4 points less right than
        the survey map. bench_adaptation, icc2021, 20 changes: the first corrected map 94.3
        -> 96.3 % right (median), 98.3 % 30 s on."""
        if self._model_spread_db is None:
            return self._base_probabilities(xy)
        return ideal_level_probabilities(self.scenario, xy, None, self._model_spread_db)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for running work; True when none is running any more."""
        worker = self._worker
        if worker is not None:
            worker.join(timeout)
        return not self._busy

    def close(self) -> None:
        """Stop the work under way and close the memory. A fit stops at its next step; an
        estimate cannot be cut short, so it is waited for ``CLOSE_WAIT_S`` at most and its
        result dropped: a cloud told to stop stops within seconds, however loaded its
        machine (a live swap on a loaded 2-core machine kept one estimating past 30 s)."""
        self._closing.set()
        self.wait(CLOSE_WAIT_S)
        self.memory.close()


def _of_reported(probabilities: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Each row's probability (n, levels) of its reported level (n,)."""
    return np.take_along_axis(probabilities, levels[:, None], -1)[:, 0]


@dataclass
class _Change:
    """A detected change while the mapper handles it."""

    start: float  # the detector's estimate of when it happened
    detected_at: float  # when it was detected (the mapper's clock)
    measurements: int  # stored since ``start``
    estimate: JammerEstimate | None = None
    tried_at: int = 0  # post-change measurements at the last estimate attempt
    tries: int = 0  # estimate attempts
    fitted_at: int = 0  # ... at the last fit
    failure_logged: bool = False
    # Whether reports since the detection showed the jammer still there (see ``_confirmed``).
    confirmed: bool = False

    @property
    def phase(self) -> str:
        return "refining" if self.estimate is not None and self.confirmed else "estimating"

    def next_job(self, config: RetrainConfig) -> str | None:
        n = self.measurements
        if self.estimate is None or not self.confirmed:
            if n >= config.min_samples and self.tries >= config.min_tries:
                return "fit"
            if n >= max(config.estimate_from, self.tried_at + config.estimate_every,
                        config.estimate_growth * self.tried_at):
                return "estimate"
            return None
        # Settled once enough has come in and the last fit is recent, or once a fit has seen
        # enough however fast more arrives: with uploads outpacing the fits (the bus at 20x
        # real time), waiting for a recent fit would keep the detector off for good.
        if self.fitted_at >= config.settle_after or (
                n >= config.settle_after and n - self.fitted_at < config.refine_every):
            return "settle"
        if n - self.fitted_at >= config.refine_every:
            return "estimate"
        return None
