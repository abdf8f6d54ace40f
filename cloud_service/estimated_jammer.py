"""The jammers as the cloud knows them from the uploads: a point estimate with its uncertainty
(``JammerEstimate``; several jammers are the first with the others beside it, see
``estimated_set``), or, while the uploads cannot pin one down, weighted hypotheses of where
it may stand (``JammerHypotheses``)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np


class JammerEstimate(NamedTuple):
    """The fitted jammer. With ``present`` false no jammer explains the uploads at least as
    well as any jammer, and every position and power field is None."""

    present: bool
    x: float | None
    y: float | None
    power_w: float | None  # nominal, as `jamnav jammer set` takes it: effective / efficiency
    effective_power_dbm: float | None  # what reaches the receiver in band
    sd_x_m: float | None
    sd_y_m: float | None
    sd_power_db: float | None
    measurements: int
    # Weighted log-likelihood of the fitted jammer less that of no jammer (nats).
    log_likelihood_ratio: float
    cov_xy_m2: float | None = None  # posterior covariance of x and y
    # Its velocity, where the cloud follows it over time (``jammer_tracking``); else None.
    vx_mps: float | None = None
    vy_mps: float | None = None
    sd_vx_mps: float | None = None
    sd_vy_mps: float | None = None
    # The jammers estimated beside this one, each present and with none of its own: their
    # interference adds to this one's in Eq. (3) wherever a map is corrected or a report
    # weighed, so that every model of the cloud reads the set.
    others: tuple[JammerEstimate, ...] = ()

    @property
    def members(self) -> tuple[JammerEstimate, ...]:
        """Each jammer of the set alone, this one first; none when ``present`` is false."""
        if not self.present:
            return ()
        return (self._replace(others=()), *self.others)

    def record(self) -> dict:
        """Plain fields for JSON (a map's card, an event), the others as records too."""
        return {**self._asdict(), "others": [other.record() for other in self.others]}

    @classmethod
    def of_record(cls, fields: dict) -> JammerEstimate:
        """The estimate ``record`` wrote (TypeError on fields it did not write)."""
        others = tuple(cls.of_record(other) for other in fields.get("others") or ())
        return cls(**{**fields, "others": others})


def estimated_set(estimates: list[JammerEstimate]) -> JammerEstimate:
    """Several present estimates as one: the first, with the rest as its ``others``."""
    first, *rest = estimates
    return first._replace(others=tuple(rest))


NO_JAMMER = JammerEstimate(False, None, None, None, None, None, None, None, 0, 0.0)


class JammerHypotheses(NamedTuple):
    """Where a jammer the uploads show may stand while they cannot pin it down yet: the
    coarse search's most probable hypotheses (each a point estimate) and their posterior
    weights, summing to 1."""

    estimates: list[JammerEstimate]
    weights: np.ndarray


def posterior_hypotheses(estimate: JammerEstimate) -> JammerHypotheses:
    """A present ``estimate`` as equally weighted hypotheses: for each jammer of its set, six
    with that one moved sqrt(3) standard deviations either side along its position's
    principal axes and its power (dB), the others where estimated. For one jammer these are
    the sigma points of its posterior, which share its mean and covariance. Weighed against
    these, a report along a zone edge the estimate is unsure of counts as the uncertainty
    allows, not as if the edge were exact. An estimate of no jammer is its one hypothesis."""
    if not estimate.present:
        return JammerHypotheses([estimate], np.ones(1))
    members = estimate.members
    hypotheses = []
    for index, member in enumerate(members):
        others = members[:index] + members[index + 1:]
        hypotheses.extend(estimated_set([moved, *others]) for moved in _sigma_points(member))
    return JammerHypotheses(hypotheses, np.full(len(hypotheses), 1.0 / len(hypotheses)))


def _sigma_points(estimate: JammerEstimate) -> list[JammerEstimate]:
    """One jammer's six sigma points (``posterior_hypotheses``)."""
    cov_xy = estimate.cov_xy_m2 or 0.0
    variances, axes = np.linalg.eigh([[estimate.sd_x_m**2, cov_xy], [cov_xy, estimate.sd_y_m**2]])
    reach = math.sqrt(3.0)
    hypotheses = []
    for sign in (-1.0, 1.0):
        for variance, axis in zip(variances.tolist(), axes.T, strict=True):
            dx, dy = sign * reach * math.sqrt(max(variance, 0.0)) * axis
            hypotheses.append(estimate._replace(x=estimate.x + dx, y=estimate.y + dy))
        hypotheses.append(estimate._replace(
            power_w=estimate.power_w * 10.0 ** (sign * reach * estimate.sd_power_db / 10.0)))
    return hypotheses
