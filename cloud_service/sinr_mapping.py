"""Online SINR mapping in the cloud (paper Sec. III-C): watch, detect, adapt, publish.

``OnlineSinrMapper`` ties the memory, the change detector (``change_detection``), the jammer
estimate (``jammer_estimation``), the withdrawal of a jammer gone (``jammer_withdrawal``) and
the network's refits (``map_refit``, trained by ``sinr_training``: the paper's mini-batches of
200, Adam lr 5e-3, L2 1e-4) into the map in service, and publishes each new one. It has no
transport of its own, so the bus shell around it stays thin.

K_n matters: the interference, and the jammer's hole, depend on where the UAV is in the whole
layout, which with few GBSs in view the network must infer from their relative positions,
whose order reshuffles at every cell edge. With every GBS in view (K_n = 12 in icc2021) the
position is explicit (BENCHMARKS.md, "Online SINR mapping", the GBSs the map sees).
"""

from __future__ import annotations

import math
import threading
import time as wall
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from cloud_service.change_detection import ChangeDetector, DetectorCheck
from cloud_service.change_handling import HandledChange, RetrainConfig
from cloud_service.driving_jammer import driving_refit
from cloud_service.estimate_inputs import EstimateInputs
from cloud_service.estimated_jammer import JammerEstimate, JammerHypotheses
from cloud_service.jammer_estimation import JammerFit, locate_jammer
from cloud_service.jammer_tracking import MOST_WINDOWS_BEHIND, WindowedTracker
from cloud_service.jammer_withdrawal import (
    CorrectionWatch,
    JammerGone,
    WithdrawalCheck,
    WithdrawalTest,
    withdrawal_evidence,
)
from cloud_service.map_correction import corrected_levels, jammer_loss_db
from cloud_service.map_refit import prior_positions, refit_network
from cloud_service.mapper_outputs import IngestReport, PublishedWeights
from cloud_service.no_jammer_belief import sinr_beliefs
from cloud_service.report_models import ReportModels
from cloud_service.sinr_memory import SinrMemory, Uploads
from cloud_service.sinr_reference import SinrReference
from cloud_service.upload_positions import positions_from_features
from planning.maps import MAP_SPACING_M, LevelRaster, sinr_network_raster
from planning.networks import SinrMapNetwork, predict_probabilities, sha256, to_bytes
from shared.measurements import MeasurementBatch
from shared.radio import RadioModel
from shared.scenario import Scenario

if TYPE_CHECKING:
    from cloud_service.sinr_training import TrainResult

TARGET_ACCURACY = 0.97  # the accuracy bar the online map is held to on fresh measurements
RECENT_KEPT = 500  # uploads over which the map in service is scored for status
CLOSE_WAIT_S = 5.0  # how long a closing mapper waits for the work under way


