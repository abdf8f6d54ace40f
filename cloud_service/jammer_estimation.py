"""Estimating the jammer (position, power, uncertainty) from the uploads alone.

The cloud knows the GBS layout (the scenario) and the ideal radio model, Eq. (1)-(5), but not
the shadowing of the world nor the receivers' noise. An upload says where the UAV was (its GBS
features, ``positions_from_features``) and which SINR level it reported.

Model. A measurement's SINR in dB is its no-jammer SINR less the jammer's loss,
10 log10(1 + I_J / (N + I)), plus the receiver's error; the level is that quantized with the
scenario's level edges (an ordinal probit). What the cloud believes of the no-jammer SINR
(``sinr_beliefs``) is Gaussian: the ideal model's value with the world's shadowing as its
spread, ``shadowing_sigma_db``; or, given the no-jammer map's level there (learned from
measurements, so it carries the shadowing), that prior truncated to the level's band and
moment-matched. Near a level's edge a map learned from noisy reports says more than its
level: its probability of the levels below the edge is the share of reports there that fell
below, which reads the SINR to within ``MAP_READING_SD_DB``, sharper than the ideal model's
spread; the two are combined by their precisions. The receiver adds ``report_sigma_db``, which
also lumps the shadowing of the jammer's own link. Whether a jammer is there is decided at one
spread, which no world contradicts; a converged estimate is then refitted at the spread that
explains the reports best, since a spread wider than the world's reads the power wrong.

Why the no-jammer map matters. In the scenarios of this project the jammer costs at most
~2.5 dB of SINR (1 W; 0.8 dB at 0.25 W, jammer.efficiency_db = -20), less than the spread of
the world's SINR about the ideal model (2.6-2.9 dB measured in icc2021-shadowed). From the
ideal model alone a jammer cannot be told from the shadowing: 2,000 uniform measurements put
it 50-75 m off (median), with confident but wrong standard deviations. Conditioned on the
world's no-jammer levels, 8 m (power 2.7 dB high: the jammer link's log-normal shadowing
raises its mean power by ~1 dB, and the rest is the model's simplifications).

Cost. The GBS signal and interference of each measurement do not depend on the jammer, and a
level's likelihood depends on the jammer only through r, its power over the interference plus
noise (dB). So each measurement gets a table of its log-likelihood over r once; a hypothesis
then costs one distance per measurement and a table look-up per power. A coarse search over
the area (plus a margin: a jammer may stand at the edge) and log-spaced powers finds the
region; a finer grid around it gives the estimate and its uncertainty as the moments of the
likelihood-weighted (flat-prior) posterior.

Shadowing is correlated over metres, so successive measurements along a path repeat one error
rather than bring new evidence. Each measurement is weighted by one over the number of
measurements in its square of side ``independent_spacing_m``: a square counts about once, so
that the likelihood ratio and the standard deviations do not claim the certainty of
thousands of independent reports.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.special import log_ndtr, ndtr, ndtri

from shared.measurements import feature_size, features_per_gbs, scenario_features
from shared.radio import JammerParams, RadioModel
from shared.scenario import Scenario

# The model (see the module docstring); measured in icc2021-shadowed (three shadowing seeds):
# the world's no-jammer SINR about the ideal model, sd 2.6-2.9 dB; the jammer's loss about the
# ideal model's, sd 0.5-0.65 dB; receiver noise 1 dB.
SHADOWING_SIGMA_DB = 3.0  # when no no-jammer map is given to fit it (``fit_shadowing_sigma``)
REPORT_SIGMA_DB = 1.2
# A converged estimate is refitted with the report spread that explains the uploads best among
# these (maximum likelihood); whether it converged is decided at REPORT_SIGMA_DB, and so are
# the hypotheses of a provisional map (at 0.3 dB a quiet sky's exact reports showed a jammer).
# An exact receiver (icc2021) read at 1.2 dB pulls the power low on the UAVs' paths, which
# hug the jammed zone's edge: about 1.7 W for a 2 W jammer, 0.8 W for 1 W (1.95 W and 0.98 W
# refitted, BENCHMARKS.md); icc2021-shadowed's uploads choose 1.2 dB.
REPORT_SIGMA_CHOICES_DB = (0.3, 0.6, REPORT_SIGMA_DB)
OUTLIER_SHARE = 0.01  # reports that may contradict the model (a deep shadow, a map error)
# Reading the SINR off a no-jammer map's probabilities near a level's edge (``_prior_of_map``):
# the probability of the levels below the edge, s, puts the SINR at edge - REPORT_SIGMA_DB *
# probit(s), the ordinal probit of the reports the map learned from, give or take
# MAP_READING_SD_DB (the network's smoothing and calibration); a share beyond MAP_SHARE_READ
# of 0 or 1 says only which side of the edge. bench_correction (icc2021-shadowed's survey map
# corrected with the true jammer, flown), success at (0,0) 1 W / (-30,10) 1 W: by the map's
# level alone 94.9 / 81.9 %, as uncorrected (it moved no level, where the jammer moves
# 11.6-13.6 % of them); read at (0.02, 1 dB) 94.6 / 91.0 %, (0.005, 1 dB) 94.6 / 91.1 %,
# (0.001, 0.5 dB) 94.8 / 94.0 %, no better at 0.3 dB or 0.0001; the true map 98.6 / 97.1 %.
MAP_READING_SD_DB = 0.5
MAP_SHARE_READ = 0.001
INDEPENDENT_SPACING_M = 3.0

# The search (see ``estimate_jammer``).
SEARCH_MARGIN_M = 10.0  # beyond the area: a jammer may stand at its edge or just outside
COARSE_SPACING_M = 5.0
COARSE_POWER_STEP_DB = 1.0
POWER_SEARCH_DB = 10.0  # searched below and above the training range of nominal powers
FINE_NODES = 13  # per side and per power of the refining grid

# The decision (see ``estimate_jammer``).
MIN_MEASUREMENTS = 30
# 15 m let through fits 20 m off with the power 7 dB high from 10 s of four flights (4 of 50
# settings); at 10 m one is left, and 60 s of flights lose 2 of 21 converged estimates.
MAX_POSITION_SD_M = 10.0
PRESENCE_LLR = 4.0
EXCLUSION_LLR = 1.0
# While no estimate converges, the hypotheses behind a provisional map: the most probable
# coarse ones holding this share of the posterior, at most this many (each costs the map one
# evaluation of the radio model over its prior points).
HYPOTHESES_MASS = 0.95
MOST_HYPOTHESES = 64
# A change was detected already: hypotheses need only explain the uploads better than no
# jammer does, by this much (nats), not prove one present (PRESENCE_LLR). bench_adaptation,
# icc2021, 20 changes, first provisional map: at 1.0 a median 9 s after the change, 94.8 %
# right (the survey map: 94.0 % in the same settings); at 2.0, 30 s and 95.8 %; at 4.0, 35 s.
HYPOTHESES_LLR = 1.0
# A provisional map keeps the survey map's level where the hypotheses leave it at least this
# probable (``corrected_levels``). bench_adaptation (icc2021, 20 changes), first provisional
# map's median accuracy: 94.8 % at 0.5, 95.2 % at 0.3 (accuracy 30 s on: 96.6 % and 96.2 %);
# icc2021-shadowed 79.3 % at both.
SURVEY_LEVEL_KEPT = 0.5

# Offsets that agree to this (mean, metres) are the same place: float32 features of points
# within ~100 m carry ~1e-5 m of rounding.
_SAME_PLACE_M = 1e-3
_RATIO_STEP_DB = 0.1  # resolution of the per-measurement likelihood tables over r
# Below -30 dB the jammer moves the SINR by under 0.005 dB; at +30 dB it has cut it by 30 dB,
# which leaves nothing but level 0. Beyond these the likelihood no longer changes with r.
_RATIO_RANGE_DB = (-30.0, 30.0)
_SINR_STEP_DB = 0.05  # resolution of the level tables over the SINR
_SINR_RANGE_DB = (-60.0, 40.0)  # beyond, every level's probability is at its limit
_SD_STEP_DB = 0.05  # spreads are rounded to this to share level tables
# A dB report's table spans its offsets from the believed SINR this far either way: past it
# every spread in use leaves only the outlier floor.
_OFFSET_RANGE_DB = 40.0
# An outlier dB report (a deep shadow, a map error) is taken as uniform over this span of
# SINRs, about what the area's SINRs span.
_OUTLIER_SPAN_DB = 40.0
# Hypotheses x measurements per vectorized block: its temporaries stay near the CPU cache.
_BLOCK_ELEMENTS = 2**20


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


class SinrBelief(NamedTuple):
    """What the cloud believes of the world's no-jammer SINR at some points (Gaussian, dB)."""

    mean_db: np.ndarray
    sd_db: np.ndarray


