"""The cloud's no-jammer beliefs corrected with a jammer it estimated (or with hypotheses of
one): how probable each level, or each dB report, is at a point. These are the prior the
corrected maps are fitted to (``corrected_levels``) and the models the detector and the
withdrawal test weigh reports by.

The no-jammer map (learned from measurements, so it carries the GBS shadowing) says in which
band the world's no-jammer SINR lies, ``no_jammer_belief`` where in the band; the ideal
model's loss to the jammer is taken off it. Where the survey map keeps to the ideal model
closely, the ideal model with the jammer serves too (``ideal_level_probabilities``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from cloud_service.estimated_jammer import JammerEstimate, JammerHypotheses
from cloud_service.no_jammer_belief import (
    SinrBelief,
    fitted_sigma,
    level_probabilities,
    prior_of_map,
)
from cloud_service.report_likelihood import (
    OUTLIER_SHARE,
    OUTLIER_SPAN_DB,
    REPORT_SIGMA_DB,
    band_edges,
    log_band_probability,
)
from shared.radio import JammerParams, RadioModel
from shared.scenario import Scenario

# A provisional map keeps the survey map's level where the hypotheses leave it at least this
# probable (``corrected_levels``): at a lower share the first provisional map came a little
# more right and the map 30 s on a little less (BENCHMARKS.md, "Online SINR mapping",
# provisional maps).
SURVEY_LEVEL_KEPT = 0.5


def corrected_levels(scenario: Scenario, no_jammer_levels_at: Callable[[np.ndarray], np.ndarray],
                     jammer: JammerEstimate | JammerHypotheses, xy: np.ndarray, *,
                     shadowing_sigma_db: float | None = None) -> np.ndarray:
    """The no-jammer map corrected with an estimated jammer, at points ``xy`` (..., 2): the
    most probable level of ``corrected_level_probabilities`` (with ``present`` false, the
    no-jammer map's). Corrected with hypotheses (a provisional map), a point keeps the
    no-jammer map's level unless they leave it less than ``SURVEY_LEVEL_KEPT`` probable: a
    provisional map departs from the survey only where the hypotheses together make it
    improbable, not wherever one of three levels edges out the others."""
    xy = np.asarray(xy, dtype=np.float64)
    no_jammer = _map_at(scenario, no_jammer_levels_at, xy)
    base = no_jammer.argmax(axis=-1)
    probabilities = _corrected(scenario, no_jammer, jammer, xy.reshape(-1, 2),
                               shadowing_sigma_db, 0.0)
    levels = probabilities.argmax(axis=-1)
    if isinstance(jammer, JammerHypotheses):
        kept = np.take_along_axis(probabilities, base[:, None], axis=-1)[:, 0]
        levels = np.where(kept >= SURVEY_LEVEL_KEPT, base, levels)
    return levels.reshape(xy.shape[:-1])


def corrected_level_probabilities(
    scenario: Scenario,
    no_jammer_levels_at: Callable[[np.ndarray], np.ndarray],
    jammer: JammerEstimate | JammerHypotheses,
    xy: np.ndarray,
    *,
    shadowing_sigma_db: float | None = None,
    report_sigma_db: float = 0.0,
) -> np.ndarray:
    """How probable each level is at points ``xy`` (..., 2) by the no-jammer map corrected
    with an estimated jammer, or with hypotheses of one (the mixture of theirs, by weight):
    shape (..., levels).

    At each point the no-jammer map's level says in which band the world's no-jammer SINR
    lies, and the ideal model (give or take ``shadowing_sigma_db``; None fits it to the
    map's levels at ``xy``, see ``fit_shadowing_sigma``), sharpened near a level's edge by
    what the map's probabilities read there (``prior_of_map``), where in the band; the
    estimated jammer takes the ideal model's loss off it. ``report_sigma_db`` widens that
    spread for what a receiver reports rather than what is there. The map was learned from
    measurements and so carries the GBS shadowing; the ideal model's own levels do not, so
    taking them where the jammer matters loses more than it corrects (BENCHMARKS.md, "Online
    SINR mapping", the estimator's model). ``no_jammer_levels_at`` maps points (m, 2) to
    levels (m,) or, better, to the probabilities of each level (m, levels), e.g. the
    no-jammer SINR network's on their features. With ``present`` false, the no-jammer map's
    most probable level, certain but for the receiver's ``report_sigma_db``.
    """
    xy = np.asarray(xy, dtype=np.float64)
    probabilities = _corrected(scenario, _map_at(scenario, no_jammer_levels_at, xy), jammer,
                               xy.reshape(-1, 2), shadowing_sigma_db, report_sigma_db)
    return probabilities.reshape(*xy.shape[:-1], scenario.channel.level_count)


def sinr_report_probabilities(
    scenario: Scenario, xy: np.ndarray, reported_db: np.ndarray,
    jammer: JammerEstimate | JammerHypotheses, belief: SinrBelief,
    report_sigma_db: float = REPORT_SIGMA_DB,
) -> np.ndarray:
    """How probable each dB report (n,) at points ``xy`` (n, 2) is with ``jammer`` (with
    hypotheses, the mixture by weight; with ``present`` false, none): the probability of its
    report step's interval when the no-jammer SINR is ``belief`` (``sinr_beliefs``) less the
    ideal model's loss to the jammer, spread by ``report_sigma_db``, with the outlier share
    of ``report_likelihood.ReportTables``."""
    losses = _IdealLosses(scenario, xy)
    sd_db = np.hypot(belief.sd_db, report_sigma_db)
    half_step = scenario.uav.report_step_db / 2.0
    total = 0.0
    for estimate, weight in _weighted(jammer):
        mean_db = belief.mean_db - losses.loss_db(estimate)
        total = total + weight * np.exp(log_band_probability(
            (reported_db - half_step - mean_db) / sd_db,
            (reported_db + half_step - mean_db) / sd_db))
    outlier = OUTLIER_SHARE * scenario.uav.report_step_db / OUTLIER_SPAN_DB
    return (1.0 - OUTLIER_SHARE) * total + outlier


def jammer_loss_db(scenario: Scenario, estimate: JammerEstimate, xy: np.ndarray) -> np.ndarray:
    """What the ideal model says a present ``estimate`` (each jammer of its set) takes off the
    SINR at points ``xy`` (n, 2), in dB."""
    return _IdealLosses(scenario, xy).loss_db(estimate)


def ideal_model_spread_db(scenario: Scenario, survey_sigma_db: float) -> float | None:
    """How far a report may lie from the ideal model's SINR where the survey map agrees with
    that model: the survey map's fitted departure from it (``fit_shadowing_sigma``) and the
    receivers' noise (their datasheet's, ``uav.measurement_noise_db``). None where that
    spread is over half the narrowest level band: the model then cannot tell a level from
    its neighbour, and every report would look probable by it (the shadowed world)."""
    spread = math.hypot(survey_sigma_db, scenario.uav.measurement_noise_db)
    narrowest = float(np.diff(scenario.channel.level_edges_db).min(initial=np.inf))
    return spread if spread <= 0.5 * narrowest else None


def ideal_level_probabilities(scenario: Scenario, xy: np.ndarray,
                              jammer: JammerEstimate | JammerHypotheses | None,
                              spread_db: float) -> np.ndarray:
    """How probable the ideal model (Eq. 1-5, with the estimated ``jammer`` if one is
    present; with hypotheses of one, the mixture of theirs by weight) makes each level at
    points ``xy`` (n, 2), give or take ``spread_db`` (``ideal_model_spread_db``): (n,
    levels); 0 where ``xy`` is NaN (a report that cannot be placed)."""
    if isinstance(jammer, JammerHypotheses):
        return sum(weight * ideal_level_probabilities(scenario, xy, estimate, spread_db)
                   for estimate, weight in _weighted(jammer))
    radio = RadioModel(scenario, shadowed=False)
    params = None if jammer is None or not jammer.present else _params_of(scenario, jammer)
    sinr_db = radio.evaluate(np.asarray(xy, dtype=np.float64), params).sinr_db[:, None]
    lower_db, upper_db = band_edges(radio, np.arange(scenario.channel.level_count))
    with np.errstate(invalid="ignore"):
        return np.exp(log_band_probability((lower_db - sinr_db) / spread_db,
                                           (upper_db - sinr_db) / spread_db))


def _weighted(jammer: JammerEstimate | JammerHypotheses) -> list[tuple[JammerEstimate, float]]:
    """A jammer's hypotheses with their weights; an estimate is one, of weight 1."""
    if isinstance(jammer, JammerHypotheses):
        return list(zip(jammer.estimates, jammer.weights.tolist(), strict=True))
    return [(jammer, 1.0)]


class _IdealLosses:
    """The ideal model's no-jammer SINR at points ``xy`` (n, 2), the GBS side worked out once,
    and the SINR each jammer hypothesis takes off it (dB): a hypothesis adds only its own
    jammer term."""

    def __init__(self, scenario: Scenario, xy: np.ndarray):
        self.scenario, self.xy = scenario, xy
        self.radio = RadioModel(scenario, shadowed=False)
        _, self._signal, self._co_channel = self.radio.serving(
            self.radio.gbs_received_power(xy))
        self.ideal_db = 10.0 * np.log10(self.radio.sinr_of(self._signal, self._co_channel, 0.0))

    def loss_db(self, estimate: JammerEstimate) -> np.ndarray:
        if not estimate.present:
            return np.zeros_like(self.ideal_db)
        jammed = self.radio.sinr_of(self._signal, self._co_channel, self.radio.jammer_interference(
            self.xy, _params_of(self.scenario, estimate)))
        return self.ideal_db - 10.0 * np.log10(jammed)


def _params_of(scenario: Scenario, estimate: JammerEstimate) -> tuple[JammerParams, ...]:
    """The radio model's jammers for a present ``estimate``, each of its set (at the
    scenario's jammer height)."""
    return tuple(JammerParams(member.x, member.y, member.power_w, scenario.jammer.height_m)
                 for member in estimate.members)


def _map_at(scenario: Scenario, map_at: Callable[[np.ndarray], np.ndarray],
            xy: np.ndarray) -> np.ndarray:
    """The no-jammer map's probabilities of each level (n, levels) at points ``xy`` (..., 2),
    from ``map_at``'s levels or probabilities."""
    return level_probabilities(map_at(xy.reshape(-1, 2)), scenario.channel.level_count)


def _corrected(scenario: Scenario, no_jammer: np.ndarray,
               jammer: JammerEstimate | JammerHypotheses, flat: np.ndarray,
               shadowing_sigma_db: float | None, report_sigma_db: float) -> np.ndarray:
    """``corrected_level_probabilities`` (n, levels) at points ``flat`` (n, 2) where the
    no-jammer map gives each level the probabilities ``no_jammer`` (n, levels). What does
    not depend on the jammer (the ideal model's SINR, the bands, the spread) is worked out
    once for all hypotheses."""
    weighted = _weighted(jammer)
    base = no_jammer.argmax(axis=-1)
    if report_sigma_db == 0.0 and not any(estimate.present for estimate, _ in weighted):
        return np.eye(scenario.channel.level_count)[base]  # what the map says, for certain
    losses = _IdealLosses(scenario, flat)
    radio, ideal_db = losses.radio, losses.ideal_db
    band_low, band_high = band_edges(radio, base)
    if shadowing_sigma_db is None:
        shadowing_sigma_db = fitted_sigma(ideal_db, band_low, band_high)
    prior_db, prior_sd_db = prior_of_map(radio, ideal_db, shadowing_sigma_db, no_jammer)
    sd_db = np.hypot(prior_sd_db, report_sigma_db)
    bounds = np.concatenate([[-np.inf], radio.level_edges_db, [np.inf]])[:, None]
    total = 0.0
    for estimate, weight in weighted:
        # With no jammer no loss: what the map says, as a receiver reports it.
        loss_db = losses.loss_db(estimate)
        # Level k needs the no-jammer SINR in [bounds_k + loss, bounds_k+1 + loss) and its band.
        low = np.maximum(band_low, bounds[:-1] + loss_db)
        high = np.minimum(band_high, bounds[1:] + loss_db)
        log_mass = log_band_probability((low - prior_db) / sd_db, (high - prior_db) / sd_db)
        mass = np.exp(log_mass - log_mass.max(axis=0))
        total = total + weight * (mass / mass.sum(axis=0)).T
    return total