class _RefitPrior(NamedTuple):
    """What a refit's prior labels its points with, and what a map fitted on it is watched
    with once in service."""

    levels: np.ndarray  # the level of each prior point
    shadowing_sigma_db: float  # fitted beside the correction (0 for an uncorrected map)
    withdrawal: WithdrawalTest  # fed with the post-change reports the map is fitted on


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
       ``ReportModels.no_jammer_probabilities``) into a prior over the whole area; the DNN
       is fitted to the prior plus every post-change upload and published at once, with the
       estimate;
    3. every ``retrain.refine_every`` further measurements, estimate and fit again, until
       ``retrain.settle_after``; then the detector re-arms on the final map. While the
       estimate is of one still jammer or none, the change is also tried as a driving one a
       few times (``HandledChange.driving_due``; ``driving_jammer``); one that drives
       corrects the map where it will be when the map flies, and is fitted again every
       ``online_map.driving_fit_every_s`` while it drives.
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
    goes on from the memory, which the restart kept. ``changed_since``: when the earliest
    change that a corrected map this cloud published answered began (None: none did); with
    ``refining_since`` it bounds the stored reports the no-jammer reference is rebuilt from
    (``_rebuild_reference``). ``base_accuracy``: the survey map's, for its publication when an
    estimate is withdrawn (``accuracy`` without a ``base_network``).
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
        changed_since: float | None = None,
        base_accuracy: float | None = None,
    ):
        self.scenario = scenario
        self.memory = memory
        self.publish = publish
        self.detector = detector or ChangeDetector.of(scenario)
        self.detector.reset()
        self.retrain = retrain or RetrainConfig()
        self.clock = clock
        self.background = background
        self.events: list[dict[str, Any]] = []
        self._network, self._accuracy = network, accuracy
        self._base = base_network or network
        self._base_accuracy = accuracy if base_network is None else base_accuracy
        self._provisional = False  # whether the map in service is a provisional one
        self._version = version
        self._seed = seed
        self._lock = threading.Lock()
        self._recent = deque(maxlen=RECENT_KEPT)
        newest = memory.newest_time()
        # When the newest report stored was taken (a restarted cloud's memory holds some).
        self._latest = -np.inf if newest is None else newest
        self._busy = False
        self._worker: threading.Thread | None = None
        # Set by ``close``: work under way stops at its next check and publishes nothing.
        self._closing = threading.Event()
        self.reference = SinrReference(scenario)
        self.report_models = ReportModels(scenario, self._base, self.reference,
                                          self._prior_positions())
        self._inputs = EstimateInputs(self.report_models, self.reference, memory)
        self._resume(estimate, refining_since)
        self._rebuild_reference(refining_since, changed_since)
        if estimate is not None and estimate.present:
            self._forget_reference_under(estimate)

    def _resume(self, estimate: JammerEstimate | None, refining_since: float | None) -> None:
        """Take over a map in service corrected with ``estimate`` (None: an uncorrected one)
        and, if it was still being refined, the handling of the change that began at
        ``refining_since``, as if that map had just been fitted."""
        self.estimate = estimate
        # How many jammers the cloud counts, placed or not: as its latest estimate try since
        # the last change counted them (None: not yet, or the uploads could not tell), none
        # once the reports withdrew every one, the rest when one of several went.
        self._jammers_counted: int | None = 0 if estimate is None else len(estimate.members)
        self._watch = CorrectionWatch.of(
            self.scenario, estimate if estimate is not None and estimate.present else None,
            0.0 if estimate is None else self.report_models.survey_sigma_db)
        self._change: HandledChange | None = None  # set while a change is being handled
        if estimate is not None and refining_since is not None:
            done = len(self.memory.since(refining_since))
            self._change = HandledChange(refining_since, self.clock(), done, estimate,
                                         tried_at=done, tries=done, confirmed=True,
                                         tracker=self._tracker(refining_since))
        # The change whose handling made the correction in service.
        self._correction_change = self._change

    def _rebuild_reference(self, *change_starts: float | None) -> None:
        """Refill the no-jammer reference from the memory a restart kept, by the rule live
        reports follow (``SinrReference``): every stored dB report taken before the earliest
        of ``change_starts`` (all of them if none is known) is offered, and committed as of the
        newest stored report, so those ``reference_delay_s`` older than it enter now and the
        others wait, to be dropped if a change is detected before them."""
        known = [start for start in change_starts if start is not None]
        for reports in self.memory.db_reports(min(known, default=math.inf)):
            xy = positions_from_features(self.scenario, reports.features)
            self.reference.offer(xy, reports.sinr_db, reports.times)
        newest = self.memory.newest_time()
        if newest is not None:
            self.reference.commit(newest)

    def _forget_reference_under(self, estimate: JammerEstimate) -> None:
        """Drop from the reference the reports that carry the loss of ``estimate``: where it
        takes ``detection_shift_db`` or more off the SINR, those nearer the survey map's
        no-jammer SINR less that loss than the SINR itself. Such a jammer was there, unseen,
        when they were taken (``SinrReference``); the others, taken before it came, are what
        its estimate reads best."""
        shift_db = self.scenario.online_map.detection_shift_db
        ideal = RadioModel(self.scenario, shadowed=False)

        def jammed(xy: np.ndarray, sinr_db: np.ndarray) -> np.ndarray:
            loss_db = jammer_loss_db(self.scenario, estimate, xy)
            survey = sinr_beliefs(ideal, xy, self.report_models.no_jammer_probabilities(xy))
            return (loss_db >= shift_db) & (sinr_db < survey.mean_db - loss_db / 2.0)

        self.reference.discard_jammed(jammed)

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
                    "jammers_counted": self._jammers_counted,
                    # Nats the reports hold against the jammer the map was corrected for.
                    "withdrawal_evidence": None if self._watch.jammer is None
                    else self._watch.whole.statistic}

    @property
    def model_spread_db(self) -> float | None:
        """How far reports may lie from the ideal model where it is the no-jammer map; None
        where the survey map departs from it too far (``ReportModels``)."""
        return self.report_models.model_spread_db

    def report_probability(self, stored: MeasurementBatch, probabilities: np.ndarray,
                           xy: np.ndarray | None = None) -> np.ndarray:
        """How probable each stored report was, as the detector weighs it: by the map in
        service or by the models, with the estimate behind that map
        (``ReportModels.report_probability``)."""
        return self.report_models.report_probability(stored, probabilities, xy, self.estimate,
                                                      self._watch.sigma_db)

    # -- watching ---------------------------------------------------------------------------
    def ingest(self, uploads: Uploads) -> IngestReport:
        stored, duplicates = self.memory.store(uploads)
        return self.take(stored, duplicates)

    def take(self, stored: MeasurementBatch, duplicates: int = 0) -> IngestReport:
        """Watch and adapt on measurements the memory has just ``stored`` (``ingest`` stores
        them first; the cloud on the lockstep clock stores a round's uploads one by one, then
        has the round taken as one batch)."""
        with self._lock:
            check, withdrawn = self._watch_locked(stored) if len(stored) else (None, None)
            job = self._claim_job_locked()
        if job is not None:
            self._start(job)
        if withdrawn is not None and self.publish is not None:
            self.publish(withdrawn)
        return IngestReport(len(stored), duplicates, check)

    def _watch_locked(self, stored: MeasurementBatch
                      ) -> tuple[DetectorCheck | None, PublishedWeights | None]:
        """Score the map in service on new reports, weigh them against the jammer behind it
        and, while no change is handled, feed them to the detector: its check, and the survey
        map to publish when the reports withdrew that jammer."""
        probabilities = predict_probabilities(self._network, stored.features)
        self._recent.extend((probabilities.argmax(-1) == stored.levels).tolist())
        self._latest = max(self._latest, float(stored.times.max()))
        xy = positions_from_features(self.scenario, stored.features)
        check = withdrawn = None
        if self._watch.jammer is not None:
            withdrawn = self._weigh_correction(stored, xy)
        # The reports that withdrew a map are not weighed again against the survey map.
        if withdrawn is None and self._change is None:
            check = self._detect_locked(stored, probabilities, xy)
        elif self._change is not None:
            self._change.measurements += int((stored.times >= self._change.start).sum())
        return check, withdrawn

    def _detect_locked(self, stored: MeasurementBatch, probabilities: np.ndarray,
                       xy: np.ndarray) -> DetectorCheck | None:
        """Feed the detector the reports taken inside the area; on a change, start handling
        it, else let the reports enter the no-jammer reference."""
        probability = self.report_probability(stored, probabilities, xy)
        # The map is learned over the area only and extrapolates past its edge, where a UAV
        # flown out (avoidance pushes some out in a crowd) contradicts it with nothing
        # changed (BENCHMARKS.md, "Planning", reports from outside the area). Reports from out
        # there are no evidence either way.
        inside = np.flatnonzero(~self.scenario.area.outside(xy))
        check = self.detector.update(probability[inside], [stored.sources[k] for k in inside],
                                     stored.times[inside], self._shift_evidence(stored, xy)[inside])
        if check is not None and check.fired:
            self._on_change(check)
        else:
            self._remember(stored, xy)
        return check

    def _remember(self, stored: MeasurementBatch, xy: np.ndarray) -> None:
        """Reports taken while no change is handled enter the no-jammer reference in turn,
        if no jammer is believed either."""
        if self._watch.jammer is None:
            self.reference.remember(xy, stored.sinr_db, stored.times)

    def _shift_evidence(self, stored: MeasurementBatch, xy: np.ndarray) -> np.ndarray:
        """What each dB report weighs for a jammer against the no-jammer reference
        (``SinrReference.shift_evidence_at``), while no jammer is believed; NaN elsewhere,
        and for level reports."""
        if self._watch.jammer is not None or not np.isfinite(stored.sinr_db).any():
            return np.full(len(stored), np.nan)
        return self.reference.shift_evidence_at(xy, stored.sinr_db)

    def _on_change(self, check: DetectorCheck) -> None:
        start = self.detector.change_start
        self.reference.discard_since(start)
        self._change = HandledChange(start, self.clock(), len(self.memory.since(start)),
                                     tracker=self._tracker(start))
        self._jammers_counted = None
        self.events.append({"type": "change_detected", "t": self.clock(),
                            "version": self._version, "source": check.source,
                            "accuracy": float(np.mean(self._recent)), "change_time": start})

    # -- withdrawal -------------------------------------------------------------------------
    def _weigh_correction(self, stored: MeasurementBatch,
                          xy: np.ndarray) -> PublishedWeights | None:
        """New reports weighed against the jammer the map in service was corrected for;
        the survey map to publish when they withdraw it. One jammer of several goes alone,
        the rest staying, unless a change is in hand."""
        fired = self._watch.weigh(self.report_models, stored, xy, self._change is None)
        if isinstance(fired, JammerGone):
            return self._withdraw_member_locked(fired)
        return None if fired is None else self._withdraw_locked(self._watch.jammer, fired)

    def _withdraw_member_locked(self, gone: JammerGone) -> None:
        """The reports say one jammer of the set behind the map is gone: the rest of the set
        is what the cloud believes and weighs reports against from now, and a change is
        handled from when that evidence began, so the next map is corrected for the rest (or
        for what the reports since then show instead)."""
        start = gone.check.since
        self.estimate = gone.rest
        self._jammers_counted = len(gone.rest.members)
        self._watch = CorrectionWatch.of(self.scenario, gone.rest, self._watch.sigma_db)
        self._change = HandledChange(start, self.clock(), len(self.memory.since(start)),
                                     gone.rest, confirmed=True, tracker=self._tracker(start))
        self.events.append({
            "type": "jammer_withdrawn", "t": self.clock(), "version": self._version,
            **{key: getattr(gone.jammer, key) for key in ("x", "y", "power_w")},
            "jammers_left": len(gone.rest.members), "evidence_nats": gone.check.statistic,
            "evidence_since": start, "reports": gone.check.reports})

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
        self.estimate, self._provisional = None, False
        if self._change is None:
            self._jammers_counted = 0
        if self._network is not self._base:
            published = self._serve_locked(self._base, to_bytes(self._base),
                                           self._base_accuracy, None, None, False)
        self._watch = CorrectionWatch.of(self.scenario)
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
            self._log_published(published, 0, 0.0)
        return published

    def _withdraw_unfitted(self, change: HandledChange,
                           jammer: JammerEstimate | JammerHypotheses,
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

    # -- adapting ---------------------------------------------------------------------------
    def _claim_job_locked(self) -> str | None:
        """The next work on the change in hand, claimed for one worker at a time."""
        if self._busy or self._change is None:
            return None
        job = self._change.next_job(self.retrain)
        if job is None and self._change.driving_due(self._latest, self.scenario.online_map):
            job = "drive"
        if job is None and self._change.tracking_due(self._latest):
            job = "track"
        if job is None and self._change.counting_due(self.retrain):
            job = "count"  # last: it changes no map
        self._busy = job is not None
        return job

    def _start(self, job: str) -> None:
        if self.background:
            self._worker = threading.Thread(target=self._run, args=(job,), name="sinr-adapt",
                                            daemon=True)
            self._worker.start()
        else:
            self._run(job)

    def _run(self, job: str) -> None:
        change = self._change
        try:
            data = self.memory.since(change.start)
            if job == "estimate":
                self._try_estimate(change, data)
            elif job == "fit":  # the DNN alone, the jammer neither placed nor confirmed
                self._fit(change, data, None)
            elif job == "drive":
                self._try_driving(change, data)
            elif job == "track":
                self._follow(change)
            elif job == "count":
                self._locate(change, data)
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

    def _locate(self, change: HandledChange, data: MeasurementBatch) -> JammerFit:
        """The estimator's fit of ``data``, the uploads since ``change`` began; its count of
        the jammers is the mapper's from now."""
        xy, levels, inputs = self._inputs.of(data)
        located = locate_jammer(self.scenario, xy, levels, **inputs)
        change.tried_at = len(data)
        with self._lock:
            if self._change is change:
                self._jammers_counted = located.count
        return located

    def _try_estimate(self, change: HandledChange, data: MeasurementBatch) -> None:
        located = self._locate(change, data)
        if self._closing.is_set():
            return
        estimate = located.estimate
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
                                "measurements": len(data), "jammers_counted": located.count})
        # A jammer the uploads show but cannot place yet: a provisional map, corrected by every
        # place it may be in proportion to its probability, until an estimate converges.
        if located.hypotheses is not None:
            self._fit(change, data, located.hypotheses)

    def _try_driving(self, change: HandledChange, data: MeasurementBatch) -> None:
        """The change fitted as a driving jammer (``HandledChange.driving_due``): where one
        drives, the map is corrected for it and published; where the one it had no longer
        drives, the jammer is estimated standing still; else all stays as it is."""
        drove = change.estimate is not None and change.estimate.vx_mps is not None
        if not drove:
            change.driving_tries += 1
        change.driving_tried_until = float(data.times.max())
        driving = driving_refit(self._inputs, data)
        if self._closing.is_set():
            return
        if driving is not None:
            change.estimate = driving
            self._fit(change, data, driving)
        elif drove:
            self._try_estimate(change, data)

    def _fit(self, change: HandledChange, data: MeasurementBatch,
             jammer: JammerEstimate | JammerHypotheses | None) -> None:
        """Fit the DNN to the post-change uploads, plus the prior of the no-jammer map
        corrected by ``jammer`` (a converged estimate, or a provisional map's hypotheses),
        and publish. Without ``jammer`` the prior is the no-jammer map as surveyed
        (``map_refit``)."""
        prior_xy = self._prior_positions()
        prior = self._refit_prior(change, data, jammer, prior_xy)
        if prior is None:
            return
        result = refit_network(
            self.scenario, self._base, data, prior_xy, prior.levels, self.retrain,
            provisional=isinstance(jammer, JammerHypotheses),
            seed=self._seed + self._version + 1, stop=self._closing.is_set)
        if self._closing.is_set():
            return
        change.fitted_at = len(data)
        published = self._serve_refit(change, data, jammer, prior, result)
        if published is None:  # withdrawn while it was being fitted
            return
        if self.publish is not None:
            self.publish(published)
        if jammer is None:  # the paper's path: one retraining per change
            self._settle(change)

    def _refit_prior(self, change: HandledChange, data: MeasurementBatch,
                     jammer: JammerEstimate | JammerHypotheses | None,
                     prior_xy: np.ndarray) -> _RefitPrior | None:
        """The prior's levels at ``prior_xy``: the no-jammer map's, or that map corrected by
        ``jammer``; None when a map corrected for ``jammer`` may not go out (``_may_serve``)."""
        withdrawal = WithdrawalTest.of(self.scenario)
        no_jammer_probabilities = self.report_models.no_jammer_probabilities
        if jammer is None:
            return _RefitPrior(no_jammer_probabilities(prior_xy).argmax(axis=-1), 0.0,
                               withdrawal)
        sigma_db = self.report_models.shadowing_sigma(prior_xy)
        if not self._may_serve(change, data, jammer, sigma_db, withdrawal):
            return None
        return _RefitPrior(corrected_levels(self.scenario, no_jammer_probabilities, jammer,
                                            prior_xy, shadowing_sigma_db=sigma_db),
                           sigma_db, withdrawal)

    def _may_serve(self, change: HandledChange, data: MeasurementBatch,
                   jammer: JammerEstimate | JammerHypotheses, sigma_db: float,
                   withdrawal: WithdrawalTest) -> bool:
        """Whether a map corrected for ``jammer`` may go out: the post-change reports it is
        to be fitted on do not already show that jammer gone (else it is withdrawn,
        ``_withdraw_unfitted``) and, for a change's first map, the reports since its
        detection confirm it (``WithdrawalTest.confirms``). ``withdrawal`` is left fed with
        those reports."""
        evidence = withdrawal_evidence(self.report_models, data,
                                       positions_from_features(self.scenario, data.features),
                                       jammer, sigma_db)
        check = withdrawal.update(*evidence)
        if check is not None and check.fired:
            self._withdraw_unfitted(change, jammer, check)
            return False
        if not change.confirmed:
            change.confirmed = withdrawal.confirms(
                evidence, change.detected_at, self.scenario.online_map.confirmation_threshold)
        return change.confirmed

    def _serve_refit(self, change: HandledChange, data: MeasurementBatch,
                     jammer: JammerEstimate | JammerHypotheses | None, prior: _RefitPrior,
                     result: TrainResult) -> PublishedWeights | None:
        """Put a refit network in service with the jammer it was corrected for, and log it:
        what to publish; None if the handling of ``change`` ended meanwhile."""
        provisional = isinstance(jammer, JammerHypotheses)
        # The estimate behind the map, when one converged; a provisional map has none.
        estimate = None if provisional else jammer
        velocity = None if change.tracker is None else change.tracker.velocity()
        if (estimate is not None and not estimate.others and estimate.vx_mps is None
                and velocity is not None):
            estimate = estimate._replace(**velocity)
        weights = to_bytes(result.network)
        with self._lock:
            if self._change is not change:
                return None
            published = self._serve_locked(result.network, weights, result.accuracy, estimate,
                                           None if estimate is None else change.start,
                                           provisional)
            self.estimate = estimate
            if estimate is not None and estimate.present:
                self._forget_reference_under(estimate)
            self._watch = CorrectionWatch.of(self.scenario, jammer, prior.shadowing_sigma_db,
                                             prior.withdrawal)
            self._correction_change = change
            if estimate is not None:
                self.events.append({"type": "jammer_estimated", "t": self.clock(),
                                    "map_version": self._version, **estimate.record()})
            self._log_published(published, len(data), result.seconds)
        return published

    def _serve_locked(self, network: SinrMapNetwork, weights: bytes, accuracy: float,
                      estimate: JammerEstimate | None, refining_since: float | None,
                      provisional: bool) -> PublishedWeights:
        """``network`` (serialized as ``weights``) in service as the next map version."""
        self._version += 1
        self._network, self._accuracy, self._provisional = network, accuracy, provisional
        return PublishedWeights(weights, sha256(weights), self._version, accuracy, estimate,
                                refining_since, provisional, self._jammers_counted)

    def _log_published(self, published: PublishedWeights, samples: int,
                       train_seconds: float) -> None:
        self.events.append({"type": "sinr_weights_published", "t": self.clock(),
                            "version": published.version, "sha256": published.sha256,
                            "accuracy": published.accuracy, "samples": samples,
                            "train_seconds": train_seconds,
                            "provisional": published.provisional})

    def _settle(self, change: HandledChange) -> None:
        with self._lock:
            if self._change is change:
                self._settle_locked()

    def _settle_locked(self) -> None:
        self._change = None
        self.detector.reset()

    def _prior_positions(self) -> np.ndarray:
        """Where the refit's prior labels the area (a fresh draw for each map version)."""
        return prior_positions(self.scenario, self._seed + self._version)

    # -- following ---------------------------------------------------------------------------
    def _tracker(self, start: float) -> WindowedTracker:
        return WindowedTracker(start, self.scenario.online_map.tracking_window_s)

    def _follow(self, change: HandledChange) -> None:
        """Estimate the windows of uploads the change's tracker has not seen, each alone, and
        log where the track puts the jammer after each that placed it."""
        tracked = change.tracker.follow(self._latest, self._inputs.window_estimate,
                                        MOST_WINDOWS_BEHIND)
        with self._lock:
            self.events.extend({**now._asdict(), "type": "jammer_tracked", "t": self.clock(),
                                "tracked_at": now.t} for now in tracked)

    # -- stopping ----------------------------------------------------------------------------
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
        machine (an estimate on a loaded machine can run far longer)."""
        self._closing.set()
        self.wait(CLOSE_WAIT_S)
        self.memory.close()