def positions_from_features(scenario: Scenario, features: np.ndarray) -> np.ndarray:
    """UAV positions (n, 2) that produced the uploaded ``features`` (n, ``feature_size``).

    Each GBS in turn (or only the one the features name, with ``policy.nearest_gbs_position``)
    is taken as the nearest one: the UAV then sits at that GBS minus the
    first (dx, dy). The candidate kept is the one whose own K_n nearest GBSs lie at the
    uploaded offsets, exact to the features' float32 precision. Offsets are compared as
    sorted lists of dx and of dy, so GBSs at equal distance (whose order rounding may swap)
    do not matter. A row is NaN where no place gives its offsets (features of another
    layout, or tampered with), and where two places do: with K_n below the GBS count a
    regular layout repeats itself, and places a lattice step apart see the same nearest
    offsets (with every GBS in view, as in icc2021, none do; naming the nearest GBS, as the
    city does, settles it).
    """
    nearby, per_gbs = scenario.policy.nearby_gbs, features_per_gbs(scenario)
    flat = np.asarray(features, dtype=np.float64).reshape(-1, feature_size(scenario))
    features = flat[:, :nearby * per_gbs].reshape(-1, nearby, per_gbs)
    if scenario.policy.nearest_gbs_position:  # the measurement names its nearest GBS
        nearest = flat[:, None, -2:]
    else:
        gbs_xy = np.asarray(scenario.gbs.positions, dtype=np.float64)
        nearest = np.broadcast_to(gbs_xy, (len(flat), *gbs_xy.shape))
    candidates = nearest - features[:, None, 0, :2]  # (n, candidates, 2)
    seen = scenario_features(scenario, candidates)[..., :nearby * per_gbs].reshape(
        *candidates.shape[:2], nearby, per_gbs)
    uploaded = np.sort(features[:, None, :, :2], axis=2)
    miss = np.abs(np.sort(seen[..., :2], axis=2) - uploaded).mean(axis=(2, 3))
    rows = np.arange(len(features))
    xy = candidates[rows, miss.argmin(axis=1)]
    elsewhere = np.abs(candidates - xy[:, None, :]).max(-1) > _SAME_PLACE_M
    ambiguous = ((miss < _SAME_PLACE_M) & elsewhere).any(axis=1)
    xy[ambiguous | (miss.min(axis=1) > _SAME_PLACE_M)] = np.nan
    return xy


