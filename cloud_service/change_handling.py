"""When the online mapper works on a detected change: how often the jammer is estimated and
the map refitted, when the DNN alone may go, and when the map settles (``RetrainConfig``),
and where the handling of one change stands, the following of its jammer included
(``HandledChange``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.jammer_tracking import WindowedTracker
from shared.scenario import OnlineMap


@dataclass(frozen=True)
class RetrainConfig:
    """How the mapper answers a detected change (values measured: BENCHMARKS.md, "Online SINR
    mapping", the mapper's schedule)."""

    # Post-change measurements before the first estimate of the jammer is tried, and between
    # tries while none converges, or between counts of the jammers while one is refined
    # (``HandledChange.counting_due``; four UAVs upload about 40 a second): at least
    # ``estimate_every`` more, and ``estimate_growth`` times as many as at the last try, so
    # that a jammer the data cannot place (a fit costs up to a second) is tried ~20 times up
    # to ``min_samples``, not at every upload.
    estimate_from: int = 40
    estimate_every: int = 40
    estimate_growth: float = 1.25
    # The corrected map is refined (estimate and DNN again, on all post-change data) every
    # ``refine_every`` post-change measurements until ``settle_after``; then the map stands
    # and the detector watches it: settling sooner left the estimate, and so the map, still
    # visibly off.
    refine_every: int = 600
    settle_after: int = 4000
    # Without a converged estimate, the DNN alone retrains once this many post-change
    # measurements are in, and the estimate has been tried ``min_tries`` times: four UAVs
    # bring 4,000 in after ~20 tries, a fleet of hundreds within a second, after two; a map
    # no estimate settled makes errors that raise the next false change.
    min_samples: int = 4000
    min_tries: int = 8
    # Mini-batches of 200 per fit (under a second on one core).
    steps: int = 1000
    # ... per provisional map: a stopgap, out in a fraction of the time, that the next try
    # replaces.
    provisional_steps: int = 250
    max_seconds: float | None = 2.5  # a slow machine still publishes within ~3 s of the data
    # No early stop: the run is short, and stopping at a high learning rate (the decay is
    # scheduled over ``steps``) would leave the class boundaries unsettled.
    target_accuracy: float | None = None
    holdout: float = 0.2


@dataclass
class HandledChange:
    """A detected change while the mapper handles it."""

    start: float  # the detector's estimate of when it happened
    detected_at: float  # when it was detected (the mapper's clock)
    measurements: int  # stored since ``start``
    estimate: JammerEstimate | None = None
    tried_at: int = 0  # post-change measurements at the last estimate attempt
    driving_tries: int = 0  # fits as a driving jammer (``driving_due``)
    driving_tried_until: float = -math.inf  # when the newest upload of the last was taken
    tries: int = 0  # estimate attempts
    fitted_at: int = 0  # ... at the last fit
    failure_logged: bool = False
    # Whether reports since the detection showed the jammer still there
    # (``WithdrawalTest.confirms``).
    confirmed: bool = False
    # Follows the jammer through windows of the uploads since ``start``; a moving one's
    # estimate from all of them may never converge, so it does not wait for one.
    tracker: WindowedTracker | None = None

    def tracking_due(self, latest: float) -> bool:
        """Whether uploads up to ``latest`` complete a window to follow the jammer through:
        one jammer, unless the change was estimated to have several."""
        several = self.estimate is not None and bool(self.estimate.others)
        return self.tracker is not None and not several and self.tracker.due(latest)

    def driving_due(self, latest: float, online_map: OnlineMap) -> bool:
        """Whether uploads up to ``latest`` call for the change to be fitted as a jammer that
        drives (``driving_jammer``), every ``online_map.driving_fit_every_s``: while its
        estimate drives, to follow it; while it is of one jammer standing still or none
        converged, to try, once the uploads span ``online_map.driving_fit_after_s`` and at
        most ``online_map.driving_fits`` times (a still fit of a driving jammer lies behind
        it, or nowhere)."""
        if latest - self.driving_tried_until < online_map.driving_fit_every_s:
            return False
        if self.estimate is None:
            return self._driving_tries_left(latest, online_map)
        if self.estimate.others or not self.estimate.present:
            return False
        return (self.estimate.vx_mps is not None
                or self._driving_tries_left(latest, online_map))

    def counting_due(self, config: RetrainConfig) -> bool:
        """Whether to count the jammers again between the refits of a still estimate
        (``refine_every`` post-change measurements apart): as often as an estimate is tried
        before one converges, so that a jammer the estimate in service lacks is counted, if
        not placed, within seconds of the uploads that show it, not at the next refit."""
        return (self.phase == "refining" and self.estimate.vx_mps is None
                and self.measurements >= max(self.tried_at + config.estimate_every,
                                             config.estimate_growth * self.tried_at))

    def _driving_tries_left(self, latest: float, online_map: OnlineMap) -> bool:
        return (latest - self.start >= online_map.driving_fit_after_s
                and self.driving_tries < online_map.driving_fits)

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
        # A driving estimate is fitted again by its own schedule (``driving_due``).
        if self.estimate.vx_mps is None and n - self.fitted_at >= config.refine_every:
            return "estimate"
        return None
