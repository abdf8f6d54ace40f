"""The jammer as the cloud knows it from the uploads: a point estimate with its uncertainty
(``JammerEstimate``), or, while the uploads cannot pin it down, weighted hypotheses of where
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


NO_JAMMER = JammerEstimate(False, None, None, None, None, None, None, None, 0, 0.0)


class JammerHypotheses(NamedTuple):
    """Where a jammer the uploads show may stand while they cannot pin it down yet: the
    coarse search's most probable hypotheses (each a point estimate) and their posterior
    weights, summing to 1."""

    estimates: list[JammerEstimate]
    weights: np.ndarray


def posterior_hypotheses(estimate: JammerEstimate) -> JammerHypotheses:
    """A present ``estimate`` as six equally weighted hypotheses, sqrt(3) standard deviations
    either side of it along its position's principal axes and its power (dB): the sigma
    points of its posterior, which share its mean and covariance. Weighed against these, a
    report along a zone edge the estimate is unsure of counts as the uncertainty allows, not
    as if the edge were exact."""
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
    return JammerHypotheses(hypotheses, np.full(len(hypotheses), 1.0 / len(hypotheses)))