def sinr_beliefs(
    radio: RadioModel, xy: np.ndarray, no_jammer_levels: np.ndarray | None = None,
    shadowing_sigma_db: float | None = None, reference: SinrBelief | None = None,
) -> SinrBelief:
    """The world's no-jammer SINR at points ``xy`` (n, 2): the ideal model's, give or take
    ``shadowing_sigma_db``; with the no-jammer map there, ``no_jammer_levels`` (its levels
    (n,) or its probabilities of each level (n, levels)), that prior sharpened by what the
    map's probabilities read near a level's edge (``_prior_of_map``) and truncated to its
    most probable level's band (the mean and sd). A sigma of None is fitted to the map's
    levels (``fit_shadowing_sigma``), or else ``SHADOWING_SIGMA_DB``. Where ``reference``
    holds what was measured at a point with no jammer (a mean and sd; NaN where nothing
    was), the ideal model's prior combined with that instead."""
    mean_db = radio.evaluate(xy).sinr_db
    if no_jammer_levels is None:
        sigma_db = SHADOWING_SIGMA_DB if shadowing_sigma_db is None else shadowing_sigma_db
        belief = SinrBelief(mean_db, np.full_like(mean_db, sigma_db))
    else:
        probabilities = _level_probabilities(no_jammer_levels, len(radio.level_edges_db) + 1)
        lower_db, upper_db = _band_edges(radio, probabilities.argmax(axis=-1))
        if shadowing_sigma_db is None:
            shadowing_sigma_db = _fitted_sigma(mean_db, lower_db, upper_db)
        belief = _truncated_normal(
            *_prior_of_map(radio, mean_db, shadowing_sigma_db, probabilities), lower_db,
            upper_db)
    if reference is None:
        return belief
    # The SINR measured there with no jammer, where it was: the ideal model's prior sharpened
    # by it, not confined to the map's band, which the map gets wrong where it errs.
    sigma_db = SHADOWING_SIGMA_DB if shadowing_sigma_db is None else shadowing_sigma_db
    known = np.isfinite(reference.mean_db)
    precision = sigma_db**-2.0 + np.where(known, reference.sd_db, np.inf) ** -2.0
    referenced = (sigma_db**-2.0 * mean_db + np.where(
        known, reference.mean_db / np.where(known, reference.sd_db, 1.0) ** 2, 0.0)) / precision
    return SinrBelief(np.where(known, referenced, belief.mean_db),
                      np.where(known, precision**-0.5, belief.sd_db))


def _level_probabilities(levels_or_probabilities: np.ndarray, level_count: int) -> np.ndarray:
    """A no-jammer map's probabilities of each level (n, levels), given them or its levels
    (n,), which it is then certain of."""
    given = np.asarray(levels_or_probabilities)
    if given.ndim == 2:
        return given.astype(np.float64)
    return np.eye(level_count)[given.astype(np.int64).reshape(-1)]


def report_shares(radio: RadioModel, sinr_db: np.ndarray,
                  report_sigma_db: float = REPORT_SIGMA_DB) -> np.ndarray:
    """The share of reports at each level (..., levels) where the SINR is ``sinr_db`` and a
    report errs by N(0, report_sigma_db^2): what a map learned from many reports there gives
    at best, and what ``_prior_of_map`` reads back."""
    bounds = np.concatenate([[-np.inf], radio.level_edges_db, [np.inf]])
    below = ndtr((bounds - np.asarray(sinr_db)[..., None]) / report_sigma_db)
    return np.diff(below, axis=-1)


def map_reading(radio: RadioModel, probabilities: np.ndarray,
                report_sigma_db: float = REPORT_SIGMA_DB) -> tuple[np.ndarray, np.ndarray]:
    """Where a map's ``probabilities`` (n, levels) of the levels reported put the SINR (dB,
    (n,)): at the level edge whose share of reports below is nearest a half, edge -
    report_sigma_db x probit(share), the ordinal probit of reports erring by
    N(0, report_sigma_db^2); and whether that share says more than which side of the edge
    (within ``MAP_SHARE_READ`` of neither 0 nor 1)."""
    below = np.cumsum(probabilities, axis=-1)[:, :-1]  # share below each edge
    edge = np.abs(below - 0.5).argmin(axis=-1)
    share = below[np.arange(len(below)), edge]
    read = (share > MAP_SHARE_READ) & (share < 1.0 - MAP_SHARE_READ)
    reading_db = radio.level_edges_db[edge] - report_sigma_db * ndtri(
        np.clip(share, MAP_SHARE_READ, 1.0 - MAP_SHARE_READ))
    return reading_db, read


def _prior_of_map(radio: RadioModel, ideal_db: np.ndarray, shadowing_sigma_db: float,
                  probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sd (n,) of the no-jammer SINR before the map's band is imposed: the ideal
    model's N(ideal_db, shadowing_sigma_db^2) combined, by precision, with what the map's
    ``probabilities`` (n, levels) read near the level edge whose share below is nearest a
    half (see ``MAP_READING_SD_DB``). Where the map is certain (a share beyond
    ``MAP_SHARE_READ``, as with levels given) the ideal model's prior stands alone."""
    reading_db, read = map_reading(radio, probabilities)
    prior_precision = shadowing_sigma_db**-2.0
    map_precision = np.where(read, MAP_READING_SD_DB**-2.0, 0.0)
    precision = prior_precision + map_precision
    mean_db = (prior_precision * ideal_db + map_precision * reading_db) / precision
    return mean_db, precision**-0.5


def fit_shadowing_sigma(radio: RadioModel, xy: np.ndarray, no_jammer_levels: np.ndarray):
    """How far the world departs from the ideal model: the sd (dB) of its no-jammer SINR
    about the ideal one that best explains the no-jammer map's levels at ``xy`` (n, 2)
    (maximum likelihood over ``_SIGMA_CHOICES_DB``). The cloud learns it from its own map,
    never from the world: measured, 0.01 dB (the least tried) with the map of icc2021,
    3.5 dB with icc2021-shadowed's true no-jammer levels and 6.3 dB with the network
    learned there (its own errors add to the shadowing)."""
    lower_db, upper_db = _band_edges(radio, np.asarray(no_jammer_levels, dtype=np.int64))
    return _fitted_sigma(radio.evaluate(xy).sinr_db, lower_db, upper_db)


_SIGMA_CHOICES_DB = np.geomspace(0.01, 10.0, 61)  # 12 % apart
_SIGMA_FIT_POINTS = 2000  # a stride through more points: the fit needs no more


def sigma_fit_sample(rows: np.ndarray) -> np.ndarray:
    """The rows of points (or of values at them) that ``fit_shadowing_sigma`` reads: a stride
    through them. A caller that labels points for it need label no others."""
    return rows[:: max(1, len(rows) // _SIGMA_FIT_POINTS)]


def _fitted_sigma(ideal_db: np.ndarray, lower_db: np.ndarray, upper_db: np.ndarray) -> float:
    ideal_db, lower_db, upper_db = (sigma_fit_sample(v) for v in (ideal_db, lower_db, upper_db))
    sigmas = _SIGMA_CHOICES_DB[:, None]
    log_model = _log_band_probability((lower_db - ideal_db) / sigmas,
                                      (upper_db - ideal_db) / sigmas)
    # The map's own errors are outliers, not shadowing: the floor keeps them from ruling.
    floor = math.log(OUTLIER_SHARE / 3.0)
    score = np.logaddexp(math.log1p(-OUTLIER_SHARE) + log_model, floor).sum(axis=1)
    return float(_SIGMA_CHOICES_DB[score.argmax()])


def _band_edges(radio: RadioModel, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    bounds = np.concatenate([[-np.inf], radio.level_edges_db, [np.inf]])
    return bounds[levels], bounds[levels + 1]


def _truncated_normal(mean: np.ndarray, sd: float | np.ndarray, lower: np.ndarray,
                      upper: np.ndarray):
    """Mean and sd of N(mean, sd^2) restricted to [lower, upper), stable far in the tails."""
    a, b = (lower - mean) / sd, (upper - mean) / sd
    log_mass = _log_band_probability(a, b)
    # phi(z) / mass and z phi(z) / mass, zero at an infinite bound.
    with np.errstate(invalid="ignore"):
        density_a = np.where(np.isfinite(a), np.exp(-0.5 * a * a - _LOG_SQRT_2PI - log_mass), 0.0)
        density_b = np.where(np.isfinite(b), np.exp(-0.5 * b * b - _LOG_SQRT_2PI - log_mass), 0.0)
        moment_a = np.where(np.isfinite(a), a * density_a, 0.0)
        moment_b = np.where(np.isfinite(b), b * density_b, 0.0)
    shift = density_a - density_b
    # Deep in a tail the variance formula cancels to rounding noise: keep a floor of 5 %.
    variance = np.maximum(1.0 + moment_a - moment_b - shift * shift, 0.0025)
    return SinrBelief(mean + sd * shift, sd * np.sqrt(variance))


_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def _log_band_probability(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """log(Phi(upper) - Phi(lower)), taken in the tail where the difference does not
    cancel; -inf for an empty band."""
    flip = lower + upper > 0
    lower, upper = np.where(flip, -upper, lower), np.where(flip, -lower, upper)
    log_upper = log_ndtr(upper)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        out = log_upper + np.log1p(-np.exp(log_ndtr(lower) - log_upper))
    return np.where(upper > lower, out, -np.inf)


def independence_weights(xy: np.ndarray, spacing_m: float) -> np.ndarray:
    """One over the number of measurements in each one's square of side ``spacing_m``."""
    cells = np.floor(xy / spacing_m).astype(np.int64)
    _, cell_of, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    return 1.0 / counts[cell_of.reshape(-1)]


class _ReportTables:
    """log P(report | believed SINR, spread), with the outlier floor, tabulated over the SINR
    for every spread in use (rounded to ``_SD_STEP_DB``, so that a few tables serve thousands
    of measurements). A level report's is the ordinal probit's: the probability of the
    level's band. A dB report's (the SINR in steps of ``step_db``) is the probability of its
    step's interval, a function of the report less the SINR, tabulated over that."""

    def __init__(self, edges_db: np.ndarray, sds_db: np.ndarray, outlier_share: float,
                 step_db: float | None):
        rounded, self.table_of = np.unique(np.rint(sds_db / _SD_STEP_DB), return_inverse=True)
        self.table_of = self.table_of.reshape(-1)
        sinr_db = np.arange(*_SINR_RANGE_DB, _SINR_STEP_DB)
        self.sinr_count = len(sinr_db)
        bounds = np.concatenate([[-np.inf], edges_db, [np.inf]])
        self.level_count = len(bounds) - 1
        spread = (rounded * _SD_STEP_DB)[:, None, None]
        self.values = _with_outliers(
            _log_band_probability((bounds[:-1, None] - sinr_db) / spread,
                                  (bounds[1:, None] - sinr_db) / spread),
            outlier_share, 1.0 / self.level_count).ravel()
        self.step_db = step_db
        if step_db is not None:  # offsets of a report from the SINR, as for the SINR above
            offsets_db = np.arange(-_OFFSET_RANGE_DB, _OFFSET_RANGE_DB, _SINR_STEP_DB)
            spread = spread[:, 0]
            self.db_values = _with_outliers(
                _log_band_probability((offsets_db - step_db / 2.0) / spread,
                                      (offsets_db + step_db / 2.0) / spread),
                outlier_share, step_db / _OUTLIER_SPAN_DB).ravel()
            self.offset_count = len(offsets_db)

    def log_probability(self, sinr_db: np.ndarray, levels: np.ndarray, rows: np.ndarray,
                        reported_db: np.ndarray | None = None):
        """For measurement ``rows`` (their spreads), reported ``levels`` and, where finite,
        SINRs ``reported_db``, at believed SINRs ``sinr_db`` (any broadcastable shapes)."""
        step = np.rint((sinr_db - _SINR_RANGE_DB[0]) / _SINR_STEP_DB).astype(np.int64)
        np.clip(step, 0, self.sinr_count - 1, out=step)
        table = self.table_of[rows] * self.level_count + levels
        by_level = self.values[table * self.sinr_count + step]
        if reported_db is None or self.step_db is None:
            return by_level
        reported = np.isfinite(reported_db)
        if not reported.any():
            return by_level
        offset = np.rint((np.where(reported, reported_db, 0.0) - sinr_db + _OFFSET_RANGE_DB)
                         / _SINR_STEP_DB).astype(np.int64)
        np.clip(offset, 0, self.offset_count - 1, out=offset)
        by_db = self.db_values[self.table_of[rows] * self.offset_count + offset]
        return np.where(reported, by_db, by_level)


def _with_outliers(log_model: np.ndarray, outlier_share: float,
                   outlier_probability: float) -> np.ndarray:
    """A report's log-probability when a share ``outlier_share`` of reports contradicts the
    model and falls anywhere, with probability ``outlier_probability``."""
    return np.logaddexp(math.log1p(-outlier_share) + log_model,
                        math.log(outlier_share * outlier_probability))


class _Evidence:
    """The measurements, reduced to what a jammer hypothesis needs: each one's weighted
    log-likelihood tabulated over r, the jammer's power over the ideal GBS interference plus
    noise (dB). The tables span ``_RATIO_RANGE_DB`` widened by ``power_span_db`` on both
    sides, so that one call's powers, up to that span apart, read them without clipping."""

    def __init__(
        self, radio: RadioModel, jammer_height_m: float, reports: Reports, weights: np.ndarray,
        belief: SinrBelief, report_sigma_db: float, outlier_share: float, power_span_db: float,
    ):
        xy, levels, reported_db = reports.xy, reports.levels, reports.sinr_db
        self.xy = xy
        self.report_sigma_db = report_sigma_db
        _, _, co_channel = radio.serving(radio.gbs_received_power(xy))
        self.interference_db = 10.0 * np.log10(radio.noise_w + co_channel)
        self.gap_m = radio.altitude_m - jammer_height_m
        self.slope_db = 5.0 * (radio.alpha + 1.0)  # I_J ~ slant_sq ** -((alpha + 1) / 2)
        self.ratio_low_db = _RATIO_RANGE_DB[0] - power_span_db
        ratios_db = np.arange(self.ratio_low_db, _RATIO_RANGE_DB[1] + power_span_db,
                              _RATIO_STEP_DB)
        loss_db = 10.0 * np.log10(1.0 + 10.0 ** (ratios_db / 10.0))  # SINR lost to the jammer
        tables = _ReportTables(radio.level_edges_db, np.hypot(belief.sd_db, report_sigma_db),
                               outlier_share, reports.step_db)
        rows = np.arange(len(xy))
        table = tables.log_probability(belief.mean_db[:, None] - loss_db, levels[:, None],
                                       rows[:, None], reported_db[:, None])
        self.table = (weights[:, None] * table).astype(np.float32).ravel()
        self.ratio_count = len(ratios_db)
        self.row_start = (rows * self.ratio_count).astype(np.int32)
        self.no_jammer = float(weights @ tables.log_probability(belief.mean_db, levels, rows,
                                                                reported_db))

    def log_likelihood_ratios(self, positions: np.ndarray, powers_dbw: np.ndarray) -> np.ndarray:
        """Log-likelihood of a jammer at each of ``positions`` (H, 2) with each effective
        power ``powers_dbw`` (P,), less that of no jammer: shape (H, P). Powers are read to
        the table's step and may span at most the ``power_span_db`` the tables were made for."""
        power_steps = np.rint((powers_dbw - powers_dbw.min()) / _RATIO_STEP_DB).astype(np.int32)
        lowest_at = self.ratio_low_db - powers_dbw.min()  # path gain read at column 0
        out = np.empty((len(positions), len(powers_dbw)))
        per_block = max(1, _BLOCK_ELEMENTS // (len(powers_dbw) * len(self.xy)))
        for start in range(0, len(positions), per_block):
            block = positions[start : start + per_block]
            offset = block[:, None, :] - self.xy
            slant_sq = (offset * offset).sum(-1) + self.gap_m**2
            gain_db = (10.0 * math.log10(self.gap_m) - self.slope_db * np.log10(slant_sq)
                       - self.interference_db)
            # Beyond the tables the likelihood no longer changes with r: clipping is exact.
            lowest = np.clip(np.rint((gain_db - lowest_at) / _RATIO_STEP_DB),
                             0, self.ratio_count - 1 - power_steps.max()).astype(np.int32)
            index = (lowest + self.row_start)[:, None, :] + power_steps[:, None]
            out[start : start + len(block)] = self.table[index].sum(axis=-1)
        return out - self.no_jammer


def estimate_jammer(
    scenario: Scenario,
    xy: np.ndarray,
    levels: np.ndarray,
    *,
    reported_db: np.ndarray | None = None,
    no_jammer_levels: np.ndarray | None = None,
    no_jammer_db: SinrBelief | None = None,
    shadowing_sigma_db: float | None = None,
    report_sigma_db: float = REPORT_SIGMA_DB,
    outlier_share: float = OUTLIER_SHARE,
    independent_spacing_m: float = INDEPENDENT_SPACING_M,
    min_measurements: int = MIN_MEASUREMENTS,
    max_position_sd_m: float = MAX_POSITION_SD_M,
    presence_llr: float = PRESENCE_LLR,
    exclusion_llr: float = EXCLUSION_LLR,
) -> JammerEstimate | None:
    """The jammer (at the scenario's jammer height) that best explains the reported
    ``levels`` (n,), and SINRs ``reported_db`` (n,) where they are finite, at positions
    ``xy`` (n, 2), or None when the data cannot pin it down.
    ``no_jammer_levels``: the no-jammer map's level (n,), or better its probability of each
    level (n, levels), at each position, which the
    estimate should be given whenever the world may differ from the ideal model (see the
    module docstring). Rows with a NaN position are ignored.

    Search: every ``COARSE_SPACING_M`` over the area plus ``SEARCH_MARGIN_M``, nominal powers
    every ``COARSE_POWER_STEP_DB`` from ``POWER_SEARCH_DB`` below the scenario's training
    range to as far above it; then ``FINE_NODES`` per side and per power around the best,
    three coarse posterior standard deviations (at least one coarse step) each way. The
    estimate is the mean of the fine posterior, its standard deviations those of the
    posterior.

    Decision, on the weighted log-likelihood ratio (LLR) of a jammer against none:
    - fewer than ``min_measurements`` rows with a position: None;
    - best coarse LLR below ``presence_llr``: no jammer (``present`` false) if the data rules
      out a jammer of the training range's middle power (geometric mean) everywhere in the
      area (its LLR below ``-exclusion_llr`` at every coarse node there); otherwise None, as
      the data has not looked everywhere a jammer may be. A weaker jammer may remain: at
      the range's lowest power (0.25 W in icc2021) it costs under 1 dB of SINR, which the
      shadowing hides even from 2,000 measurements over the whole area;
    - best coarse hypothesis on the edge of the search (position on the outer ring, power
      the lowest or the highest searched), or a posterior position standard deviation along
      the least certain direction above ``max_position_sd_m``: None;
    - otherwise the estimate.

    ``shadowing_sigma_db``: sd of the world's no-jammer SINR about the ideal model's; None
    fits it to ``no_jammer_levels`` (``fit_shadowing_sigma``), or without them takes
    ``SHADOWING_SIGMA_DB``. ``report_sigma_db``: what a report adds once that SINR is
    known (receiver noise, the jammer link's own shadowing): whether a jammer is found is
    decided at it, and an estimate is then refitted with the spread among
    ``REPORT_SIGMA_CHOICES_DB`` that explains the reports best (``_refitted``).
    """

    reports = Reports.of(scenario, xy, levels, reported_db)

    def search_at(sigma_db: float) -> _Searched | None:
        return _coarse_search(scenario, reports, no_jammer_levels, no_jammer_db,
                              shadowing_sigma_db, sigma_db, outlier_share,
                              independent_spacing_m, min_measurements)

    searched = search_at(report_sigma_db)
    if searched is None:
        return None
    estimate = _decide(scenario, searched, presence_llr, exclusion_llr, max_position_sd_m)
    return _refitted(scenario, searched, estimate, search_at)


def _refitted(scenario: Scenario, searched: _Searched, estimate: JammerEstimate | None,
              search_at: Callable[[float], _Searched | None]) -> JammerEstimate | None:
    """A converged ``estimate`` of ``searched`` refined again on the coarse search (of
    ``search_at`` a report spread) of ``REPORT_SIGMA_CHOICES_DB`` whose best hypothesis
    explains the reports best, if that is not ``searched``'s own; anything else as it is."""
    if estimate is None or not estimate.present:
        return estimate
    best, best_log_likelihood = searched, searched.evidence.no_jammer + float(searched.llr.max())
    for sigma_db in REPORT_SIGMA_CHOICES_DB:
        if sigma_db == searched.evidence.report_sigma_db:
            continue
        other = search_at(sigma_db)
        log_likelihood = other.evidence.no_jammer + float(other.llr.max())
        if log_likelihood > best_log_likelihood:
            best, best_log_likelihood = other, log_likelihood
    if best is searched:
        return estimate
    fine, fine_llr = _refine(best.evidence, best.search, best.llr)
    return _present(scenario, fine, len(best.evidence.xy), fine_llr)


def _decide(scenario: Scenario, searched: _Searched, presence_llr: float, exclusion_llr: float,
            max_position_sd_m: float) -> JammerEstimate | None:
    """``estimate_jammer``'s decision on a coarse search."""
    evidence, search, llr = searched
    if llr.max() < presence_llr:
        excluded = llr[search.in_area, search.middle_of_range] < -exclusion_llr
        return _absent(len(evidence.xy), float(llr.max())) if excluded.all() else None
    best_position, best_power = np.unravel_index(llr.argmax(), llr.shape)
    if search.on_edge[best_position] or best_power in (0, len(search.powers_dbw) - 1):
        return None
    fine, fine_llr = _refine(evidence, search, llr)
    if fine.worst_sd_m > max_position_sd_m:
        return None
    return _present(scenario, fine, len(evidence.xy), fine_llr)


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


def jammer_hypotheses(
    scenario: Scenario,
    xy: np.ndarray,
    levels: np.ndarray,
    *,
    reported_db: np.ndarray | None = None,
    no_jammer_levels: np.ndarray | None = None,
    no_jammer_db: SinrBelief | None = None,
    mass: float = HYPOTHESES_MASS,
    most: int = MOST_HYPOTHESES,
    presence_llr: float = HYPOTHESES_LLR,
    report_sigma_db: float = REPORT_SIGMA_DB,
) -> JammerHypotheses | None:
    """The fewest coarse hypotheses (at most ``most``) that hold ``mass`` of the posterior of
    a jammer of the scenario's expected powers, when one explains the uploads better than
    none (best LLR at least ``presence_llr``); None otherwise.
    The same search and model as ``estimate_jammer``, which answers None in that case when
    the posterior is too wide."""
    searched = _default_search(scenario, Reports.of(scenario, xy, levels, reported_db),
                               no_jammer_levels, no_jammer_db, report_sigma_db)
    if searched is None:
        return None
    return _hypotheses(scenario, searched, mass, most, presence_llr)


class JammerFit(NamedTuple):
    estimate: JammerEstimate | None  # as ``estimate_jammer``
    hypotheses: JammerHypotheses | None  # as ``jammer_hypotheses``, when no estimate converged


def locate_jammer(scenario: Scenario, xy: np.ndarray, levels: np.ndarray, *,
                  reported_db: np.ndarray | None = None,
                  no_jammer_levels: np.ndarray | None = None,
                  no_jammer_db: SinrBelief | None = None,
                  report_sigma_db: float = REPORT_SIGMA_DB) -> JammerFit:
    """``estimate_jammer`` and, if it gives no estimate, ``jammer_hypotheses``, both with
    their defaults but ``report_sigma_db``, from one coarse search (most of the cost of
    each)."""
    reports = Reports.of(scenario, xy, levels, reported_db)
    searched = _default_search(scenario, reports, no_jammer_levels, no_jammer_db,
                               report_sigma_db)
    if searched is None:
        return JammerFit(None, None)
    estimate = _decide(scenario, searched, PRESENCE_LLR, EXCLUSION_LLR, MAX_POSITION_SD_M)
    if estimate is not None:
        return JammerFit(_refitted(scenario, searched, estimate, lambda sigma_db: _default_search(
            scenario, reports, no_jammer_levels, no_jammer_db, sigma_db)), None)
    return JammerFit(None, _hypotheses(scenario, searched, HYPOTHESES_MASS, MOST_HYPOTHESES,
                                       HYPOTHESES_LLR))


def _hypotheses(scenario: Scenario, searched: _Searched, mass: float, most: int,
                presence_llr: float) -> JammerHypotheses | None:
    """``jammer_hypotheses`` on a coarse search."""
    evidence, search, llr = searched
    # Early on, a far stronger jammer farther off explains the few contradicting reports as
    # well as the right one, and it would darken the whole map: a provisional map weighs only
    # the powers the scenario expects (its training range).
    low_w, high_w = scenario.training.jammer_power_range_w
    nominal_w = 10.0 ** ((search.powers_dbw - scenario.jammer.efficiency_db) / 10.0)
    expected = (nominal_w >= low_w * (1 - 1e-9)) & (nominal_w <= high_w * (1 + 1e-9))
    llr = np.where(expected, llr, -np.inf)
    if llr.max() < presence_llr:
        return None
    weight = np.exp(llr - llr.max()).ravel()
    weight /= weight.sum()
    order = np.argsort(weight)[::-1]
    kept = order[: min(most, int(np.searchsorted(np.cumsum(weight[order]), mass)) + 1)]
    positions, powers = np.unravel_index(kept, llr.shape)
    estimates = [
        _present(scenario, _Posterior(*search.positions[p], search.powers_dbw[k],
                                      np.zeros((2, 2)), 0.0),
                 len(evidence.xy), float(llr[p, k]))
        for p, k in zip(positions.tolist(), powers.tolist(), strict=True)]
    return JammerHypotheses(estimates, weight[kept] / weight[kept].sum())


class _Searched(NamedTuple):
    evidence: _Evidence
    search: _CoarseSearch
    llr: np.ndarray  # (positions, powers): weighted LLR of each hypothesis against none


def _default_search(scenario: Scenario, reports: Reports, no_jammer_levels: np.ndarray | None,
                    no_jammer_db: SinrBelief | None,
                    report_sigma_db: float = REPORT_SIGMA_DB) -> _Searched | None:
    """``_coarse_search`` with ``estimate_jammer``'s defaults."""
    return _coarse_search(scenario, reports, no_jammer_levels, no_jammer_db, None,
                          report_sigma_db, OUTLIER_SHARE, INDEPENDENT_SPACING_M,
                          MIN_MEASUREMENTS)


def _coarse_search(scenario: Scenario, reports: Reports, no_jammer_levels: np.ndarray | None,
                   no_jammer_db: SinrBelief | None, shadowing_sigma_db: float | None,
                   report_sigma_db: float,
                   outlier_share: float, independent_spacing_m: float,
                   min_measurements: int) -> _Searched | None:
    """The evidence of the located rows, the coarse search and its LLRs (positions x
    powers); None with fewer than ``min_measurements`` located rows."""
    located = np.isfinite(reports.xy).all(axis=1)
    reports = reports.take(located)
    if no_jammer_levels is not None:
        no_jammer_levels = np.asarray(no_jammer_levels)[located]  # levels or probabilities
    if no_jammer_db is not None:
        no_jammer_db = SinrBelief(no_jammer_db.mean_db[located], no_jammer_db.sd_db[located])
    if len(reports.xy) < min_measurements:
        return None
    radio = RadioModel(scenario, shadowed=False)
    search = _CoarseSearch.of(scenario)
    evidence = _Evidence(
        radio, scenario.jammer.height_m, reports,
        independence_weights(reports.xy, independent_spacing_m),
        sinr_beliefs(radio, reports.xy, no_jammer_levels, shadowing_sigma_db, no_jammer_db),
        report_sigma_db, outlier_share, np.ptp(search.powers_dbw))
    return _Searched(evidence, search,
                     evidence.log_likelihood_ratios(search.positions, search.powers_dbw))


def _refine(evidence: _Evidence, search: _CoarseSearch, llr: np.ndarray):
    """The posterior on a finer grid around the best coarse hypothesis, and its best LLR."""
    best_position, best_power = np.unravel_index(llr.argmax(), llr.shape)
    coarse = _Posterior.of(search.positions, search.powers_dbw, llr)
    positions = _square_grid(
        search.positions[best_position], max(COARSE_SPACING_M, 3.0 * coarse.worst_sd_m))
    powers_dbw = search.powers_dbw[best_power] + np.linspace(-1.0, 1.0, FINE_NODES) * max(
        COARSE_POWER_STEP_DB, 3.0 * coarse.sd_power_db)
    fine_llr = evidence.log_likelihood_ratios(positions, powers_dbw)
    return _Posterior.of(positions, powers_dbw, fine_llr), float(fine_llr.max())


def _absent(measurements: int, llr: float) -> JammerEstimate:
    return JammerEstimate(False, None, None, None, None, None, None, None, measurements, llr)


def _present(scenario: Scenario, fit: _Posterior, measurements: int, llr: float):
    return JammerEstimate(
        present=True, x=fit.x, y=fit.y,
        power_w=10.0 ** ((fit.power_dbw - scenario.jammer.efficiency_db) / 10.0),
        effective_power_dbm=fit.power_dbw + 30.0,
        sd_x_m=math.sqrt(fit.cov_xy[0, 0]), sd_y_m=math.sqrt(fit.cov_xy[1, 1]),
        sd_power_db=fit.sd_power_db, measurements=measurements, log_likelihood_ratio=llr,
        cov_xy_m2=float(fit.cov_xy[0, 1]))


class _Posterior(NamedTuple):
    """Likelihood-weighted moments over a grid of hypotheses (flat prior in x, y and dB)."""

    x: float
    y: float
    power_dbw: float
    cov_xy: np.ndarray  # (2, 2), m^2
    sd_power_db: float

    @property
    def worst_sd_m(self) -> float:
        """Standard deviation along the position's least certain direction."""
        return math.sqrt(max(float(np.linalg.eigvalsh(self.cov_xy)[-1]), 0.0))

    @classmethod
    def of(cls, positions: np.ndarray, powers_dbw: np.ndarray, llr: np.ndarray) -> _Posterior:
        weight = np.exp(llr - llr.max())
        weight /= weight.sum()
        position_weight, power_weight = weight.sum(axis=1), weight.sum(axis=0)
        mean_xy = position_weight @ positions
        centred = positions - mean_xy
        cov_xy = (centred * position_weight[:, None]).T @ centred
        mean_power = float(power_weight @ powers_dbw)
        sd_power = math.sqrt(max(float(power_weight @ (powers_dbw - mean_power) ** 2), 0.0))
        return cls(float(mean_xy[0]), float(mean_xy[1]), mean_power, cov_xy, sd_power)


class _CoarseSearch(NamedTuple):
    positions: np.ndarray  # (H, 2)
    on_edge: np.ndarray  # (H,) bool: the outer ring of the search
    in_area: np.ndarray  # (H,) bool: inside the scenario's area
    powers_dbw: np.ndarray  # (P,) effective powers
    middle_of_range: int  # index of the training range's middle power (in dB)

    @classmethod
    def of(cls, scenario: Scenario) -> _CoarseSearch:
        area = scenario.area
        xs = _spaced(area.x_min - SEARCH_MARGIN_M, area.x_max + SEARCH_MARGIN_M, COARSE_SPACING_M)
        ys = _spaced(area.y_min - SEARCH_MARGIN_M, area.y_max + SEARCH_MARGIN_M, COARSE_SPACING_M)
        positions = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        on_edge = np.isin(positions[:, 0], xs[[0, -1]]) | np.isin(positions[:, 1], ys[[0, -1]])
        in_area = ((positions >= (area.x_min, area.y_min))
                   & (positions <= (area.x_max, area.y_max))).all(axis=1)
        low_w, high_w = scenario.training.jammer_power_range_w
        low_db, high_db = 10.0 * math.log10(low_w), 10.0 * math.log10(high_w)
        nominal_db = _spaced(low_db - POWER_SEARCH_DB, high_db + POWER_SEARCH_DB,
                             COARSE_POWER_STEP_DB)
        middle = int(np.abs(nominal_db - (low_db + high_db) / 2.0).argmin())
        return cls(positions, on_edge, in_area, nominal_db + scenario.jammer.efficiency_db,
                   middle)


def _spaced(low: float, high: float, step: float) -> np.ndarray:
    """From ``low`` to at least ``high`` every ``step``, centred on the span."""
    count = math.ceil((high - low) / step - 1e-9) + 1
    return (low + high) / 2.0 + step * (np.arange(count) - (count - 1) / 2.0)


def _square_grid(center: np.ndarray, half_width: float) -> np.ndarray:
    offsets = np.linspace(-half_width, half_width, FINE_NODES)
    return np.stack(np.meshgrid(center[0] + offsets, center[1] + offsets), -1).reshape(-1, 2)


def corrected_levels(
    scenario: Scenario,
    no_jammer_levels_at: Callable[[np.ndarray], np.ndarray],
    jammer: JammerEstimate | JammerHypotheses,
    xy: np.ndarray,
    *,
    shadowing_sigma_db: float | None = None,
) -> np.ndarray:
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
    what the map's probabilities read there (``_prior_of_map``), where in the band; the estimated
    jammer takes the ideal model's loss off it. ``report_sigma_db`` widens that spread for
    what a receiver reports rather than what is there. The map was learned from
    measurements and so carries the GBS shadowing; the ideal model's own levels do not
    (they agree with the world on ~61 % of icc2021-shadowed), so taking them where the jammer
    matters loses more than it corrects. ``no_jammer_levels_at`` maps points (m, 2) to
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
    of ``_ReportTables``."""
    losses = _IdealLosses(scenario, xy)
    sd_db = np.hypot(belief.sd_db, report_sigma_db)
    half_step = scenario.uav.report_step_db / 2.0
    total = 0.0
    for estimate, weight in _weighted(jammer):
        mean_db = belief.mean_db - losses.loss_db(estimate)
        total = total + weight * np.exp(_log_band_probability(
            (reported_db - half_step - mean_db) / sd_db,
            (reported_db + half_step - mean_db) / sd_db))
    outlier = OUTLIER_SHARE * scenario.uav.report_step_db / _OUTLIER_SPAN_DB
    return (1.0 - OUTLIER_SHARE) * total + outlier


def ideal_model_spread_db(scenario: Scenario, survey_sigma_db: float) -> float | None:
    """How far a report may lie from the ideal model's SINR where the survey map agrees with
    that model: the survey map's fitted departure from it (``fit_shadowing_sigma``) and the
    receivers' noise (their datasheet's, ``uav.measurement_noise_db``). None where that
    spread is over half the narrowest level band: the model then cannot tell a level from
    its neighbour, and every report would look probable by it (icc2021-shadowed: 6.4 dB
    against a 0.8 dB band; icc2021: 0.03 dB)."""
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
                   for estimate, weight in zip(jammer.estimates, jammer.weights.tolist(),
                                               strict=True))
    radio = RadioModel(scenario, shadowed=False)
    params = None if jammer is None or not jammer.present else _params_of(scenario, jammer)
    sinr_db = radio.evaluate(np.asarray(xy, dtype=np.float64), params).sinr_db[:, None]
    lower_db, upper_db = _band_edges(radio, np.arange(scenario.channel.level_count))
    with np.errstate(invalid="ignore"):
        return np.exp(_log_band_probability((lower_db - sinr_db) / spread_db,
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


def _params_of(scenario: Scenario, estimate: JammerEstimate) -> JammerParams:
    """The radio model's jammer for a present ``estimate`` (at the scenario's jammer height)."""
    return JammerParams(estimate.x, estimate.y, estimate.power_w, scenario.jammer.height_m)


def _map_at(scenario: Scenario, map_at: Callable[[np.ndarray], np.ndarray],
            xy: np.ndarray) -> np.ndarray:
    """The no-jammer map's probabilities of each level (n, levels) at points ``xy`` (..., 2),
    from ``map_at``'s levels or probabilities."""
    return _level_probabilities(map_at(xy.reshape(-1, 2)), scenario.channel.level_count)


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
    band_low, band_high = _band_edges(radio, base)
    if shadowing_sigma_db is None:
        shadowing_sigma_db = _fitted_sigma(ideal_db, band_low, band_high)
    prior_db, prior_sd_db = _prior_of_map(radio, ideal_db, shadowing_sigma_db, no_jammer)
    sd_db = np.hypot(prior_sd_db, report_sigma_db)
    bounds = np.concatenate([[-np.inf], radio.level_edges_db, [np.inf]])[:, None]
    total = 0.0
    for estimate, weight in weighted:
        # With no jammer no loss: what the map says, as a receiver reports it.
        loss_db = losses.loss_db(estimate)
        # Level k needs the no-jammer SINR in [bounds_k + loss, bounds_k+1 + loss) and its band.
        low = np.maximum(band_low, bounds[:-1] + loss_db)
        high = np.minimum(band_high, bounds[1:] + loss_db)
        log_mass = _log_band_probability((low - prior_db) / sd_db, (high - prior_db) / sd_db)
        mass = np.exp(log_mass - log_mass.max(axis=0))
        total = total + weight * (mass / mass.sum(axis=0)).T
    return total
